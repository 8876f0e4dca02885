// Deck keywords -> Model: the steps and their standard loads (*STEP, *STATIC, *BOUNDARY, *CLOAD, *DLOAD, *NODE PRINT,
// *NODE FILE, *EL PRINT, *EL FILE, *END STEP; solver_cpp/README.md, Standard keywords).
#include "deck/model_builder.hpp"

#include <algorithm>
#include <set>
#include <string>

namespace calfit::deck_building {

// CalculiX *STATIC: the default minimum time increment is this fraction of the step's period (or the initial
// increment, if smaller).
constexpr double kMinIncrementFraction = 1e-5;

void ModelBuilder::step(const KeywordBlock& b) {
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

void ModelBuilder::static_procedure(const KeywordBlock& b) {
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

void ModelBuilder::boundary(const KeywordBlock& b) {
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

void ModelBuilder::cload(const KeywordBlock& b) {
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

void ModelBuilder::dload(const KeywordBlock& b) {
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

void ModelBuilder::output_request(const KeywordBlock& b) {
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

void ModelBuilder::end_step(const KeywordBlock& b) {
  b.allow_only({});
  no_data(b);
  if (!in_step_) throw DeckError(b.where, "*END STEP without a matching *STEP");
  model_.steps.back().loads = loads_;
  in_step_ = false;
}

}  // namespace calfit::deck_building
