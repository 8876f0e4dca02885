// Deck keywords -> Model: contact (*SURFACE INTERACTION, *SURFACE BEHAVIOR, *FRICTION, *CONTACT PAIR, *MODEL CHANGE,
// *GAP PROFILE; solver_cpp/README.md, Contact).
#include "deck/model_builder.hpp"

#include <algorithm>
#include <cstddef>
#include <string>

namespace calfit::deck_building {

void ModelBuilder::surface_interaction(const KeywordBlock& b) {
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

InteractionDef& ModelBuilder::interaction_for(const KeywordBlock& b) {
  if (current_interaction_ < 0) throw DeckError(b.where, "*" + b.name + " must follow a *SURFACE INTERACTION keyword");
  return model_.interactions[current_interaction_];
}

void ModelBuilder::surface_behavior(const KeywordBlock& b) {
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

void ModelBuilder::friction(const KeywordBlock& b) {
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

int ModelBuilder::surface_named(const std::string& name, const SourceLocation& where) const {
  const int s = model_.surface(name);
  if (s < 0) throw DeckError(where, "surface " + name + " is not defined (*SURFACE, NAME=" + name + ")");
  return s;
}

void ModelBuilder::contact_pair(const KeywordBlock& b) {
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

void ModelBuilder::model_change(const KeywordBlock& b) {
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

// *GAP PROFILE, SLAVE=<surface>[, CX=, CY=]: data lines k, a_k, b_k (mm; none: a profile at zero whose
// coefficients *SENSITIVITY may still ask about). The surface must be the slave of a *CONTACT PAIR given before.
void ModelBuilder::gap_profile(const KeywordBlock& b) {
  b.allow_only({"SLAVE", "CX", "CY"});
  model_data(b);
  GapProfile p;
  p.where = b.where;
  const std::string name = upper(b.required("SLAVE"));
  p.surface = surface_named(name, b.where);
  if (std::none_of(model_.contact_pairs.begin(), model_.contact_pairs.end(),
                   [&](const ContactPairDef& pair) { return pair.slave == p.surface; }))
    throw DeckError(b.where, "surface " + name + " is the slave of no *CONTACT PAIR: put *GAP PROFILE after the "
                             "*CONTACT PAIR whose slave surface it moves");
  if (model_.gap_profile(p.surface) >= 0) throw DeckError(b.where, "surface " + name + " has two *GAP PROFILE blocks");
  const auto cx = b.value("CX"), cy = b.value("CY");
  if (cx.has_value() != cy.has_value()) throw DeckError(b.where, "give both CX= and CY= (or neither)");
  if (cx) {
    p.has_center = true;
    p.center = {to_double(*cx, b.where, "CX"), to_double(*cy, b.where, "CY")};
  }
  read_harmonics(b, "*GAP PROFILE data line (k, a_k, b_k in mm)", 0, "0: a uniform offset a_0", p.harmonics);
  model_.gap_profiles.push_back(p);
}

}  // namespace calfit::deck_building
