// Deck keywords -> Model. One handler per keyword, registered in one table
// (ModelBuilder::handlers), each checking its parameters and data where they are
// read, so that every error names the line that caused it and says the fix.
#include "deck/deck_reader.hpp"
#include "material/laws.hpp"
#include "model/model.hpp"
#include "model/parameters.hpp"
#include "element/solid_element.hpp"

#include <algorithm>
#include <cmath>
#include <functional>
#include <iomanip>
#include <set>
#include <sstream>

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

double TensionProfile::factor(double theta) const {
  if (type == Type::Fourier) {
    constexpr double kDegree = 3.14159265358979323846 / 180.0;
    double f = 1.0;
    for (const auto& [k, ab] : harmonics) f += ab.first * std::cos(k * theta * kDegree) + ab.second * std::sin(k * theta * kDegree);
    return f;
  }
  const auto& t = angle_factor;
  if (t.size() == 1) return t[0].second;
  theta = std::fmod(std::fmod(theta, 360.0) + 360.0, 360.0);
  for (std::size_t k = 0; k < t.size(); ++k) {
    const auto& a = t[k];
    const auto& b = t[(k + 1) % t.size()];
    const double span = k + 1 < t.size() ? b.first - a.first : b.first + 360.0 - a.first;
    double offset = theta - a.first;
    if (offset < 0) offset += 360.0;
    if (offset <= span) return a.second + (b.second - a.second) * (span > 0 ? offset / span : 0.0);
  }
  return t.back().second;
}

double TensionProfile::minimum_factor(double* at_degrees) const {
  // Sample finely enough to bracket every minimum (16 points per period of the highest
  // harmonic), then refine the smallest sample by golden section within its bracket.
  const int k_max = harmonics.empty() ? 1 : harmonics.rbegin()->first;
  const int n = std::max(720, 16 * k_max);
  const double spacing = 360.0 / n;
  int best = 0;
  for (int i = 1; i < n; ++i)
    if (factor(i * spacing) < factor(best * spacing)) best = i;
  double lo = (best - 1) * spacing, hi = (best + 1) * spacing;
  const double ratio = 0.5 * (std::sqrt(5.0) - 1.0);
  for (int it = 0; it < 60; ++it) {
    const double a = hi - ratio * (hi - lo), b = lo + ratio * (hi - lo);
    if (factor(a) < factor(b)) {
      hi = b;
    } else {
      lo = a;
    }
  }
  const double angle = std::fmod(0.5 * (lo + hi) + 360.0, 360.0);
  if (at_degrees) *at_degrees = angle;
  return std::min(factor(angle), factor(best * spacing));
}

ParameterState Model::parameter_state() const {
  return {materials, profiles, steps.empty() ? LoadState{} : steps.back().loads};
}

namespace {

// CalculiX *STATIC: the default minimum time increment is this fraction of the step's period (or the initial
// increment, if smaller).
constexpr double kMinIncrementFraction = 1e-5;

struct Context {
  const DataLine& line;
  std::size_t field_count() const { return line.fields.size(); }
  const std::string& field(std::size_t i, const std::string& what) const {
    if (i >= line.fields.size() || line.fields[i].empty()) throw DeckError(line.where, what + " is missing");
    return line.fields[i];
  }
  double number(std::size_t i, const std::string& what) const { return to_double(field(i, what), line.where, what); }
  int integer(std::size_t i, const std::string& what) const { return to_int(field(i, what), line.where, what); }
};

class ModelBuilder {
public:
  explicit ModelBuilder(const std::string& path) { model_.deck_path = path; }

  Model build() {
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

private:
  using Handler = std::function<void(const KeywordBlock&)>;
  Model model_;
  int current_material_ = -1;
  bool material_has_law_ = false;
  bool in_step_ = false;
  bool step_has_static_ = false;
  LoadState loads_;                 // state carried from step to step
  std::vector<DataLine> sensitivity_lines_;  // resolved once the whole model is known
  std::map<int, double> model_bcs_;  // *BOUNDARY given before the first step

  std::map<std::string, Handler> handlers() {
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
    h["MODEL CHANGE"] = bind(&ModelBuilder::model_change);
    h["VOLUME CHANGE"] = bind(&ModelBuilder::volume_change);
    h["AXIAL STRETCH"] = bind(&ModelBuilder::axial_stretch);
    h["RIGID MOTION"] = bind(&ModelBuilder::rigid_motion);
    return h;
  }

  static std::string unknown_keyword_message(const std::string& name) {
    return "unknown keyword *" + name + " (see solver_cpp/README.md for the keywords calfit-fe reads)";
  }

  // ---- context checks -------------------------------------------------------
  void model_data(const KeywordBlock& b) const {
    if (in_step_) throw DeckError(b.where, "*" + b.name + " is model data: put it before the first *STEP");
  }
  void step_data(const KeywordBlock& b) const {
    if (!in_step_) throw DeckError(b.where, "*" + b.name + " belongs inside a *STEP ... *END STEP block");
  }
  static void no_data(const KeywordBlock& b) {
    if (!b.data.empty()) throw DeckError(b.data.front().where, "*" + b.name + " takes no data lines");
  }
  static void needs_data(const KeywordBlock& b) {
    if (b.data.empty()) throw DeckError(b.where, "*" + b.name + " needs at least one data line");
  }
  static void field_count(const DataLine& line, std::size_t min, std::size_t max, const std::string& what) {
    const std::size_t n = line.fields.size();
    if (n < min || n > max)
      throw DeckError(line.where, what + ": expected " + (min == max ? std::to_string(min)
                                                                      : std::to_string(min) + " to " + std::to_string(max)) +
                                      " values, found " + std::to_string(n));
  }

  // ---- lookups ----------------------------------------------------------------
  int node(const std::string& text, const SourceLocation& where) const {
    const int id = to_int(text, where, "node number");
    const auto it = model_.node_index.find(id);
    if (it == model_.node_index.end()) throw DeckError(where, "node " + text + " is not defined (no *NODE line for it)");
    return it->second;
  }
  std::vector<int> nodes_of(const std::string& text, const SourceLocation& where) const {
    if (looks_like_int(text)) return {node(text, where)};
    const auto it = model_.node_sets.find(upper(text));
    if (it == model_.node_sets.end()) throw DeckError(where, "node set " + text + " is not defined (*NSET, NSET=" + text + ")");
    return it->second;
  }
  std::vector<int> elements_of(const std::string& text, const SourceLocation& where) const {
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
  static int dof_number(const std::string& text, const SourceLocation& where) {
    const int dof = to_int(text, where, "degree of freedom");
    if (dof < 1 || dof > 2)
      throw DeckError(where, "degree of freedom " + text + " does not exist in plane strain: use 1 (x) or 2 (y)");
    return dof - 1;
  }
  static int face_label(const std::string& text, const std::string& prefix, const SourceLocation& where) {
    const std::string u = upper(text);
    if (u.size() == prefix.size() + 1 && u.compare(0, prefix.size(), prefix) == 0 && u.back() >= '1' && u.back() <= '3')
      return u.back() - '1';
    throw DeckError(where, "face label " + text + " is not valid for a triangle: use " + prefix + "1, " + prefix + "2 or " +
                               prefix + "3");
  }

  // ---- model data -----------------------------------------------------------
  void heading(const KeywordBlock& b) {
    b.allow_only({});
    model_data(b);
  }

  void node(const KeywordBlock& b) {
    b.allow_only({"NSET"});
    model_data(b);
    needs_data(b);
    const std::optional<std::string> set = b.value("NSET");
    for (const DataLine& line : b.data) {
      field_count(line, 3, 4, "*NODE data line (id, x, y[, z])");
      Context c{line};
      const int id = c.integer(0, "node number");
      if (id <= 0) throw DeckError(line.where, "node number must be positive, found " + std::to_string(id));
      if (model_.node_index.count(id)) throw DeckError(line.where, "node " + std::to_string(id) + " is defined twice");
      const int index = static_cast<int>(model_.coordinates.size());
      model_.node_index[id] = index;
      model_.node_ids.push_back(id);
      model_.coordinates.emplace_back(c.number(1, "x coordinate"), c.number(2, "y coordinate"));
      if (c.field_count() == 4) c.number(3, "z coordinate");
      if (set) model_.node_sets[upper(*set)].push_back(index);
    }
  }

  void element(const KeywordBlock& b) {
    b.allow_only({"TYPE", "ELSET"});
    model_data(b);
    needs_data(b);
    const std::string type = upper(b.required("TYPE"));
    ElementShape shape;
    if (type == "CPE3" || type == "CPE3H") {
      shape = ElementShape::T3;
    } else if (type == "CPE6" || type == "CPE6H") {
      shape = ElementShape::T6;
    } else {
      throw DeckError(b.where, "unknown element type " + type +
                                   ": calfit-fe is plane strain (TYPE=CPE3, CPE6, or the hybrid CPE3H, CPE6H)");
    }
    const bool hybrid = type.back() == 'H';
    const std::size_t n = static_cast<std::size_t>(node_count(shape));
    const std::optional<std::string> set = b.value("ELSET");
    for (const DataLine& line : b.data) {
      field_count(line, n + 1, n + 1, "*ELEMENT, TYPE=" + type + " data line (id and " + std::to_string(n) + " nodes)");
      Context c{line};
      ElementDef e;
      e.id = c.integer(0, "element number");
      if (e.id <= 0) throw DeckError(line.where, "element number must be positive");
      if (model_.element_index.count(e.id))
        throw DeckError(line.where, "element " + std::to_string(e.id) + " is defined twice");
      e.shape = shape;
      e.type = type;
      e.hybrid = hybrid;
      e.where = line.where;
      for (std::size_t k = 1; k <= n; ++k) e.nodes.push_back(node(line.fields[k], line.where));
      if (std::set<int>(e.nodes.begin(), e.nodes.end()).size() != n)
        throw DeckError(line.where, "element " + std::to_string(e.id) + " lists the same node twice");
      const int index = static_cast<int>(model_.elements.size());
      model_.element_index[e.id] = index;
      model_.elements.push_back(std::move(e));
      if (set) model_.element_sets[upper(*set)].push_back(index);
    }
  }

  template <typename Resolve>
  void fill_set(const KeywordBlock& b, std::vector<int>& target, Resolve resolve, const std::string& item) {
    needs_data(b);
    for (const DataLine& line : b.data) {
      if (b.flag("GENERATE")) {
        field_count(line, 2, 3, "GENERATE data line (first, last[, increment])");
        Context c{line};
        const int first = c.integer(0, "first " + item), last = c.integer(1, "last " + item);
        const int step = c.field_count() == 3 ? c.integer(2, "increment") : 1;
        if (step <= 0 || last < first) throw DeckError(line.where, "GENERATE needs first <= last and a positive increment");
        for (int id = first; id <= last; id += step) {
          const std::vector<int> found = resolve(std::to_string(id), line.where);
          target.insert(target.end(), found.begin(), found.end());
        }
        continue;
      }
      for (const std::string& f : line.fields) {
        if (f.empty()) continue;
        const std::vector<int> found = resolve(f, line.where);
        target.insert(target.end(), found.begin(), found.end());
      }
    }
  }

  void node_set(const KeywordBlock& b) {
    b.allow_only({"NSET", "GENERATE"});
    model_data(b);
    std::vector<int>& target = model_.node_sets[upper(b.required("NSET"))];
    fill_set(b, target, [this](const std::string& t, const SourceLocation& w) { return nodes_of(t, w); }, "node");
  }

  void element_set(const KeywordBlock& b) {
    b.allow_only({"ELSET", "GENERATE"});
    model_data(b);
    std::vector<int>& target = model_.element_sets[upper(b.required("ELSET"))];
    fill_set(b, target, [this](const std::string& t, const SourceLocation& w) { return elements_of(t, w); }, "element");
  }

  void surface(const KeywordBlock& b) {
    b.allow_only({"NAME", "TYPE"});
    model_data(b);
    needs_data(b);
    const std::string type = upper(b.value("TYPE").value_or("ELEMENT"));
    if (type != "ELEMENT") throw DeckError(b.where, "*SURFACE, TYPE=" + type + " is not supported: use TYPE=ELEMENT");
    const std::string name = upper(b.required("NAME"));
    if (model_.surface(name) >= 0) throw DeckError(b.where, "surface " + name + " is defined twice");
    std::vector<Face> faces;
    for (const DataLine& line : b.data) {
      field_count(line, 2, 2, "*SURFACE data line (element or element set, face S1..S3)");
      const int face = face_label(line.fields[1], "S", line.where);
      for (int e : elements_of(line.fields[0], line.where)) faces.push_back({e, face});
    }
    model_.surface_names.push_back(name);
    model_.surfaces.push_back(std::move(faces));
  }

  void material(const KeywordBlock& b) {
    b.allow_only({"NAME"});
    model_data(b);
    no_data(b);
    check_material_complete();
    current_interaction_ = -1;
    const std::string name = upper(b.required("NAME"));
    if (model_.material(name) >= 0) throw DeckError(b.where, "material " + name + " is defined twice");
    model_.materials.push_back({name, nullptr, {}, b.where});
    current_material_ = static_cast<int>(model_.materials.size()) - 1;
    material_has_law_ = false;
  }

  void check_material_complete() const {
    if (current_material_ >= 0 && !material_has_law_) {
      const MaterialDef& m = model_.materials[current_material_];
      throw DeckError(m.where, "material " + m.name + " has no *HYPERELASTIC or *ELASTIC data");
    }
  }

  const DataLine& single_data_line(const KeywordBlock& b) {
    if (current_material_ < 0) throw DeckError(b.where, "*" + b.name + " must follow a *MATERIAL keyword");
    if (material_has_law_)
      throw DeckError(b.where, "material " + model_.materials[current_material_].name + " already has a constitutive law");
    needs_data(b);
    if (b.data.size() > 1)
      throw DeckError(b.data[1].where, "temperature-dependent material data is not supported: give one data line");
    return b.data.front();
  }

  static void require(bool ok, const DataLine& line, const std::string& message) {
    if (!ok) throw DeckError(line.where, message);
  }

  // Checks nothing: the caller checked the constants where it read them.
  void set_law(LawConstants constants) {
    MaterialDef& m = model_.materials[current_material_];
    m.law = make_law(constants);
    m.constants = std::move(constants);
    material_has_law_ = true;
  }

  // The data line of a law, read into its named constants (law_constant_names order); the
  // last `optional` constants may be left off the line and are then 0 (AVRIL's C20).
  static LawConstants read_constants(const DataLine& line, const std::string& law, int order, const std::string& what,
                                     std::size_t optional = 0) {
    LawConstants c{law, law_constant_names(law, order), {}};
    field_count(line, c.names.size() - optional, c.names.size(), what);
    for (std::size_t i = 0; i < c.names.size(); ++i)
      c.values.push_back(i < line.fields.size() ? Context{line}.number(i, c.names[i]) : 0.0);
    return c;
  }

  void hyperelastic(const KeywordBlock& b) {
    model_data(b);
    const DataLine& line = single_data_line(b);
    std::string law = "NEO HOOKE";
    int n = 1;
    for (const Parameter& p : b.parameters) {
      if (p.name == "N") {
        n = to_int(p.value, b.where, "N");
        if (n < 1 || n > 3) throw DeckError(b.where, "REDUCED POLYNOMIAL needs N = 1, 2 or 3");
      } else if (p.name == "NEO HOOKE" || p.name == "MOONEY-RIVLIN" || p.name == "REDUCED POLYNOMIAL" ||
                 p.name == "ARRUDA-BOYCE" || p.name == "AVRIL") {
        law = p.name;
      } else {
        throw DeckError(b.where, "unknown parameter " + p.name +
                                     " on *HYPERELASTIC (calfit-fe reads NEO HOOKE, MOONEY-RIVLIN, REDUCED "
                                     "POLYNOMIAL with N=, ARRUDA-BOYCE, AVRIL)");
      }
    }
    auto nonneg = [&](double d, const std::string& name) { require(d >= 0.0, line, name + " must be >= 0 (0 means incompressible)"); };
    if (law == "NEO HOOKE") {
      const LawConstants c = read_constants(line, law, 1, "*HYPERELASTIC, NEO HOOKE data (C10, D1)");
      require(c.values[0] > 0.0, line, "C10 must be > 0");
      nonneg(c.values[1], "D1");
      set_law(c);
    } else if (law == "MOONEY-RIVLIN") {
      const LawConstants c = read_constants(line, law, 1, "*HYPERELASTIC, MOONEY-RIVLIN data (C10, C01, D1)");
      require(c.values[0] + c.values[1] > 0.0, line, "C10 + C01 (the initial shear modulus / 2) must be > 0");
      nonneg(c.values[2], "D1");
      set_law(c);
    } else if (law == "REDUCED POLYNOMIAL") {
      const LawConstants c = read_constants(line, law, n, "*HYPERELASTIC, REDUCED POLYNOMIAL, N=" + std::to_string(n) +
                                                              " data (C10..CN0, D1..DN)");
      for (int i = 0; i < n; ++i) nonneg(c.values[static_cast<std::size_t>(n + i)], "D" + std::to_string(i + 1));
      require(c.values[0] > 0.0, line, "C10 must be > 0");
      set_law(c);
    } else if (law == "ARRUDA-BOYCE") {
      const LawConstants c = read_constants(line, law, 1, "*HYPERELASTIC, ARRUDA-BOYCE data (mu, lambda_m, D)");
      require(c.values[0] > 0.0, line, "mu must be > 0");
      require(c.values[1] >= 1.0, line, "lambda_m (locking stretch) must be >= 1");
      nonneg(c.values[2], "D");
      set_law(c);
    } else {  // AVRIL, with the optional C20 (I1bar - 3)^2 of the `stiffening` effect (0 when not given)
      const LawConstants c = read_constants(line, law, 1, "*HYPERELASTIC, AVRIL data (C10, Kv[, C20])", 1);
      require(c.values[0] > 0.0, line, "C10 must be > 0");
      require(c.values[1] > 0.0, line, "Kv must be > 0");
      require(c.values[2] >= 0.0, line, "C20 must be >= 0 (it stiffens the law at large strain; 0 drops the term)");
      set_law(c);
    }
  }

  void elastic(const KeywordBlock& b) {
    b.allow_only({"TYPE"});
    model_data(b);
    const std::string type = upper(b.value("TYPE").value_or("ISO"));
    if (type != "ISO") throw DeckError(b.where, "*ELASTIC, TYPE=" + type + " is not supported: use TYPE=ISO");
    const DataLine& line = single_data_line(b);
    const LawConstants c = read_constants(line, "ELASTIC", 1, "*ELASTIC data (E, nu)");
    require(c.values[0] > 0.0, line, "Young's modulus E must be > 0");
    require(c.values[1] > -1.0 && c.values[1] < 0.5, line, "Poisson's ratio must lie in (-1, 0.5)");
    set_law(c);
  }

  void solid_section(const KeywordBlock& b) {
    b.allow_only({"ELSET", "MATERIAL", "INTEGRATION"});
    model_data(b);
    check_material_complete();
    SectionDef s;
    s.where = b.where;
    const std::string material = upper(b.required("MATERIAL"));
    s.material = model_.material(material);
    if (s.material < 0) throw DeckError(b.where, "material " + material + " is not defined (*MATERIAL, NAME=" + material + ")");
    const std::string integration = upper(b.value("INTEGRATION").value_or("REDUCED"));
    if (integration != "FULL" && integration != "REDUCED")
      throw DeckError(b.where, "INTEGRATION must be FULL or REDUCED");
    s.full_integration = integration == "FULL";
    if (b.data.size() > 1) throw DeckError(b.data[1].where, "*SOLID SECTION takes at most one data line (thickness)");
    if (!b.data.empty() && !b.data[0].fields.empty()) {
      s.thickness = Context{b.data[0]}.number(0, "thickness");
      require(s.thickness > 0.0, b.data[0], "thickness must be > 0");
    }
    const int index = static_cast<int>(model_.sections.size());
    model_.sections.push_back(s);
    for (int e : elements_of(b.required("ELSET"), b.where)) {
      ElementDef& el = model_.elements[e];
      if (el.section >= 0)
        throw DeckError(b.where, "element " + std::to_string(el.id) + " is already in another *SOLID SECTION");
      el.section = index;
    }
  }

  template <typename Map>
  static void apply_op(const KeywordBlock& b, Map& target) {
    const std::string op = upper(b.value("OP").value_or("MOD"));
    if (op == "NEW") {
      target.clear();
    } else if (op != "MOD") {
      throw DeckError(b.where, "OP must be MOD or NEW");
    }
  }

  void boundary(const KeywordBlock& b) {
    b.allow_only({"OP"});
    needs_data(b);
    std::map<int, double>& target = in_step_ ? loads_.prescribed : model_bcs_;
    if (in_step_) apply_op(b, target);
    for (const DataLine& line : b.data) {
      field_count(line, 2, 4, "*BOUNDARY data line (node or set, first dof[, last dof[, value]])");
      Context c{line};
      const int first = dof_number(line.fields[1], line.where);
      const int last = c.field_count() >= 3 && !line.fields[2].empty() ? dof_number(line.fields[2], line.where) : first;
      if (last < first) throw DeckError(line.where, "last dof is smaller than first dof");
      const double value = c.field_count() == 4 ? c.number(3, "prescribed value") : 0.0;
      if (!in_step_ && value != 0.0)
        throw DeckError(line.where, "a nonzero prescribed value belongs inside a *STEP (model-level *BOUNDARY fixes to 0)");
      for (int n : nodes_of(line.fields[0], line.where)) {
        if (in_step_) check_not_rigid(n, line.where);
        for (int d = first; d <= last; ++d) target[2 * n + d] = value;
      }
    }
  }

  void tension_profile(const KeywordBlock& b) {
    b.allow_only({"NAME", "TYPE", "CX", "CY"});
    model_data(b);
    TensionProfile p;
    p.name = upper(b.required("NAME"));
    p.where = b.where;
    const std::string type = upper(b.value("TYPE").value_or("TABLE"));
    if (type != "TABLE" && type != "FOURIER") throw DeckError(b.where, "*TENSION PROFILE, TYPE=" + type + " is not known: use TABLE or FOURIER");
    p.type = type == "FOURIER" ? TensionProfile::Type::Fourier : TensionProfile::Type::Table;
    const auto cx = b.value("CX"), cy = b.value("CY");
    if (cx.has_value() != cy.has_value()) throw DeckError(b.where, "give both CX= and CY= (or neither)");
    if (cx) {
      p.has_center = true;
      p.center = {to_double(*cx, b.where, "CX"), to_double(*cy, b.where, "CY")};
    }
    if (model_.profile(p.name) >= 0) throw DeckError(b.where, "tension profile " + p.name + " is defined twice");
    if (p.type == TensionProfile::Type::Fourier) {
      read_fourier_profile(b, p);
    } else {
      read_table_profile(b, p);
    }
    model_.profiles.push_back(p);
  }

  static void read_table_profile(const KeywordBlock& b, TensionProfile& p) {
    needs_data(b);
    for (const DataLine& line : b.data) {
      field_count(line, 2, 2, "*TENSION PROFILE data line (angle in degrees, factor)");
      Context c{line};
      const double angle = c.number(0, "angle"), factor = c.number(1, "factor");
      require(angle >= 0.0 && angle < 360.0, line, "angle must lie in [0, 360) degrees");
      require(factor >= 0.0, line, "tension factor must be >= 0");
      if (!p.angle_factor.empty() && angle <= p.angle_factor.back().first)
        throw DeckError(line.where, "angles must increase from line to line");
      p.angle_factor.emplace_back(angle, factor);
    }
  }

  // TYPE=FOURIER: data lines k, a_k, b_k (none: a uniform tension whose coefficients
  // *SENSITIVITY may still ask about); the factor must stay > 0 all around.
  static void read_fourier_profile(const KeywordBlock& b, TensionProfile& p) {
    for (const DataLine& line : b.data) {
      field_count(line, 3, 3, "*TENSION PROFILE, TYPE=FOURIER data line (k, a_k, b_k)");
      Context c{line};
      const int k = c.integer(0, "harmonic number k");
      require(k >= 1, line, "harmonic number k must be >= 1 (the constant term is the TENSION itself)");
      if (p.harmonics.count(k)) throw DeckError(line.where, "harmonic " + std::to_string(k) + " is listed twice");
      p.harmonics[k] = {c.number(1, "a_k"), c.number(2, "b_k")};
    }
    double angle = 0.0;
    const double smallest = p.minimum_factor(&angle);
    if (!(smallest > 0.0)) {
      std::ostringstream where;
      where << std::setprecision(4) << smallest << " at " << angle;
      throw DeckError(b.where, "the tension factor 1 + sum_k (a_k cos k theta + b_k sin k theta) of profile " + p.name +
                                   " falls to " + where.str() + " degrees: it must stay > 0 all around");
    }
  }

  // ---- contact ------------------------------------------------------------------
  int current_interaction_ = -1;

  void surface_interaction(const KeywordBlock& b) {
    b.allow_only({"NAME"});
    model_data(b);
    no_data(b);
    check_material_complete();
    current_material_ = -1;
    InteractionDef def;
    def.name = upper(b.required("NAME"));
    def.where = b.where;
    for (const InteractionDef& other : model_.interactions)
      if (other.name == def.name) throw DeckError(b.where, "surface interaction " + def.name + " is defined twice");
    model_.interactions.push_back(def);
    current_interaction_ = static_cast<int>(model_.interactions.size()) - 1;
  }

  InteractionDef& interaction_for(const KeywordBlock& b) {
    if (current_interaction_ < 0) throw DeckError(b.where, "*" + b.name + " must follow a *SURFACE INTERACTION keyword");
    return model_.interactions[current_interaction_];
  }

  void surface_behavior(const KeywordBlock& b) {
    b.allow_only({"PRESSURE-OVERCLOSURE"});
    model_data(b);
    InteractionDef& def = interaction_for(b);
    const std::string law = upper(b.required("PRESSURE-OVERCLOSURE"));
    if (law != "LINEAR")
      throw DeckError(b.where, "PRESSURE-OVERCLOSURE=" + law + " is not supported: calfit-fe reads LINEAR (penalty)");
    needs_data(b);
    if (b.data.size() > 1) throw DeckError(b.data[1].where, "*SURFACE BEHAVIOR takes one data line");
    const DataLine& line = b.data[0];
    // sigma_inf and c0 (CalculiX's tension branch for open gaps) are read for
    // compatibility; calfit-fe models no adhesion, so they must not ask for it.
    field_count(line, 1, 3, "*SURFACE BEHAVIOR data (K[, sigma_inf, c0])");
    def.law.penalty = Context{line}.number(0, "slope K");
    require(def.law.penalty > 0.0, line, "the penalty slope K must be > 0");
    def.has_behavior = true;
  }

  void friction(const KeywordBlock& b) {
    b.allow_only({});
    model_data(b);
    InteractionDef& def = interaction_for(b);
    needs_data(b);
    const DataLine& line = b.data[0];
    field_count(line, 2, 2, "*FRICTION data (mu, stick slope lambda)");
    Context c{line};
    def.law.friction = c.number(0, "friction coefficient mu");
    def.law.stick_slope = c.number(1, "stick slope lambda");
    require(def.law.friction >= 0.0, line, "mu must be >= 0");
    require(def.law.stick_slope > 0.0, line, "the stick slope must be > 0 (traction per unit slip)");
  }

  int surface_named(const std::string& name, const SourceLocation& where) const {
    const int s = model_.surface(name);
    if (s < 0) throw DeckError(where, "surface " + name + " is not defined (*SURFACE, NAME=" + name + ")");
    return s;
  }

  void contact_pair(const KeywordBlock& b) {
    b.allow_only({"INTERACTION", "TYPE"});
    model_data(b);
    const std::string type = upper(b.value("TYPE").value_or("NODE TO SURFACE"));
    if (type != "NODE TO SURFACE" && type != "SURFACE TO SURFACE")
      throw DeckError(b.where, "TYPE=" + type + " is not supported: use NODE TO SURFACE or SURFACE TO SURFACE");
    const std::string name = upper(b.required("INTERACTION"));
    int interaction = -1;
    for (std::size_t k = 0; k < model_.interactions.size(); ++k)
      if (model_.interactions[k].name == name) interaction = static_cast<int>(k);
    if (interaction < 0)
      throw DeckError(b.where, "surface interaction " + name + " is not defined (*SURFACE INTERACTION, NAME=" + name + ")");
    if (!model_.interactions[interaction].has_behavior)
      throw DeckError(b.where, "surface interaction " + name + " has no *SURFACE BEHAVIOR (the penalty slope)");
    needs_data(b);
    for (const DataLine& line : b.data) {
      field_count(line, 2, 2, "*CONTACT PAIR data line (slave surface, master surface)");
      ContactPairDef pair;
      pair.slave = surface_named(line.fields[0], line.where);
      pair.master = surface_named(line.fields[1], line.where);
      pair.interaction = interaction;
      pair.where = line.where;
      if (pair.slave == pair.master) throw DeckError(line.where, "a surface cannot be in contact with itself");
      model_.contact_pairs.push_back(pair);
      loads_.contact_active.push_back(1);
    }
  }

  void model_change(const KeywordBlock& b) {
    b.allow_only({"TYPE", "ADD", "REMOVE"});
    step_data(b);
    const std::string type = upper(b.required("TYPE"));
    if (type != "CONTACT PAIR") throw DeckError(b.where, "*MODEL CHANGE, TYPE=" + type + " is not supported (TYPE=CONTACT PAIR)");
    if (b.flag("ADD") == b.flag("REMOVE")) throw DeckError(b.where, "*MODEL CHANGE needs exactly one of ADD or REMOVE");
    needs_data(b);
    for (const DataLine& line : b.data) {
      field_count(line, 2, 2, "*MODEL CHANGE data line (slave surface, master surface)");
      const int slave = surface_named(line.fields[0], line.where), master = surface_named(line.fields[1], line.where);
      bool found = false;
      for (std::size_t k = 0; k < model_.contact_pairs.size(); ++k)
        if (model_.contact_pairs[k].slave == slave && model_.contact_pairs[k].master == master) {
          loads_.contact_active[k] = b.flag("ADD") ? 1 : 0;
          found = true;
        }
      if (!found) throw DeckError(line.where, "no *CONTACT PAIR joins " + line.fields[0] + " and " + line.fields[1]);
    }
  }

  // ---- steps ------------------------------------------------------------------
  void step(const KeywordBlock& b) {
    b.allow_only({"NLGEOM", "INC"});
    if (in_step_) throw DeckError(b.where, "*STEP inside a step: close the previous one with *END STEP");
    no_data(b);
    check_material_complete();
    current_material_ = -1;
    current_interaction_ = -1;
    const Parameter* nlgeom = b.find("NLGEOM");
    if (!nlgeom || (nlgeom->has_value && upper(nlgeom->value) != "YES"))
      throw DeckError(b.where, "calfit-fe solves finite strain only: write *STEP, NLGEOM");
    if (model_.steps.empty())
      for (const auto& [dof, value] : model_bcs_) loads_.prescribed[dof] = value;
    StepDef s;
    s.where = b.where;
    if (const auto inc = b.value("INC")) {
      s.max_increments = to_int(*inc, b.where, "INC");
      if (s.max_increments < 1) throw DeckError(b.where, "INC must be >= 1");
    }
    model_.steps.push_back(s);
    in_step_ = true;
    step_has_static_ = false;
  }

  void static_procedure(const KeywordBlock& b) {
    b.allow_only({"DIRECT"});
    step_data(b);
    if (step_has_static_) throw DeckError(b.where, "a step has one *STATIC");
    step_has_static_ = true;
    StepDef& s = model_.steps.back();
    if (b.data.size() > 1) throw DeckError(b.data[1].where, "*STATIC takes one data line");
    if (b.data.empty()) return;
    const DataLine& line = b.data[0];
    field_count(line, 0, 4, "*STATIC data line (initial dt, period, min dt, max dt)");
    Context c{line};
    auto get = [&](std::size_t i, double fallback, const std::string& what) {
      return i < c.field_count() && !line.fields[i].empty() ? c.number(i, what) : fallback;
    };
    s.initial_dt = get(0, s.initial_dt, "initial time increment");
    s.period = get(1, s.period, "time period");
    // CalculiX's defaults: the minimum is the initial increment or 1e-5 of the period, whichever is smaller; the
    // maximum is the period (CalculiX: 1e30, which the period bounds anyway)
    s.min_dt = get(2, std::min(kMinIncrementFraction * s.period, s.initial_dt), "minimum time increment");
    s.max_dt = get(3, s.period, "maximum time increment");
    require(s.period > 0.0, line, "time period must be > 0");
    require(s.initial_dt > 0.0 && s.initial_dt <= s.period, line, "initial increment must lie in (0, period]");
    require(s.min_dt > 0.0 && s.min_dt <= s.initial_dt, line, "minimum increment must lie in (0, initial increment]");
    require(s.max_dt >= s.initial_dt, line, "maximum increment must be >= the initial increment");
    if (b.flag("DIRECT")) s.min_dt = s.max_dt = s.initial_dt;
  }

  void cload(const KeywordBlock& b) {
    b.allow_only({"OP"});
    step_data(b);
    needs_data(b);
    apply_op(b, loads_.forces);
    for (const DataLine& line : b.data) {
      field_count(line, 3, 3, "*CLOAD data line (node or set, dof, magnitude)");
      const int dof = dof_number(line.fields[1], line.where);
      const double value = Context{line}.number(2, "force");
      for (int n : nodes_of(line.fields[0], line.where)) loads_.forces[2 * n + dof] = value;
    }
  }

  void dload(const KeywordBlock& b) {
    b.allow_only({"OP"});
    step_data(b);
    needs_data(b);
    apply_op(b, loads_.pressures);
    for (const DataLine& line : b.data) {
      field_count(line, 3, 3, "*DLOAD data line (element or set, P1..P3, pressure)");
      const int face = face_label(line.fields[1], "P", line.where);
      const double value = Context{line}.number(2, "pressure");
      for (int e : elements_of(line.fields[0], line.where)) loads_.pressures[{e, face}] = value;
    }
  }

  void laplace_pressure(const KeywordBlock& b) {
    b.allow_only({"SURFACE", "TENSION", "PROFILE", "OP"});
    step_data(b);
    no_data(b);
    apply_op(b, loads_.laplace);
    const std::string name = b.required("SURFACE");
    const int surface = model_.surface(name);
    if (surface < 0) throw DeckError(b.where, "surface " + name + " is not defined (*SURFACE, NAME=" + name + ")");
    LaplaceLoad load;
    load.tension = to_double(b.required("TENSION"), b.where, "TENSION");
    if (load.tension < 0.0) throw DeckError(b.where, "TENSION must be >= 0 (a garment pulls, it does not push)");
    if (const auto profile = b.value("PROFILE")) {
      load.profile = model_.profile(*profile);
      if (load.profile < 0)
        throw DeckError(b.where, "tension profile " + *profile + " is not defined (*TENSION PROFILE, NAME=" + *profile + ")");
    }
    loads_.laplace[surface] = load;
  }

  // ---- project kinematics: *VOLUME CHANGE, *AXIAL STRETCH, *RIGID MOTION ----------
  // The one data line of a keyword that takes exactly `count` values.
  static const DataLine& one_data_line(const KeywordBlock& b, std::size_t count, const std::string& what) {
    needs_data(b);
    if (b.data.size() > 1) throw DeckError(b.data[1].where, "*" + b.name + " takes one data line (" + what + ")");
    field_count(b.data[0], count, count, "*" + b.name + " data line (" + what + ")");
    return b.data[0];
  }

  void volume_change(const KeywordBlock& b) {
    b.allow_only({"ELSET", "OP"});
    step_data(b);
    apply_op(b, loads_.volume_change);
    const std::vector<int> elements = elements_of(b.required("ELSET"), b.where);
    const DataLine& line = one_data_line(b, 1, "dv, the relative volume change of the stress-free state");
    const double dv = Context{line}.number(0, "dv");
    require(dv > -1.0, line,
            "dv must be > -1: the stress-free volume becomes (1 + dv) times the reference volume "
            "(e.g. -0.05 for a 5% fluid loss)");
    for (int e : elements) loads_.volume_change[e] = dv;
  }

  void axial_stretch(const KeywordBlock& b) {
    b.allow_only({});
    step_data(b);
    const DataLine& line = one_data_line(b, 1, "lambda_z, the out-of-plane stretch F33");
    const double stretch = Context{line}.number(0, "lambda_z");
    require(stretch > 0.0, line, "lambda_z must be > 0 (1 is plane strain, e.g. 0.98 for a 2% axial shortening)");
    loads_.axial_stretch = stretch;
  }

  void rigid_motion(const KeywordBlock& b) {
    b.allow_only({"NSET", "CX", "CY", "OP"});
    step_data(b);
    apply_op(b, loads_.rigid_motions);
    RigidMotion motion;
    motion.where = b.where;
    motion.node_set = upper(b.required("NSET"));
    motion.nodes = nodes_of(b.required("NSET"), b.where);
    std::sort(motion.nodes.begin(), motion.nodes.end());  // sorted, once each: binary_search below
    motion.nodes.erase(std::unique(motion.nodes.begin(), motion.nodes.end()), motion.nodes.end());
    const auto cx = b.value("CX"), cy = b.value("CY");
    if (cx.has_value() != cy.has_value()) throw DeckError(b.where, "give both CX= and CY= (or neither: the set's centroid)");
    if (cx) {
      motion.center = {to_double(*cx, b.where, "CX"), to_double(*cy, b.where, "CY")};
    } else {
      for (int n : motion.nodes) motion.center += model_.coordinates[n];
      motion.center /= static_cast<double>(motion.nodes.size());
    }
    const DataLine& line = one_data_line(b, 3, "ux, uy, angle in degrees");
    Context c{line};
    motion.ux = c.number(0, "ux");
    motion.uy = c.number(1, "uy");
    motion.angle_degrees = c.number(2, "angle");
    for (const auto& [name, other] : loads_.rigid_motions) {
      if (name == motion.node_set) continue;  // OP=MOD: this set's motion is replaced
      for (int n : motion.nodes)
        if (std::binary_search(other.nodes.begin(), other.nodes.end(), n))
          throw DeckError(b.where, "node " + std::to_string(model_.node_ids[n]) + " of set " + motion.node_set +
                                       " is already moved by *RIGID MOTION, NSET=" + name + " (line " +
                                       std::to_string(other.where.line) + "): a node follows one rigid motion; split the sets or use OP=NEW");
    }
    // The motion prescribes both dofs of its nodes: it takes over from a *BOUNDARY on them
    // (a bone clamped in the model data, then moved).
    for (int n : motion.nodes) {
      loads_.prescribed.erase(2 * n);
      loads_.prescribed.erase(2 * n + 1);
    }
    loads_.rigid_motions[motion.node_set] = std::move(motion);
  }

  // A *BOUNDARY inside a step may not prescribe a node that a rigid motion drives.
  void check_not_rigid(int node, const SourceLocation& where) const {
    for (const auto& [name, motion] : loads_.rigid_motions)
      if (std::binary_search(motion.nodes.begin(), motion.nodes.end(), node))
        throw DeckError(where, "node " + std::to_string(model_.node_ids[node]) + " is moved by *RIGID MOTION, NSET=" +
                                   name + " (line " + std::to_string(motion.where.line) +
                                   "): remove it from that set, or remove the motion with *RIGID MOTION, OP=NEW");
  }

  // Model or step data alike: the parameters are resolved against the whole model (and
  // the last step) in finish().
  void sensitivity(const KeywordBlock& b) {
    b.allow_only({"PRESSURE"});
    needs_data(b);
    const std::string pressure = upper(b.value("PRESSURE").value_or("NO"));
    if (pressure != "YES" && pressure != "NO") throw DeckError(b.where, "PRESSURE must be YES or NO");
    if (!model_.sensitivity.requested) model_.sensitivity.where = b.where;
    model_.sensitivity.requested = true;
    model_.sensitivity.pressure = model_.sensitivity.pressure || pressure == "YES";
    sensitivity_lines_.insert(sensitivity_lines_.end(), b.data.begin(), b.data.end());
  }

  void resolve_sensitivities() {
    if (!model_.sensitivity.requested) return;
    if (!model_.contact_pairs.empty())
      throw DeckError(model_.sensitivity.where,
                      "*SENSITIVITY is not available with *CONTACT PAIR: contact makes the solution depend on the "
                      "loading path (active set, friction history); remove one of them");
    std::set<std::string> names;
    for (const DataLine& line : sensitivity_lines_) {
      SensitivityParameter p = resolve_sensitivity_parameter(model_, line);
      if (!names.insert(p.name).second) throw DeckError(line.where, "parameter " + p.name + " is listed twice");
      model_.sensitivity.parameters.push_back(std::move(p));
    }
  }

  void output_request(const KeywordBlock& b) {
    b.allow_only({"NSET", "ELSET", "FREQUENCY", "TOTALS", "GLOBAL", "OUTPUT", "POSITION"});
    step_data(b);
    if (const auto nset = b.value("NSET")) nodes_of(*nset, b.where);
    if (const auto elset = b.value("ELSET")) elements_of(*elset, b.where);
    const bool nodal = b.name.rfind("NODE", 0) == 0;
    const std::set<std::string> known = nodal ? std::set<std::string>{"U", "RF"} : std::set<std::string>{"S", "E", "ENER"};
    for (const DataLine& line : b.data)
      for (const std::string& f : line.fields)
        if (!f.empty() && !known.count(upper(f)))
          throw DeckError(line.where, "output variable " + f + " is not available on *" + b.name +
                                          (nodal ? " (use U, RF)" : " (use S, E, ENER)"));
  }

  void end_step(const KeywordBlock& b) {
    b.allow_only({});
    no_data(b);
    if (!in_step_) throw DeckError(b.where, "*END STEP without a matching *STEP");
    model_.steps.back().loads = loads_;
    in_step_ = false;
  }

  // ---- whole-model checks -----------------------------------------------------
  void finish(const SourceLocation& last) {
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

  void check_geometry(const ElementDef& e) const {
    NodeMatrix X(node_count(e.shape), 2);
    for (int k = 0; k < X.rows(); ++k) X.row(k) = model_.coordinates[e.nodes[k]].transpose();
    // Corner area and scale: a clockwise element is inverted, a flat one degenerate.
    const Eigen::Vector2d a = X.row(1) - X.row(0), c = X.row(2) - X.row(0);
    const double area = 0.5 * (a.x() * c.y() - a.y() * c.x());
    const double scale = std::max({a.squaredNorm(), c.squaredNorm(), (X.row(2) - X.row(1)).squaredNorm()});
    const std::string id = std::to_string(e.id);
    if (std::abs(area) <= 1e-10 * scale || scale == 0.0)
      throw DeckError(e.where, "element " + id + " is degenerate (zero area): its corner nodes are collinear or coincide");
    if (area < 0.0)
      throw DeckError(e.where, "element " + id + " is inverted (nodes listed clockwise): list its corners counter-clockwise");
    if (e.shape == ElementShape::T6) {
      // Mid-side nodes far from their edge make det(dX/dxi) change sign inside.
      static const SolidElementProbe probe;
      if (probe.min_jacobian(X) <= 0.0)
        throw DeckError(e.where, "element " + id + " is distorted: a mid-side node lies too far from its edge's midpoint");
    }
  }

  // Checks det(dX/dxi) of a T6 at its nodes and the 6-point rule, which covers the
  // places where a misplaced mid-side node makes the map fold.
  struct SolidElementProbe {
    double min_jacobian(const NodeMatrix& X) const {
      static const double probes[][2] = {{0, 0},   {1, 0},   {0, 1},   {0.5, 0},   {0.5, 0.5}, {0, 0.5},
                                         {1. / 3, 1. / 3}, {0.1, 0.1}, {0.8, 0.1}, {0.1, 0.8}};
      Eigen::VectorXd N;
      Eigen::MatrixXd dN;
      double smallest = 1e300;
      for (const auto& p : probes) {
        shape_functions(ElementShape::T6, p[0], p[1], N, dN);
        smallest = std::min(smallest, (X.transpose() * dN).determinant());
      }
      return smallest;
    }
  };
};

}  // namespace

Model build_model(const std::string& path) { return ModelBuilder(path).build(); }

}  // namespace calfit
