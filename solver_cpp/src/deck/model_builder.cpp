// Deck keywords -> Model. One handler per keyword, registered in one table
// (ModelBuilder::handlers), each checking its parameters and data where they are
// read, so that every error names the line that caused it and says the fix.
// This file: the Model's lookups, the keyword table and build(), the checks and lookups the handlers share, and
// the whole-model checks; the handlers are in the files of their keyword families (see model_builder.hpp).
#include "deck/build_model.hpp"
#include "deck/model_builder.hpp"
#include "element/triangle.hpp"
#include "material/material.hpp"

#include <algorithm>
#include <cmath>
#include <string>
#include <utility>

namespace calfit {

int Model::surface(const std::string& name) const {
  const auto it = std::find(surface_names.begin(), surface_names.end(), upper(name));
  return it == surface_names.end() ? -1 : static_cast<int>(it - surface_names.begin());
}

namespace {
// Index of the first item whose name is `name` (upper-cased), -1 when none.
template <typename Items>
int index_by_name(const Items& items, const std::string& name) {
  const std::string key = upper(name);
  const auto it = std::find_if(items.begin(), items.end(), [&](const auto& item) { return item.name == key; });
  return it == items.end() ? -1 : static_cast<int>(it - items.begin());
}
}  // namespace

int Model::material(const std::string& name) const { return index_by_name(materials, name); }

int Model::profile(const std::string& name) const { return index_by_name(profiles, name); }

ParameterState Model::parameter_state() const {
  return {materials, profiles, gap_profiles, steps.empty() ? LoadState{} : steps.back().loads, {}, {}};
}

int Model::gap_profile(int surface_index) const {
  for (std::size_t k = 0; k < gap_profiles.size(); ++k)
    if (gap_profiles[k].surface == surface_index) return static_cast<int>(k);
  return -1;
}

std::vector<int> Model::surface_nodes(int surface_index) const {
  std::vector<int> nodes;
  for (const Face& f : surfaces[surface_index]) {
    const ElementDef& e = elements[f.element];
    for (int local : face_nodes(e.shape, f.face)) nodes.push_back(e.nodes[local]);
  }
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  return nodes;
}

Eigen::Vector2d Model::gap_center(const GapProfile& profile) const {
  if (profile.has_center) return profile.center;
  const std::vector<int> nodes = surface_nodes(profile.surface);
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  for (int n : nodes) center += coordinates[n];
  return center / static_cast<double>(std::max<std::size_t>(nodes.size(), 1));
}

double GapProfile::basis(int k, bool sine, const Eigen::Vector2d& X, const Eigen::Vector2d& about) {
  const double theta = std::atan2(X.y() - about.y(), X.x() - about.x());
  return sine ? std::sin(k * theta) : std::cos(k * theta);
}

double GapProfile::offset(const Eigen::Vector2d& X, const Eigen::Vector2d& about) const {
  double delta = 0.0;
  for (const auto& [k, ab] : harmonics) delta += ab.first * basis(k, false, X, about) + ab.second * basis(k, true, X, about);
  return delta;
}

namespace deck_building {

Model ModelBuilder::build() {
  const std::vector<KeywordBlock> blocks = read_deck(model_.deck_path);
  const std::map<std::string, Handler> table = handlers();
  for (const KeywordBlock& block : blocks) {
    const auto it = table.find(block.name);
    if (it == table.end()) throw DeckError(block.where, unknown_keyword_message(block.name));
    it->second(block);
  }
  finish(blocks.empty() ? SourceLocation{model_.deck_path, 0} : blocks.back().where);
  return std::move(model_);
}

std::map<std::string, ModelBuilder::Handler> ModelBuilder::handlers() {
  auto bind = [this](void (ModelBuilder::*fn)(const KeywordBlock&)) {
    return [this, fn](const KeywordBlock& b) { (this->*fn)(b); };
  };
  std::map<std::string, Handler> h = {
      {"HEADING", bind(&ModelBuilder::heading)},
      {"NODE", bind(&ModelBuilder::node)},
      {"ELEMENT", bind(&ModelBuilder::element)},
      {"NSET", bind(&ModelBuilder::node_set)},
      {"ELSET", bind(&ModelBuilder::element_set)},
      {"SURFACE", bind(&ModelBuilder::surface)},
      {"MATERIAL", bind(&ModelBuilder::material)},
      {"HYPERELASTIC", bind(&ModelBuilder::hyperelastic)},
      {"ELASTIC", bind(&ModelBuilder::elastic)},
      {"SOLID SECTION", bind(&ModelBuilder::solid_section)},
      {"BOUNDARY", bind(&ModelBuilder::boundary)},
      {"TENSION PROFILE", bind(&ModelBuilder::tension_profile)},
      {"STEP", bind(&ModelBuilder::step)},
      {"STATIC", bind(&ModelBuilder::static_procedure)},
      {"CLOAD", bind(&ModelBuilder::cload)},
      {"DLOAD", bind(&ModelBuilder::dload)},
      {"LAPLACE PRESSURE", bind(&ModelBuilder::laplace_pressure)},
      {"SENSITIVITY", bind(&ModelBuilder::sensitivity)},
      {"NODE PRINT", bind(&ModelBuilder::output_request)},
      {"NODE FILE", bind(&ModelBuilder::output_request)},
      {"EL PRINT", bind(&ModelBuilder::output_request)},
      {"EL FILE", bind(&ModelBuilder::output_request)},
      {"END STEP", bind(&ModelBuilder::end_step)},
  };
  h["SURFACE INTERACTION"] = bind(&ModelBuilder::surface_interaction);
  h["SURFACE BEHAVIOR"] = bind(&ModelBuilder::surface_behavior);
  h["FRICTION"] = bind(&ModelBuilder::friction);
  h["CONTACT PAIR"] = bind(&ModelBuilder::contact_pair);
  h["GAP PROFILE"] = bind(&ModelBuilder::gap_profile);
  h["MODEL CHANGE"] = bind(&ModelBuilder::model_change);
  h["VOLUME CHANGE"] = bind(&ModelBuilder::volume_change);
  h["AXIAL STRETCH"] = bind(&ModelBuilder::axial_stretch);
  h["RIGID MOTION"] = bind(&ModelBuilder::rigid_motion);
  return h;
}

std::string ModelBuilder::unknown_keyword_message(const std::string& name) {
  return "unknown keyword *" + name + " (see solver_cpp/README.md for the keywords calfit-fe reads)";
}

// ---- context checks -------------------------------------------------------
void ModelBuilder::model_data(const KeywordBlock& b) const {
  if (in_step_) throw DeckError(b.where, "*" + b.name + " is model data: put it before the first *STEP");
}
void ModelBuilder::step_data(const KeywordBlock& b) const {
  if (!in_step_) throw DeckError(b.where, "*" + b.name + " belongs inside a *STEP ... *END STEP block");
}
void ModelBuilder::no_data(const KeywordBlock& b) {
  if (!b.data.empty()) throw DeckError(b.data.front().where, "*" + b.name + " takes no data lines");
}
void ModelBuilder::needs_data(const KeywordBlock& b) {
  if (b.data.empty()) throw DeckError(b.where, "*" + b.name + " needs at least one data line");
}
void ModelBuilder::field_count(const DataLine& line, std::size_t min, std::size_t max, const std::string& what) {
  const std::size_t n = line.fields.size();
  if (n < min || n > max)
    throw DeckError(line.where, what + ": expected " + (min == max ? std::to_string(min)
                                                                    : std::to_string(min) + " to " + std::to_string(max)) +
                                    " values, found " + std::to_string(n));
}
void ModelBuilder::require(bool ok, const DataLine& line, const std::string& message) {
  if (!ok) throw DeckError(line.where, message);
}

// ---- lookups ----------------------------------------------------------------
int ModelBuilder::node(const std::string& text, const SourceLocation& where) const {
  const int id = to_int(text, where, "node number");
  const auto it = model_.node_index.find(id);
  if (it == model_.node_index.end()) throw DeckError(where, "node " + text + " is not defined (no *NODE line for it)");
  return it->second;
}
std::vector<int> ModelBuilder::nodes_of(const std::string& text, const SourceLocation& where) const {
  if (looks_like_int(text)) return {node(text, where)};
  const auto it = model_.node_sets.find(upper(text));
  if (it == model_.node_sets.end()) throw DeckError(where, "node set " + text + " is not defined (*NSET, NSET=" + text + ")");
  return it->second;
}
std::vector<int> ModelBuilder::elements_of(const std::string& text, const SourceLocation& where) const {
  if (looks_like_int(text)) {
    const int id = to_int(text, where, "element number");
    const auto it = model_.element_index.find(id);
    if (it == model_.element_index.end()) throw DeckError(where, "element " + text + " is not defined");
    return {it->second};
  }
  const auto it = model_.element_sets.find(upper(text));
  if (it == model_.element_sets.end())
    throw DeckError(where, "element set " + text + " is not defined (*ELSET, ELSET=" + text + ")");
  return it->second;
}
int ModelBuilder::dof_number(const std::string& text, const SourceLocation& where) {
  const int dof = to_int(text, where, "degree of freedom");
  if (dof < 1 || dof > 2)
    throw DeckError(where, "degree of freedom " + text + " does not exist in plane strain: use 1 (x) or 2 (y)");
  return dof - 1;
}
int ModelBuilder::face_label(const std::string& text, const std::string& prefix, const SourceLocation& where) {
  const std::string u = upper(text);
  if (u.size() == prefix.size() + 1 && u.compare(0, prefix.size(), prefix) == 0 && u.back() >= '1' && u.back() <= '3')
    return u.back() - '1';
  throw DeckError(where, "face label " + text + " is not valid for a triangle: use " + prefix + "1, " + prefix + "2 or " +
                             prefix + "3");
}

// ---- model data -----------------------------------------------------------
void ModelBuilder::heading(const KeywordBlock& b) {
  b.allow_only({});
  model_data(b);
}

// ---- whole-model checks -----------------------------------------------------
void ModelBuilder::finish(const SourceLocation& last) {
  check_material_complete();
  if (in_step_) throw DeckError(model_.steps.back().where, "this *STEP has no *END STEP");
  if (model_.coordinates.empty()) throw DeckError(last, "the deck defines no nodes (*NODE)");
  if (model_.elements.empty()) throw DeckError(last, "the deck defines no elements (*ELEMENT)");
  if (model_.steps.empty()) throw DeckError(last, "the deck defines no step: add *STEP, NLGEOM / *STATIC / *END STEP");
  for (const ElementDef& e : model_.elements) {
    if (e.section < 0)
      throw DeckError(e.where, "element " + std::to_string(e.id) + " has no *SOLID SECTION (put it in an ELSET with one)");
    const SectionDef& s = model_.sections[e.section];
    const MaterialDef& m = model_.materials[s.material];
    if (e.hybrid && !dynamic_cast<const SplitHyperelastic*>(m.law.get()))
      throw DeckError(s.where, "hybrid element " + e.type + " needs a *HYPERELASTIC material (with a volumetric "
                               "part); material " + m.name + " is *ELASTIC");
    if (!e.hybrid && m.law->incompressible())
      throw DeckError(s.where, "material " + m.name + " is incompressible (D = 0): displacement elements " + e.type +
                                   " cannot represent it; use the hybrid " + e.type + "H or give D1 > 0");
    check_geometry(e);
  }
  resolve_sensitivities();
}

}  // namespace deck_building

Model build_model(const std::string& path) { return deck_building::ModelBuilder(path).build(); }

}  // namespace calfit
