// Deck keywords -> Model: *SENSITIVITY, the parameters whose du/dtheta the last step reports (solver_cpp/README.md,
// Sensitivities); deck/sensitivity_parameters.cpp resolves each data line.
#include "deck/model_builder.hpp"
#include "deck/sensitivity_parameters.hpp"

#include <cctype>
#include <set>
#include <string>
#include <utility>

namespace calfit::deck_building {

// Model or step data alike: the parameters are resolved against the whole model (and
// the last step) in finish().
void ModelBuilder::sensitivity(const KeywordBlock& b) {
  b.allow_only({"PRESSURE", "NAME"});
  needs_data(b);
  const std::string pressure = upper(b.value("PRESSURE").value_or("NO"));
  if (pressure != "YES" && pressure != "NO") throw DeckError(b.where, "PRESSURE must be YES or NO");
  if (!model_.sensitivity.requested) model_.sensitivity.where = b.where;
  model_.sensitivity.requested = true;
  model_.sensitivity.pressure = model_.sensitivity.pressure || pressure == "YES";
  if (!b.find("NAME")) {
    for (const DataLine& line : b.data) sensitivity_entries_.push_back({"", line.where, {{line, 1.0}}});
    return;
  }
  // one parameter from the block's lines, each `<parameter line>, <weight>`
  const std::string name = b.required("NAME");
  for (char c : name)
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == ':' || c == '.' || c == '-'))
      throw DeckError(b.where, "*SENSITIVITY, NAME=" + name + ": a name of letters, digits and _ : . - (it names "
                               "the output files' columns)");
  PendingSensitivity entry{name, b.where, {}};
  for (const DataLine& line : b.data) {
    if (line.fields.size() < 2)
      throw DeckError(line.where, "*SENSITIVITY, NAME=" + name + ": each line is a parameter line followed by its "
                                  "weight, e.g. MATERIAL, FAT, C10, 1.5");
    DataLine member = line;
    member.fields.pop_back();
    entry.lines.emplace_back(member, to_double(line.fields.back(), line.where, "the parameter's weight"));
  }
  sensitivity_entries_.push_back(std::move(entry));
}

void ModelBuilder::resolve_sensitivities() {
  if (!model_.sensitivity.requested) return;
  // Frictionless penalty contact is elastic: the converged state is a function of theta as long as no slave
  // node changes its contact status, and its tangent, contact elements included, gives du/dtheta. Friction makes
  // the state depend on the loading path (the stick history): the sensitivities are then carried along it
  // (solver/sensitivity.hpp, (4)-(5)), for what acts on the elements alone: material constants, and the volume
  // change or axial stretch that the last step brings in; and for the contact's own gap offsets (GAP PROFILE),
  // which act at every increment (a load on faces or a prescribed motion is not carried).
  bool friction = false;
  for (const ContactPairDef& pair : model_.contact_pairs)
    friction = friction || model_.interactions[pair.interaction].law.friction > 0.0;
  auto before_last_step = [&](const SensitivityParameter& p) {
    for (std::size_t k = 0; k + 1 < model_.steps.size(); ++k) {
      const LoadState& loads = model_.steps[k].loads;
      if (p.name == "AXIAL STRETCH" && loads.axial_stretch != 1.0) return true;
      if (p.name.rfind("VOLUME CHANGE:", 0) == 0)
        for (int e : p.scope.elements)
          if (const auto dv = loads.volume_change.find(e); dv != loads.volume_change.end() && dv->second != 0.0)
            return true;
    }
    return false;
  };
  auto resolved = [&](const DataLine& line) {
    SensitivityParameter p = resolve_sensitivity_parameter(model_, line);
    if (friction && (!p.scope.faces.empty() || p.scope.prescribed || before_last_step(p)))
      throw DeckError(line.where, "with *FRICTION on a *CONTACT PAIR, *SENSITIVITY carries along the loading path "
                                  "material constants, the volume change or axial stretch of the last step and "
                                  "GAP PROFILE and SHAPE coefficients only, not " + p.name + ": difference runs of the "
                                  "deck for it, or remove *FRICTION");
    return p;
  };
  std::set<std::string> names;
  for (const PendingSensitivity& entry : sensitivity_entries_) {
    SensitivityParameter p;
    if (entry.combined_name.empty()) {
      p = resolved(entry.lines.front().first);
    } else {
      std::vector<std::pair<SensitivityParameter, double>> members;
      for (const auto& [line, weight] : entry.lines) members.emplace_back(resolved(line), weight);
      p = combine_sensitivity_parameters(model_, entry.combined_name, entry.where, members);
    }
    if (!names.insert(p.name).second) throw DeckError(entry.where, "parameter " + p.name + " is listed twice");
    model_.sensitivity.parameters.push_back(std::move(p));
  }
}

}  // namespace calfit::deck_building
