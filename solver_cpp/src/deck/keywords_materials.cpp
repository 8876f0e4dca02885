// Deck keywords -> Model: materials and sections (*MATERIAL, *HYPERELASTIC, *ELASTIC, *SOLID SECTION;
// solver_cpp/README.md, Standard keywords, and Project keywords for *HYPERELASTIC, AVRIL).
#include "deck/model_builder.hpp"
#include "material/laws.hpp"

#include <algorithm>
#include <string>
#include <utility>
#include <vector>

namespace calfit::deck_building {

void ModelBuilder::material(const KeywordBlock& b) {
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

void ModelBuilder::check_material_complete() const {
  if (current_material_ >= 0 && !material_has_law_) {
    const MaterialDef& m = model_.materials[current_material_];
    throw DeckError(m.where, "material " + m.name + " has no *HYPERELASTIC or *ELASTIC data");
  }
}

// CalculiX reads at most 8 constants from a material data line and continues on the next one
// (*HYPERELASTIC, POLYNOMIAL, N=3: C10, C01, C20, C11, C02, C30, C21, C12, then C03, D1, D2, D3), so a
// law of `count` constants takes ceil(count / 8) lines; more lines would be temperature-dependent data.
std::vector<DataLine> ModelBuilder::law_data_lines(const KeywordBlock& b, std::size_t count) {
  if (current_material_ < 0) throw DeckError(b.where, "*" + b.name + " must follow a *MATERIAL keyword");
  if (material_has_law_)
    throw DeckError(b.where, "material " + model_.materials[current_material_].name + " already has a constitutive law");
  needs_data(b);
  const std::size_t lines = (count + kConstantsPerLine - 1) / kConstantsPerLine;
  if (b.data.size() < lines)
    throw DeckError(b.data.back().where, "the law's " + std::to_string(count) + " constants take " + std::to_string(lines) +
                                             " data lines (at most " + std::to_string(kConstantsPerLine) +
                                             " a line, as CalculiX reads them): continue on the next line");
  if (b.data.size() > lines)
    throw DeckError(b.data[lines].where, "temperature-dependent material data is not supported: give " +
                                             (lines == 1 ? std::string("one data line") : std::to_string(lines) + " data lines"));
  return std::vector<DataLine>(b.data.begin(), b.data.begin() + static_cast<long>(lines));
}

// Checks nothing: the caller checked the constants where it read them.
void ModelBuilder::set_law(LawConstants constants) {
  MaterialDef& m = model_.materials[current_material_];
  m.law = make_law(constants);
  m.constants = std::move(constants);
  material_has_law_ = true;
}

// The data lines of a law, read into its named constants (law_constant_names order): every line but the
// last holds kConstantsPerLine of them; the last `optional` constants may be left off the last line and are
// then 0 (AVRIL's C20).
LawConstants ModelBuilder::read_constants(const KeywordBlock& b, const std::string& law, int order,
                                          const std::string& what, std::size_t optional) {
  LawConstants c{law, law_constant_names(law, order), {}};
  const std::vector<DataLine> lines = law_data_lines(b, c.names.size());
  for (std::size_t k = 0; k < lines.size(); ++k) {
    const std::size_t first = k * kConstantsPerLine, count = std::min(kConstantsPerLine, c.names.size() - first);
    const bool last = k + 1 == lines.size();
    const std::string fix = lines.size() > 1 ? ", " + std::to_string(kConstantsPerLine) +
                                                   " a line as CalculiX reads them and the rest on the next line"
                                             : "";
    field_count(lines[k], count - (last ? optional : 0), count, what + fix);
    for (std::size_t i = 0; i < count; ++i)
      c.values.push_back(i < lines[k].fields.size() ? Context{lines[k]}.number(i, c.names[first + i]) : 0.0);
  }
  return c;
}

void ModelBuilder::hyperelastic(const KeywordBlock& b) {
  model_data(b);
  std::string law = "NEO HOOKE";
  int n = 1;
  for (const Parameter& p : b.parameters) {
    if (p.name == "N") {
      n = to_int(p.value, b.where, "N");
      if (n < 1 || n > 3) throw DeckError(b.where, "POLYNOMIAL and REDUCED POLYNOMIAL need N = 1, 2 or 3");
    } else if (p.name == "NEO HOOKE" || p.name == "MOONEY-RIVLIN" || p.name == "POLYNOMIAL" ||
               p.name == "REDUCED POLYNOMIAL" || p.name == "ARRUDA-BOYCE" || p.name == "AVRIL") {
      law = p.name;
    } else {
      throw DeckError(b.where, "unknown parameter " + p.name +
                                   " on *HYPERELASTIC (calfit-fe reads NEO HOOKE, MOONEY-RIVLIN, POLYNOMIAL with N=, "
                                   "REDUCED POLYNOMIAL with N=, ARRUDA-BOYCE, AVRIL)");
    }
  }
  // The checks name the data line the constant is on: the first for the C's, the last for the D's.
  auto nonneg = [&](double d, const std::string& name) {
    require(d >= 0.0, b.data.back(), name + " must be >= 0 (0 means incompressible)");
  };
  auto require_first = [&](bool ok, const std::string& message) { require(ok, b.data.front(), message); };
  if (law == "NEO HOOKE") {
    const LawConstants c = read_constants(b, law, 1, "*HYPERELASTIC, NEO HOOKE data (C10, D1)");
    require_first(c.values[0] > 0.0, "C10 must be > 0");
    nonneg(c.values[1], "D1");
    set_law(c);
  } else if (law == "MOONEY-RIVLIN") {
    const LawConstants c = read_constants(b, law, 1, "*HYPERELASTIC, MOONEY-RIVLIN data (C10, C01, D1)");
    require_first(c.values[0] + c.values[1] > 0.0, "C10 + C01 (the initial shear modulus / 2) must be > 0");
    nonneg(c.values[2], "D1");
    set_law(c);
  } else if (law == "POLYNOMIAL") {
    // As in CalculiX any Cij may be negative (the law's stability over the strains reached is the user's:
    // Bouten and Drapier's fat has C20 < 0); the initial shear modulus 2 (C10 + C01) must be positive.
    const std::vector<std::string> names = law_constant_names(law, n);
    std::string list;
    for (std::size_t i = 0; i < names.size(); ++i) list += (i ? ", " : "") + names[i];
    const LawConstants c =
        read_constants(b, law, n, "*HYPERELASTIC, POLYNOMIAL, N=" + std::to_string(n) + " data (" + list + ")");
    require_first(c.values[0] + c.values[1] > 0.0, "C10 + C01 (the initial shear modulus / 2) must be > 0");
    for (int i = 1; i <= n; ++i) {
      const std::string d = "D" + std::to_string(i);
      nonneg(c.values[static_cast<std::size_t>(c.index(d))], d);
    }
    set_law(c);
  } else if (law == "REDUCED POLYNOMIAL") {
    const LawConstants c = read_constants(b, law, n, "*HYPERELASTIC, REDUCED POLYNOMIAL, N=" + std::to_string(n) +
                                                         " data (C10..CN0, D1..DN)");
    for (int i = 0; i < n; ++i) nonneg(c.values[static_cast<std::size_t>(n + i)], "D" + std::to_string(i + 1));
    require_first(c.values[0] > 0.0, "C10 must be > 0");
    set_law(c);
  } else if (law == "ARRUDA-BOYCE") {
    const LawConstants c = read_constants(b, law, 1, "*HYPERELASTIC, ARRUDA-BOYCE data (mu, lambda_m, D)");
    require_first(c.values[0] > 0.0, "mu must be > 0");
    require_first(c.values[1] >= 1.0, "lambda_m (locking stretch) must be >= 1");
    nonneg(c.values[2], "D");
    set_law(c);
  } else {  // AVRIL, with the optional C20 (I1bar - 3)^2 of the `stiffening` effect (0 when not given)
    const LawConstants c = read_constants(b, law, 1, "*HYPERELASTIC, AVRIL data (C10, Kv[, C20])", 1);
    require_first(c.values[0] > 0.0, "C10 must be > 0");
    require_first(c.values[1] > 0.0, "Kv must be > 0");
    require_first(c.values[2] >= 0.0, "C20 must be >= 0 (it stiffens the law at large strain; 0 drops the term)");
    set_law(c);
  }
}

void ModelBuilder::elastic(const KeywordBlock& b) {
  b.allow_only({"TYPE"});
  model_data(b);
  const std::string type = upper(b.value("TYPE").value_or("ISO"));
  if (type != "ISO") throw DeckError(b.where, "*ELASTIC, TYPE=" + type + " is not supported: use TYPE=ISO");
  const LawConstants c = read_constants(b, "ELASTIC", 1, "*ELASTIC data (E, nu)");
  const DataLine& line = b.data.front();
  require(c.values[0] > 0.0, line, "Young's modulus E must be > 0");
  require(c.values[1] > -1.0 && c.values[1] < 0.5, line, "Poisson's ratio must lie in (-1, 0.5)");
  set_law(c);
}

void ModelBuilder::solid_section(const KeywordBlock& b) {
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

}  // namespace calfit::deck_building
