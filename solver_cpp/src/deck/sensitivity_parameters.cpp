// Sensitivity parameter kinds: see sensitivity_parameters.hpp.
#include "deck/sensitivity_parameters.hpp"
#include "element/triangle.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <set>

namespace calfit {
namespace {

using Resolver = SensitivityParameter (*)(const Model&, const DataLine&);

void expect_fields(const DataLine& line, std::size_t n, const std::string& form) {
  if (line.fields.size() != n)
    throw DeckError(line.where, "*SENSITIVITY data line: expected " + form + ", found " + std::to_string(line.fields.size()) +
                                    " values");
}

std::vector<std::pair<int, int>> faces_of(const Model& model, int surface) {
  std::vector<std::pair<int, int>> faces;
  for (const Face& f : model.surfaces[surface]) faces.emplace_back(f.element, f.face);
  return faces;
}

void sort_unique(std::vector<std::pair<int, int>>& faces) {
  std::sort(faces.begin(), faces.end());
  faces.erase(std::unique(faces.begin(), faces.end()), faces.end());
}

// MATERIAL, <material>, <constant>: the law is rebuilt from its constants with one changed.
SensitivityParameter material_constant(const Model& model, const DataLine& line) {
  expect_fields(line, 3, "MATERIAL, material name, constant");
  const std::string name = upper(line.fields[1]), constant = upper(line.fields[2]);
  const int material = model.material(name);
  if (material < 0) throw DeckError(line.where, "material " + name + " is not defined (*MATERIAL, NAME=" + name + ")");
  const LawConstants& law = model.materials[material].constants;
  const int index = law.index(constant);
  if (index < 0) {
    std::string known;
    for (const std::string& n : law.names) known += (known.empty() ? "" : ", ") + n;
    throw DeckError(line.where, "material " + name + " (" + law.law + ") has no constant " + constant + ": its constants are " + known);
  }
  SensitivityParameter p;
  p.name = "MATERIAL:" + name + ":" + constant;
  p.where = line.where;
  // Where the constant is 0 (C01, C20 switched off) the step takes the size of the law's
  // constants of the same kind (the C's are stresses, the D's compliances).
  double same_kind = 0.0;
  for (std::size_t i = 0; i < law.names.size(); ++i)
    if (law.names[i][0] == constant[0]) same_kind = std::max(same_kind, std::abs(law.values[i]));
  p.scale = same_kind > 0.0 ? same_kind : 1.0;
  // The isochoric coefficients (every Cij of the polynomial laws) and the moduli scale the
  // stress linearly, in displacement and hybrid elements alike; the compliances D, KV
  // (hybrid: G'(p) is not linear in it), LAMBDA_M and NU do not.
  static const std::set<std::string> linear = {"C10", "C01", "C20", "C11", "C02", "C30", "C21", "C12", "C03", "MU", "E"};
  p.affine = linear.count(constant) > 0;
  p.get = [material, index](const ParameterState& s) { return s.materials[material].constants.values[index]; };
  p.set = [material, index](ParameterState& s, double value) {
    MaterialDef& m = s.materials[material];
    m.constants.values[index] = value;
    m.law = make_law(m.constants);
  };
  for (std::size_t e = 0; e < model.elements.size(); ++e)
    if (model.sections[model.elements[e].section].material == material) p.scope.elements.push_back(static_cast<int>(e));
  if (p.scope.elements.empty()) throw DeckError(line.where, "material " + name + " is used by no element (*SOLID SECTION)");
  return p;
}

// The surface of a TENSION or REFERENCE line: it must carry a *LAPLACE PRESSURE in the last step.
int laplace_surface(const Model& model, const DataLine& line, const std::string& kind, const std::string& quantity) {
  expect_fields(line, 2, kind + ", surface");
  const std::string name = upper(line.fields[1]);
  const int surface = model.surface(name);
  if (surface < 0) throw DeckError(line.where, "surface " + name + " is not defined (*SURFACE, NAME=" + name + ")");
  if (!model.steps.back().loads.laplace.count(surface))
    throw DeckError(line.where, "the last step has no *LAPLACE PRESSURE on surface " + name + ": no " + quantity +
                                    " to differentiate");
  return surface;
}

// TENSION, <surface>: the garment tension of the last step's *LAPLACE PRESSURE there.
SensitivityParameter laplace_tension(const Model& model, const DataLine& line) {
  const int surface = laplace_surface(model, line, "TENSION", "TENSION");
  SensitivityParameter p;
  p.name = "TENSION:" + model.surface_names[surface];
  p.where = line.where;
  p.affine = true;  // both shares of the load are linear in the nodal tension
  p.get = [surface](const ParameterState& s) { return s.loads.laplace.at(surface).tension; };
  p.set = [surface](ParameterState& s, double value) { s.loads.laplace.at(surface).tension = value; };
  p.scope.faces = faces_of(model, surface);
  sort_unique(p.scope.faces);
  return p;
}

// REFERENCE, <surface>: the share alpha of the reference-contour law in the last step's *LAPLACE PRESSURE
// there (0 where the keyword does not give it). The load (1 - alpha) f_deformed + alpha f_reference is affine
// in alpha, dR/dalpha = -(f_reference - f_deformed) at fixed u: the score of the reference law. The setter
// takes any value: (3) of sensitivity.hpp evaluates the load at 2 alpha, or at 1 where alpha = 0.
SensitivityParameter laplace_reference(const Model& model, const DataLine& line) {
  const int surface = laplace_surface(model, line, "REFERENCE", "REFERENCE share");
  SensitivityParameter p;
  p.name = "REFERENCE:" + model.surface_names[surface];
  p.where = line.where;
  p.affine = true;
  p.get = [surface](const ParameterState& s) { return s.loads.laplace.at(surface).reference; };
  p.set = [surface](ParameterState& s, double value) { s.loads.laplace.at(surface).reference = value; };
  p.scope.faces = faces_of(model, surface);
  sort_unique(p.scope.faces);
  return p;
}

// get and set of a_k (cosine) or b_k of the Fourier series of profile `index` in a state's `profiles` (0 where it
// does not list k).
template <typename Profile>
void fourier_accessors(SensitivityParameter& p, std::vector<Profile> ParameterState::*profiles, int index, int k,
                       bool cosine) {
  p.get = [=](const ParameterState& s) {
    const auto& h = (s.*profiles)[static_cast<std::size_t>(index)].harmonics;
    const auto it = h.find(k);
    return it == h.end() ? 0.0 : (cosine ? it->second.first : it->second.second);
  };
  p.set = [=](ParameterState& s, double value) {
    auto& ab = (s.*profiles)[static_cast<std::size_t>(index)].harmonics[k];
    (cosine ? ab.first : ab.second) = value;
  };
}

// The surface a data line names in its second field, and its index; DeckError when the model has none.
std::pair<std::string, int> named_surface(const Model& model, const DataLine& line) {
  const std::string name = upper(line.fields[1]);
  const int surface = model.surface(name);
  if (surface < 0) throw DeckError(line.where, "surface " + name + " is not defined (*SURFACE, NAME=" + name + ")");
  return {name, surface};
}

// The harmonic of an `A<k>` / `B<k>` field (A from k = 0 when allow_a0); DeckError otherwise.
std::pair<int, bool> harmonic_label(const DataLine& line, const std::string& what, bool allow_a0) {
  const std::string label = upper(line.fields[2]);
  const std::string digits = label.size() > 1 ? label.substr(1) : "";
  const bool valid = (label[0] == 'A' || label[0] == 'B') && !digits.empty() && digits.size() < 6 &&
                     std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; }) &&
                     std::stoi(digits) >= (label[0] == 'A' && allow_a0 ? 0 : 1);
  if (!valid)
    throw DeckError(line.where, what + " coefficient " + line.fields[2] + " is not valid: " +
                                    (allow_a0 ? "use A<k> (k >= 0) or B<k> (k >= 1), e.g. A2"
                                              : "use A<k> or B<k> with k >= 1 (e.g. A2)"));
  return {std::stoi(digits), label[0] == 'B'};
}

// PROFILE, <profile>, A<k> | B<k>: a Fourier coefficient, 0 where the profile does not list k.
SensitivityParameter profile_coefficient(const Model& model, const DataLine& line) {
  expect_fields(line, 3, "PROFILE, profile name, A<k> or B<k>");
  const std::string name = upper(line.fields[1]);
  const int profile = model.profile(name);
  if (profile < 0) throw DeckError(line.where, "tension profile " + name + " is not defined (*TENSION PROFILE, NAME=" + name + ")");
  if (model.profiles[profile].type != TensionProfile::Type::Fourier)
    throw DeckError(line.where, "tension profile " + name + " is TYPE=TABLE: coefficients A<k>, B<k> belong to TYPE=FOURIER profiles");
  const auto [k, sine] = harmonic_label(line, "profile", false);
  const bool cosine = !sine;
  SensitivityParameter p;
  p.name = "PROFILE:" + name + ":" + (cosine ? "A" : "B") + std::to_string(k);
  p.where = line.where;
  p.affine = true;  // the factor, and so the tension and the load, are linear in a_k, b_k
  fourier_accessors(p, &ParameterState::profiles, profile, k, cosine);
  for (const auto& [surface, load] : model.steps.back().loads.laplace)
    if (load.profile == profile) {
      const auto faces = faces_of(model, surface);
      p.scope.faces.insert(p.scope.faces.end(), faces.begin(), faces.end());
    }
  if (p.scope.faces.empty())
    throw DeckError(line.where, "tension profile " + name + " is used by no *LAPLACE PRESSURE of the last step (PROFILE=" + name + ")");
  sort_unique(p.scope.faces);
  return p;
}

// GAP PROFILE, <slave surface>, A<k> | B<k>: a coefficient of the surface's *GAP PROFILE (mm; 0 where it does not
// list k). R depends on it through the contact elements only, which StaticAnalysis differentiates itself
// (contact_parameter_derivatives): the scope is empty, and get/set only report the value.
SensitivityParameter gap_coefficient(const Model& model, const DataLine& line) {
  expect_fields(line, 3, "GAP PROFILE, slave surface, A<k> or B<k>");
  const auto [name, surface] = named_surface(model, line);
  const int profile = model.gap_profile(surface);
  if (profile < 0)
    throw DeckError(line.where, "surface " + name + " has no *GAP PROFILE: add *GAP PROFILE, SLAVE=" + name +
                                    " (no data lines: a profile at zero) after its *CONTACT PAIR");
  const auto [k, sine] = harmonic_label(line, "gap profile", true);
  const bool cosine = !sine;
  SensitivityParameter p;
  p.name = "GAP PROFILE:" + name + ":" + (cosine ? "A" : "B") + std::to_string(k);
  p.where = line.where;
  // mm. The pressure sensitivities' difference step is 1e-4 of it: the band's nearly incompressible pressure,
  // a bulk modulus times J - 1, loses its digits to round-off over a step of 1e-7 mm (1 % where dp/da is small)
  p.scale = 1.0;
  p.affine = true;
  fourier_accessors(p, &ParameterState::gap_profiles, profile, k, cosine);
  p.gap_surface = surface;
  p.gap_harmonic = k;
  p.gap_sine = !cosine;
  return p;
}

// The elements with a node in `nodes` (sorted).
std::vector<int> elements_touching(const Model& model, const std::vector<int>& nodes) {
  std::vector<int> elements;
  for (std::size_t e = 0; e < model.elements.size(); ++e)
    for (int n : model.elements[e].nodes)
      if (std::binary_search(nodes.begin(), nodes.end(), n)) {
        elements.push_back(static_cast<int>(e));
        break;
      }
  return elements;
}

// The faces loaded in the last step (follower pressure or Laplace) of the given (sorted) elements.
std::vector<std::pair<int, int>> loaded_faces_of(const Model& model, const std::vector<int>& elements) {
  const LoadState& loads = model.steps.back().loads;
  std::vector<std::pair<int, int>> faces;
  for (const auto& entry : loads.pressures) faces.push_back(entry.first);
  for (const auto& entry : loads.laplace) {
    const auto surface = faces_of(model, entry.first);
    faces.insert(faces.end(), surface.begin(), surface.end());
  }
  faces.erase(std::remove_if(faces.begin(), faces.end(),
                             [&](const std::pair<int, int>& f) { return !std::binary_search(elements.begin(), elements.end(), f.first); }),
              faces.end());
  sort_unique(faces);
  return faces;
}

// SHAPE, <surface>, A<k> | B<k>: the surface's nodes moved radially, X += theta cos k phi e_r (sin k phi for B),
// phi and e_r about the centroid of its nodes (mm; 0 is the mesh's own shape): a segmented contour's shape error.
// The elements touching them are rebuilt on the moved positions (central difference), and any contact element
// with such a node sees it moved (StaticAnalysis::contact_parameter_derivatives).
SensitivityParameter shape_coefficient(const Model& model, const DataLine& line) {
  expect_fields(line, 3, "SHAPE, surface, A<k> or B<k>");
  const auto [name, surface] = named_surface(model, line);
  const auto [k, sine] = harmonic_label(line, "shape", true);
  SensitivityParameter p;
  p.name = "SHAPE:" + name + ":" + (sine ? "B" : "A") + std::to_string(k);
  p.where = line.where;
  p.scale = 1.0;  // mm: the difference step is 1e-4 mm
  const std::vector<int> nodes = model.surface_nodes(surface);
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  for (int n : nodes) center += model.coordinates[n];
  center /= static_cast<double>(std::max<std::size_t>(nodes.size(), 1));
  for (int n : nodes) {
    const Eigen::Vector2d radial = model.coordinates[n] - center;
    if (radial.norm() == 0.0) continue;
    p.shape.emplace_back(n, GapProfile::basis(k, sine, model.coordinates[n], center) * radial.normalized());
  }
  const std::string key = p.name;
  const auto shape = p.shape;
  p.get = [key](const ParameterState& s) {
    const auto it = s.shape_coefficients.find(key);
    return it == s.shape_coefficients.end() ? 0.0 : it->second;
  };
  p.set = [key, shape](ParameterState& s, double value) {
    double& current = s.shape_coefficients[key];
    for (const auto& [node, direction] : shape)  // (Eigen's vectors start uninitialized)
      s.node_shifts.try_emplace(node, Eigen::Vector2d::Zero()).first->second += (value - current) * direction;
    current = value;
  };
  p.scope.elements = elements_touching(model, nodes);
  if (!loaded_faces_of(model, p.scope.elements).empty())
    throw DeckError(line.where, "SHAPE of surface " + name + ": its elements carry face loads in the last step "
                                "(*LAPLACE PRESSURE, *DLOAD), which a moved contour would change too; calfit-fe "
                                "differentiates the shape of unloaded or contact surfaces only (for Laplace's "
                                "garment, PROFILE lines give the pressure's change)");
  return p;
}

// VOLUME CHANGE, <elset>: the dv of the set's elements in the last step (0 where the step
// has none), one value shared by the set; the setter gives it to every element of the set.
SensitivityParameter volume_change(const Model& model, const DataLine& line) {
  expect_fields(line, 2, "VOLUME CHANGE, element set");
  const std::string name = upper(line.fields[1]);
  const auto set = model.element_sets.find(name);
  if (set == model.element_sets.end()) throw DeckError(line.where, "element set " + name + " is not defined (*ELSET or ELSET= on *ELEMENT)");
  std::vector<int> elements = set->second;
  std::sort(elements.begin(), elements.end());
  elements.erase(std::unique(elements.begin(), elements.end()), elements.end());
  if (elements.empty()) throw DeckError(line.where, "element set " + name + " is empty");
  const std::map<int, double>& dv = model.steps.back().loads.volume_change;
  auto dv_of = [&dv](int e) {
    const auto it = dv.find(e);
    return it == dv.end() ? 0.0 : it->second;
  };
  for (int e : elements)
    if (dv_of(e) != dv_of(elements.front()))
      throw DeckError(line.where, "the elements of set " + name + " have different volume changes in the last step (" +
                                      std::to_string(dv_of(elements.front())) + " and " + std::to_string(dv_of(e)) +
                                      "): VOLUME CHANGE differentiates one dv that the whole set shares");
  SensitivityParameter p;
  p.name = "VOLUME CHANGE:" + name;
  p.where = line.where;
  p.scale = 0.1;  // a tissue's volume change is a few per cent: dv = 0 is differenced with h = 1e-5
  const int first = elements.front();
  p.get = [first](const ParameterState& s) {
    const auto it = s.loads.volume_change.find(first);
    return it == s.loads.volume_change.end() ? 0.0 : it->second;
  };
  p.set = [elements](ParameterState& s, double value) {
    for (int e : elements) s.loads.volume_change[e] = value;
  };
  p.scope.elements = elements;
  return p;
}

// AXIAL STRETCH: lambda_z of the last step (1 without *AXIAL STRETCH); every element.
SensitivityParameter axial_stretch(const Model& model, const DataLine& line) {
  expect_fields(line, 1, "AXIAL STRETCH");
  SensitivityParameter p;
  p.name = "AXIAL STRETCH";
  p.where = line.where;
  p.get = [](const ParameterState& s) { return s.loads.axial_stretch; };
  p.set = [](ParameterState& s, double value) { s.loads.axial_stretch = value; };
  for (std::size_t e = 0; e < model.elements.size(); ++e) p.scope.elements.push_back(static_cast<int>(e));
  return p;
}

// RIGID MOTION, <nset>, UX | UY | ANGLE: a component of the set's *RIGID MOTION in the last
// step. Without one the set must be clamped (both dofs of every node prescribed to 0 by
// *BOUNDARY), which is the motion at zero about the set's centroid: the value is 0 and
// the setter adds that motion. The parameter moves prescribed dofs.
SensitivityParameter rigid_motion(const Model& model, const DataLine& line) {
  expect_fields(line, 3, "RIGID MOTION, node set, UX or UY or ANGLE");
  const std::string name = upper(line.fields[1]), component = upper(line.fields[2]);
  const auto set = model.node_sets.find(name);
  if (set == model.node_sets.end()) throw DeckError(line.where, "node set " + name + " is not defined (*NSET, NSET=" + name + ")");
  if (component != "UX" && component != "UY" && component != "ANGLE")
    throw DeckError(line.where, "rigid motion component " + line.fields[2] +
                                    " is not valid: use UX, UY (translation) or ANGLE (degrees, counter-clockwise)");
  std::vector<int> nodes = set->second;
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  if (nodes.empty()) throw DeckError(line.where, "node set " + name + " is empty");

  const LoadState& loads = model.steps.back().loads;
  Eigen::Vector2d low = model.coordinates[nodes.front()], high = low;
  for (int n : nodes) {
    low = low.cwiseMin(model.coordinates[n]);
    high = high.cwiseMax(model.coordinates[n]);
  }
  RigidMotion at_zero;  // what an absent motion is
  if (!loads.rigid_motions.count(name)) {
    for (int n : nodes)
      for (int dof : {2 * n, 2 * n + 1}) {
        const auto prescribed = loads.prescribed.find(dof);
        if (prescribed == loads.prescribed.end() || prescribed->second != 0.0)
          throw DeckError(line.where, "node set " + name + " has no *RIGID MOTION in the last step and node " +
                                          std::to_string(model.node_ids[n]) +
                                          " is not clamped (*BOUNDARY, both dofs 0): a motion at zero would move it");
      }
    at_zero.node_set = name;
    at_zero.nodes = nodes;
    for (int n : nodes) at_zero.center += model.coordinates[n];
    at_zero.center /= static_cast<double>(nodes.size());
    at_zero.where = line.where;
  }
  SensitivityParameter p;
  p.name = "RIGID MOTION:" + name + ":" + component;
  p.where = line.where;
  // The size of the value where it is 0: a hundredth of the set's extent for a translation
  // (the difference step is then 1e-6 of the extent), a degree for the angle.
  p.scale = component == "ANGLE" ? 1.0 : std::max(0.01 * (high - low).norm(), 1e-300);
  using Component = double RigidMotion::*;
  const Component field = component == "UX" ? &RigidMotion::ux : component == "UY" ? &RigidMotion::uy : &RigidMotion::angle_degrees;
  p.get = [name, field](const ParameterState& s) {
    const auto it = s.loads.rigid_motions.find(name);
    return it == s.loads.rigid_motions.end() ? 0.0 : it->second.*field;
  };
  p.set = [name, field, at_zero](ParameterState& s, double value) {
    auto it = s.loads.rigid_motions.find(name);
    if (it == s.loads.rigid_motions.end()) it = s.loads.rigid_motions.emplace(name, at_zero).first;
    it->second.*field = value;
  };
  p.scope.prescribed = true;
  p.scope.elements = elements_touching(model, nodes);
  p.scope.faces = loaded_faces_of(model, p.scope.elements);
  return p;
}

const std::map<std::string, Resolver>& kinds() {
  static const std::map<std::string, Resolver> table = {
      {"MATERIAL", material_constant},
      {"TENSION", laplace_tension},
      {"REFERENCE", laplace_reference},
      {"PROFILE", profile_coefficient},
      {"GAP PROFILE", gap_coefficient},
      {"SHAPE", shape_coefficient},
      {"VOLUME CHANGE", volume_change},
      {"AXIAL STRETCH", axial_stretch},
      {"RIGID MOTION", rigid_motion},
  };
  return table;
}

}  // namespace

SensitivityParameter resolve_sensitivity_parameter(const Model& model, const DataLine& line) {
  const std::string kind = line.fields.empty() ? "" : upper(line.fields[0]);
  const auto it = kinds().find(kind);
  if (it == kinds().end()) {
    std::string known;
    for (const auto& entry : kinds()) known += (known.empty() ? "" : ", ") + entry.first;
    throw DeckError(line.where, "unknown sensitivity parameter kind " + (kind.empty() ? std::string("''") : kind) +
                                    " (calfit-fe knows " + known + ")");
  }
  return it->second(model, line);
}

SensitivityParameter combine_sensitivity_parameters(const Model& model, const std::string& name,
                                                    const SourceLocation& where,
                                                    const std::vector<std::pair<SensitivityParameter, double>>& members) {
  if (members.empty()) throw DeckError(where, "*SENSITIVITY, NAME=" + name + " lists no parameter");
  SensitivityParameter c;
  c.name = name;
  c.where = where;
  c.affine = true;
  // The step t moves member i by w_i t: the largest step that moves no member by more than its own step
  c.scale = std::numeric_limits<double>::infinity();
  const ParameterState base = model.parameter_state();
  std::set<int> elements;
  for (const auto& [p, weight] : members) {
    if (p.gap_surface >= 0 || !p.shape.empty())
      throw DeckError(p.where, p.name + " acts through the contact elements and cannot be combined with other "
                               "parameters: give it in a *SENSITIVITY block of its own (without NAME=)");
    if (!(weight != 0.0) || !std::isfinite(weight))
      throw DeckError(p.where, "the weight of " + p.name + " in *SENSITIVITY, NAME=" + name + " must be a nonzero number");
    c.affine = c.affine && p.affine;
    c.scope.prescribed = c.scope.prescribed || p.scope.prescribed;
    elements.insert(p.scope.elements.begin(), p.scope.elements.end());
    c.scope.faces.insert(c.scope.faces.end(), p.scope.faces.begin(), p.scope.faces.end());
    const double value = std::abs(p.get(base));
    c.scale = std::min(c.scale, (value > 0.0 ? value : p.scale) / std::abs(weight));
  }
  c.scope.elements.assign(elements.begin(), elements.end());
  sort_unique(c.scope.faces);
  c.get = [](const ParameterState&) { return 0.0; };
  c.set = [members](ParameterState& s, double t) {
    for (const auto& [p, weight] : members) p.set(s, p.get(s) + weight * t);
  };
  return c;
}

}  // namespace calfit
