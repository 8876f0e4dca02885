// Strain-energy laws: see laws.hpp for the equations and their sources.
#include "material/laws.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace calfit {

namespace {

// x^n for n >= 0 by repeated products: exact for the small integer exponents of the polynomial law,
// and 0^0 = 1 (std::pow would take a logarithm, and no term here needs a negative power).
double power(double x, int n) {
  double r = 1.0;
  for (int k = 0; k < n; ++k) r *= x;
  return r;
}

}  // namespace

IsochoricDerivatives ReducedPolynomialIsochoric::evaluate(double I1bar, double) const {
  IsochoricDerivatives w;
  const double x = I1bar - 3.0;
  for (std::size_t k = 0; k < c_.size(); ++k) {  // products, not std::pow: a neo-Hooke point took two logarithms
    const int n = static_cast<int>(k) + 1;
    const double i = n;
    w.W += c_[k] * power(x, n);
    w.W1 += c_[k] * i * power(x, n - 1);
    if (k >= 1) w.W11 += c_[k] * i * (i - 1.0) * power(x, n - 2);
  }
  return w;
}

std::string ReducedPolynomialIsochoric::description() const {
  std::ostringstream out;
  out << "reduced polynomial (";
  for (std::size_t k = 0; k < c_.size(); ++k) out << (k ? ", " : "") << "C" << k + 1 << "0=" << c_[k];
  out << ")";
  return out.str();
}

IsochoricDerivatives MooneyRivlinIsochoric::evaluate(double I1bar, double I2bar) const {
  IsochoricDerivatives w;
  w.W = c10_ * (I1bar - 3.0) + c01_ * (I2bar - 3.0);
  w.W1 = c10_;
  w.W2 = c01_;
  return w;
}

std::string MooneyRivlinIsochoric::description() const {
  std::ostringstream out;
  out << "Mooney-Rivlin (C10=" << c10_ << ", C01=" << c01_ << ")";
  return out.str();
}

// Term by term, with x = I1bar - 3, y = I2bar - 3:
//   d/dx c x^i y^j = c i x^(i-1) y^j,  d/dy = c j x^i y^(j-1), and so on; a derivative that lowers an
// exponent below 0 vanishes (the term does not depend on that invariant).
IsochoricDerivatives PolynomialIsochoric::evaluate(double I1bar, double I2bar) const {
  IsochoricDerivatives w;
  const double x = I1bar - 3.0, y = I2bar - 3.0;
  for (const Term& t : terms_) {
    const double i = t.i, j = t.j;
    w.W += t.c * power(x, t.i) * power(y, t.j);
    if (t.i >= 1) w.W1 += t.c * i * power(x, t.i - 1) * power(y, t.j);
    if (t.j >= 1) w.W2 += t.c * j * power(x, t.i) * power(y, t.j - 1);
    if (t.i >= 2) w.W11 += t.c * i * (i - 1.0) * power(x, t.i - 2) * power(y, t.j);
    if (t.i >= 1 && t.j >= 1) w.W12 += t.c * i * j * power(x, t.i - 1) * power(y, t.j - 1);
    if (t.j >= 2) w.W22 += t.c * j * (j - 1.0) * power(x, t.i) * power(y, t.j - 2);
  }
  return w;
}

std::string PolynomialIsochoric::description() const {
  std::ostringstream out;
  out << "polynomial (";
  for (std::size_t k = 0; k < terms_.size(); ++k)
    out << (k ? ", " : "") << "C" << terms_[k].i << terms_[k].j << "=" << terms_[k].c;
  out << ")";
  return out.str();
}

std::vector<std::pair<int, int>> polynomial_exponents(int order) {
  std::vector<std::pair<int, int>> exponents;
  for (int degree = 1; degree <= order; ++degree)
    for (int i = degree; i >= 0; --i) exponents.emplace_back(i, degree - i);
  return exponents;
}

ArrudaBoyceIsochoric::ArrudaBoyceIsochoric(double mu, double lambda_m)
    : mu_(mu), lambda_m_(lambda_m), a_{0.5, 1.0 / 20.0, 11.0 / 1050.0, 19.0 / 7000.0, 519.0 / 673750.0} {}

IsochoricDerivatives ArrudaBoyceIsochoric::evaluate(double I1bar, double) const {
  IsochoricDerivatives w;
  const double inv_l2 = 1.0 / (lambda_m_ * lambda_m_);
  double scale = 1.0;  // lambda_m^-(2i-2)
  for (int k = 0; k < 5; ++k) {
    const double i = k + 1.0;
    const double c = mu_ * a_[k] * scale;
    w.W += c * (std::pow(I1bar, i) - std::pow(3.0, i));
    w.W1 += c * i * std::pow(I1bar, i - 1.0);
    if (k >= 1) w.W11 += c * i * (i - 1.0) * std::pow(I1bar, i - 2.0);
    scale *= inv_l2;
  }
  return w;
}

std::string ArrudaBoyceIsochoric::description() const {
  std::ostringstream out;
  out << "Arruda-Boyce (mu=" << mu_ << ", lambda_m=" << lambda_m_ << ")";
  return out.str();
}

VolumetricDerivatives PolynomialVolumetric::evaluate(double J) const {
  VolumetricDerivatives u;
  const double x = J - 1.0;
  for (std::size_t k = 0; k < d_.size(); ++k) {
    if (d_[k] == 0.0) continue;
    const int m = 2 * (static_cast<int>(k) + 1);
    const double n = m;
    u.U += power(x, m) / d_[k];
    u.dU += n * power(x, m - 1) / d_[k];
    u.d2U += n * (n - 1.0) * power(x, m - 2) / d_[k];
  }
  return u;
}

double PolynomialVolumetric::dilatation(double p) const {
  if (is_constraint()) return 1.0;
  bool quadratic = true;
  for (std::size_t k = 1; k < d_.size(); ++k) quadratic = quadratic && d_[k] == 0.0;
  if (quadratic) return 1.0 + 0.5 * p * d_[0];  // U' = 2 (Theta - 1) / D1 = p
  return VolumetricEnergy::dilatation(p);
}

std::string PolynomialVolumetric::description() const {
  std::ostringstream out;
  out << "polynomial volumetric (";
  for (std::size_t k = 0; k < d_.size(); ++k) out << (k ? ", " : "") << "D" << k + 1 << "=" << d_[k];
  out << ")";
  return out.str();
}

VolumetricDerivatives LogVolumetric::evaluate(double J) const {
  VolumetricDerivatives u;
  u.U = k_ * (0.5 * (J * J - 1.0) - std::log(J));
  u.dU = k_ * (J - 1.0 / J);
  u.d2U = k_ * (1.0 + 1.0 / (J * J));
  return u;
}

double LogVolumetric::dilatation(double p) const {
  if (is_constraint()) return 1.0;
  const double q = p / k_;  // K (Theta - 1/Theta) = p: the positive root of Theta^2 - q Theta - 1
  return 0.5 * (q + std::sqrt(q * q + 4.0));
}

std::string LogVolumetric::description() const {
  std::ostringstream out;
  out << "log volumetric (K=" << k_ << ")";
  return out.str();
}

int LawConstants::index(const std::string& name) const {
  const auto it = std::find(names.begin(), names.end(), name);
  return it == names.end() ? -1 : static_cast<int>(it - names.begin());
}

std::vector<std::string> law_constant_names(const std::string& law, int order) {
  if (law == "NEO HOOKE") return {"C10", "D1"};
  if (law == "MOONEY-RIVLIN") return {"C10", "C01", "D1"};
  if (law == "ARRUDA-BOYCE") return {"MU", "LAMBDA_M", "D"};
  if (law == "AVRIL") return {"C10", "KV", "C20"};  // C20: 0 when the data line gives two values
  if (law == "ELASTIC") return {"E", "NU"};
  if (law == "POLYNOMIAL") {  // C10, C01, C20, C11, C02, ... then D1..DN (CalculiX's order)
    std::vector<std::string> names;
    for (const auto& [i, j] : polynomial_exponents(order)) names.push_back("C" + std::to_string(i) + std::to_string(j));
    for (int i = 1; i <= order; ++i) names.push_back("D" + std::to_string(i));
    return names;
  }
  if (law == "REDUCED POLYNOMIAL") {
    std::vector<std::string> names;
    for (int i = 1; i <= order; ++i) names.push_back("C" + std::to_string(i) + "0");
    for (int i = 1; i <= order; ++i) names.push_back("D" + std::to_string(i));
    return names;
  }
  throw std::invalid_argument("unknown material law " + law);
}

std::shared_ptr<const Material> make_law(const LawConstants& c) {
  using std::make_shared;
  const std::vector<double>& v = c.values;
  if (v.size() != c.names.size() || v.empty()) throw std::invalid_argument("constants of " + c.law + " do not match their names");
  if (c.law == "NEO HOOKE")
    return make_shared<SplitHyperelastic>(make_shared<ReducedPolynomialIsochoric>(std::vector<double>{v[0]}),
                                          make_shared<PolynomialVolumetric>(std::vector<double>{v[1]}));
  if (c.law == "MOONEY-RIVLIN")
    return make_shared<SplitHyperelastic>(make_shared<MooneyRivlinIsochoric>(v[0], v[1]),
                                          make_shared<PolynomialVolumetric>(std::vector<double>{v[2]}));
  if (c.law == "REDUCED POLYNOMIAL") {
    const std::size_t n = v.size() / 2;
    return make_shared<SplitHyperelastic>(
        make_shared<ReducedPolynomialIsochoric>(std::vector<double>(v.begin(), v.begin() + static_cast<long>(n))),
        make_shared<PolynomialVolumetric>(std::vector<double>(v.begin() + static_cast<long>(n), v.end())));
  }
  if (c.law == "POLYNOMIAL") {
    // The order is the number of D's; the Cij come first, in polynomial_exponents order.
    const auto n = std::count_if(c.names.begin(), c.names.end(), [](const std::string& s) { return s[0] == 'D'; });
    const std::vector<std::pair<int, int>> exponents = polynomial_exponents(static_cast<int>(n));
    const auto split = static_cast<long>(exponents.size());
    if (split + n != static_cast<long>(v.size()))
      throw std::invalid_argument("constants of POLYNOMIAL do not match its order");
    std::vector<PolynomialIsochoric::Term> terms;
    for (std::size_t k = 0; k < exponents.size(); ++k)
      terms.push_back({exponents[k].first, exponents[k].second, v[k]});
    return make_shared<SplitHyperelastic>(
        make_shared<PolynomialIsochoric>(std::move(terms)),
        make_shared<PolynomialVolumetric>(std::vector<double>(v.begin() + split, v.end())));
  }
  if (c.law == "ARRUDA-BOYCE")  // CalculiX: U = [(J^2 - 1)/2 - ln J] / D
    return make_shared<SplitHyperelastic>(make_shared<ArrudaBoyceIsochoric>(v[0], v[1]),
                                          make_shared<LogVolumetric>(v[2] != 0.0 ? 1.0 / v[2] : 0.0));
  if (c.law == "AVRIL") {
    // C20 (I1bar - 3)^2 stiffens the law; at C20 = 0 the term is dropped, which is the same
    // law (and the same derivative in C20: the term's stress vanishes at C20 = 0 too, so a
    // sensitivity evaluates it from the copies at C20 != 0).
    const std::vector<double> coefficients = v[2] != 0.0 ? std::vector<double>{v[0], v[2]} : std::vector<double>{v[0]};
    return make_shared<SplitHyperelastic>(make_shared<ReducedPolynomialIsochoric>(coefficients),
                                          make_shared<LogVolumetric>(v[1]));
  }
  if (c.law == "ELASTIC") return make_shared<StVenantKirchhoff>(v[0], v[1]);
  throw std::invalid_argument("unknown material law " + c.law);
}

}  // namespace calfit
