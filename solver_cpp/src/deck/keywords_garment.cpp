// Deck keywords -> Model: the garment's pressure (*TENSION PROFILE with its factor T(theta) / TENSION, *LAPLACE
// PRESSURE p = T/r, Avril et al. eq. (1), with the share REFERENCE of the reference-curvature law;
// solver_cpp/README.md, Project keywords).
#include "deck/model_builder.hpp"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>
#include <string>

namespace calfit {

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

namespace deck_building {

void ModelBuilder::read_harmonics(const KeywordBlock& b, const std::string& what, int lowest, const std::string& why,
                                  std::map<int, std::pair<double, double>>& harmonics) {
  for (const DataLine& line : b.data) {
    field_count(line, 3, 3, what);
    Context c{line};
    const int k = c.integer(0, "harmonic number k");
    require(k >= lowest, line, "harmonic number k must be >= " + std::to_string(lowest) + " (" + why + ")");
    if (harmonics.count(k)) throw DeckError(line.where, "harmonic " + std::to_string(k) + " is listed twice");
    harmonics[k] = {c.number(1, "a_k"), c.number(2, "b_k")};
  }
}

void ModelBuilder::tension_profile(const KeywordBlock& b) {
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

void ModelBuilder::read_table_profile(const KeywordBlock& b, TensionProfile& p) {
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
void ModelBuilder::read_fourier_profile(const KeywordBlock& b, TensionProfile& p) {
  read_harmonics(b, "*TENSION PROFILE, TYPE=FOURIER data line (k, a_k, b_k)", 1, "the constant term is the TENSION itself",
                 p.harmonics);
  double angle = 0.0;
  const double smallest = p.minimum_factor(&angle);
  if (!(smallest > 0.0)) {
    std::ostringstream where;
    where << std::setprecision(4) << smallest << " at " << angle;
    throw DeckError(b.where, "the tension factor 1 + sum_k (a_k cos k theta + b_k sin k theta) of profile " + p.name +
                                 " falls to " + where.str() + " degrees: it must stay > 0 all around");
  }
}

void ModelBuilder::laplace_pressure(const KeywordBlock& b) {
  b.allow_only({"SURFACE", "TENSION", "PROFILE", "REFERENCE", "OP"});
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
  if (const auto reference = b.value("REFERENCE")) {
    load.reference = to_double(*reference, b.where, "REFERENCE");
    if (!(load.reference >= 0.0 && load.reference <= 1.0))
      throw DeckError(b.where, "REFERENCE=" + *reference +
                                   " is outside [0, 1]: it is the share of the reference-curvature law (0: the pressure "
                                   "follows the deformed contour, 1: it is fixed by the unloaded contour)");
  }
  loads_.laplace[surface] = load;
}

}  // namespace deck_building

}  // namespace calfit
