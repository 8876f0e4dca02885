// Sensitivity unit tests.
//  - dR/dtheta of every parameter kind (each constant of each law, TENSION, PROFILE A<k>
//    and B<k>, listed and unlisted, REFERENCE (the garment's reference-contour share, at 0 and
//    inside (0, 1), where TENSION and PROFILE see both shares of the load), VOLUME CHANGE, AXIAL STRETCH, RIGID MOTION UX/UY/ANGLE,
//    each where its keyword is absent and where it is given) against an independent central difference: the
//    residual of the full evaluation path (StaticAnalysis::residual) of two models read
//    from decks written with theta -/+ h, at the base model's converged u. This checks
//    the setters, the scopes and the scoped evaluation together; displacement (CPE6)
//    and hybrid (CPE6H) elements.
//  - The scoped evaluation over every element and face equals the full residual.
//  - *TENSION PROFILE, TYPE=FOURIER: the factor, its minimum, the read-time check.
//  - SparseSystem::solve_refined: an old factorization refined against a changed matrix
//    gives that matrix's solution.
#include "check.hpp"
#include "deck/build_model.hpp"
#include "solver/sensitivity.hpp"
#include "solver/sparse_system.hpp"
#include "solver/static_analysis.hpp"

#include <array>
#include <cmath>
#include <optional>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <map>
#include <sstream>

using namespace calfit;

namespace {

const std::filesystem::path kDir = std::filesystem::temp_directory_path() / "calfit_test_sensitivity";
const double kPi = std::acos(-1.0);

std::string write(const std::string& name, const std::string& text) {
  std::filesystem::create_directories(kDir);
  const std::filesystem::path p = kDir / name;
  std::ofstream(p) << text;
  return p.string();
}

std::string number(double v) {
  std::ostringstream out;
  out << std::setprecision(17) << v;
  return out.str();
}

// A ring sector R_in <= r <= R_out, 10 <= angle <= 110 degrees, T6 elements on a polar
// grid (curved sides exact), inner layer MUSCLE, outer layer FAT, inner arc clamped, a
// Laplace-law garment with a FOURIER tension profile on the outer arc. Optionally a
// *VOLUME CHANGE of MUSCLE, an *AXIAL STRETCH and a *RIGID MOTION of the inner arc (which
// then replaces its clamp).
struct SectorCase {
  std::string element_type = "CPE6";
  std::string muscle_law, fat_law;  // as after *HYPERELASTIC, or ELASTIC
  std::map<std::string, double> muscle, fat;  // constant name -> value
  double tension = 0.3;
  double reference = 0.0;  // REFERENCE= of the *LAPLACE PRESSURE
  std::map<int, std::pair<double, double>> harmonics = {{1, {0.1, 0.05}}};
  std::optional<double> muscle_dv, axial_stretch;
  std::optional<std::array<double, 3>> inner_motion;  // ux, uy, angle in degrees
  std::vector<std::string> sensitivities;  // *SENSITIVITY data lines

  // The value a parameter name (MATERIAL:FAT:C10, TENSION:SKIN, PROFILE:GARMENT:B2) refers to.
  double& value(const std::string& name) {
    if (name.rfind("MATERIAL:MUSCLE:", 0) == 0) return muscle.at(name.substr(16));
    if (name.rfind("MATERIAL:FAT:", 0) == 0) return fat.at(name.substr(13));
    if (name == "TENSION:SKIN") return tension;
    if (name == "REFERENCE:SKIN") return reference;
    // An absent keyword is the same model as the keyword at its neutral value.
    if (name == "VOLUME CHANGE:MUSCLE") return muscle_dv ? *muscle_dv : muscle_dv.emplace(0.0);
    if (name == "AXIAL STRETCH") return axial_stretch ? *axial_stretch : axial_stretch.emplace(1.0);
    if (name.rfind("RIGID MOTION:INNER:", 0) == 0) {
      if (!inner_motion) inner_motion.emplace(std::array<double, 3>{0.0, 0.0, 0.0});
      const std::string component = name.substr(19);
      return (*inner_motion)[component == "UX" ? 0 : component == "UY" ? 1 : 2];
    }
    const int k = std::stoi(name.substr(17));
    auto& ab = harmonics[k];
    return name[16] == 'A' ? ab.first : ab.second;
  }

  std::string deck() const {
    const int nr = 2, nt = 6, rows = 2 * nr + 1, columns = 2 * nt + 1;
    const double r_in = 1.0, r_out = 2.0, t0 = 10.0 * kPi / 180.0, t1 = 110.0 * kPi / 180.0;
    auto id = [&](int a, int b) { return 1 + a * columns + b; };
    std::ostringstream d;
    d << "*NODE\n";
    for (int a = 0; a < rows; ++a)
      for (int b = 0; b < columns; ++b) {
        const double r = r_in + (r_out - r_in) * a / (rows - 1.0), t = t0 + (t1 - t0) * b / (columns - 1.0);
        d << id(a, b) << ", " << number(r * std::cos(t)) << ", " << number(r * std::sin(t)) << "\n";
      }
    std::ostringstream muscle_elements, fat_elements, surface;
    int element = 0;
    for (int i = 0; i < nr; ++i)
      for (int j = 0; j < nt; ++j) {
        // corners in (radial, angular) grid steps; counter-clockwise in (r, theta) and so in (x, y)
        const int p00[2] = {2 * i, 2 * j}, p10[2] = {2 * i + 2, 2 * j}, p11[2] = {2 * i + 2, 2 * j + 2},
                  p01[2] = {2 * i, 2 * j + 2};
        for (const auto& tri : {std::array<const int*, 3>{p00, p10, p11}, std::array<const int*, 3>{p00, p11, p01}}) {
          std::ostringstream& out = i == 0 ? muscle_elements : fat_elements;
          out << ++element;
          for (int k = 0; k < 3; ++k) out << ", " << id(tri[k][0], tri[k][1]);
          for (int k = 0; k < 3; ++k)
            out << ", " << id((tri[k][0] + tri[(k + 1) % 3][0]) / 2, (tri[k][1] + tri[(k + 1) % 3][1]) / 2);
          out << "\n";
          if (i == nr - 1 && tri[1] == p10) surface << element << ", S2\n";  // p10 -> p11 on r = r_out
        }
      }
    d << "*ELEMENT, TYPE=" << element_type << ", ELSET=MUSCLE\n" << muscle_elements.str();
    d << "*ELEMENT, TYPE=" << element_type << ", ELSET=FAT\n" << fat_elements.str();
    d << "*NSET, NSET=INNER\n";
    for (int b = 0; b < columns; ++b) d << id(0, b) << "\n";
    d << "*SURFACE, NAME=SKIN, TYPE=ELEMENT\n" << surface.str();
    auto material = [&](const std::string& name, const std::string& law, const std::map<std::string, double>& values) {
      d << "*MATERIAL, NAME=" << name << "\n";
      d << (law == "ELASTIC" ? "*ELASTIC\n" : "*HYPERELASTIC, " + law + "\n");
      const std::string base = law.substr(0, law.find(','));
      const bool ordered = base == "REDUCED POLYNOMIAL" || base == "POLYNOMIAL";
      const int order = ordered ? std::stoi(law.substr(law.find("N=") + 2)) : 1;
      const std::vector<std::string> names = law_constant_names(base, order);
      // 8 constants a data line, the rest on the next (CalculiX's layout: POLYNOMIAL, N=3).
      for (std::size_t k = 0; k < names.size(); ++k)
        d << (k == 0 ? "" : k % 8 == 0 ? "\n" : ", ") << number(values.at(names[k]));
      d << "\n*SOLID SECTION, ELSET=" << name << ", MATERIAL=" << name << "\n";
    };
    material("MUSCLE", muscle_law, muscle);
    material("FAT", fat_law, fat);
    d << "*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n";
    for (const auto& [k, ab] : harmonics) d << k << ", " << number(ab.first) << ", " << number(ab.second) << "\n";
    d << "*BOUNDARY\nINNER, 1, 2\n*STEP, NLGEOM\n*STATIC\n0.5, 1.0\n";
    if (muscle_dv) d << "*VOLUME CHANGE, ELSET=MUSCLE\n" << number(*muscle_dv) << "\n";
    if (axial_stretch) d << "*AXIAL STRETCH\n" << number(*axial_stretch) << "\n";
    if (inner_motion)
      d << "*RIGID MOTION, NSET=INNER\n" << number((*inner_motion)[0]) << ", " << number((*inner_motion)[1]) << ", "
        << number((*inner_motion)[2]) << "\n";
    d << "*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=" << number(tension) << ", PROFILE=GARMENT";
    if (reference != 0.0) d << ", REFERENCE=" << number(reference);
    d << "\n*END STEP\n";
    if (!sensitivities.empty()) {
      d << "*SENSITIVITY\n";
      for (const std::string& line : sensitivities) d << line << "\n";
    }
    return d.str();
  }
};

Model read(const SectorCase& c, const std::string& name) { return build_model(write(name + ".inp", c.deck())); }

Eigen::VectorXd solve(const Model& model, StaticAnalysis& analysis) {
  for (std::size_t k = 0; k < model.steps.size(); ++k) CHECK(analysis.run_step(static_cast<int>(k), [](const std::string&) {}).converged);
  return analysis.solution();
}

// R of the model read from the deck of `c` at u (the full evaluation path), with the inner
// arc where that model's own solution puts it (a rigid motion moves it with theta).
Eigen::VectorXd residual_of(const SectorCase& c, const std::string& name, Eigen::VectorXd u) {
  const Model model = read(c, name);
  StaticAnalysis analysis(model, SolverSettings{});
  const Eigen::VectorXd own = solve(model, analysis);  // also prepares the step's loads
  for (int node : model.node_sets.at("INNER")) u.segment<2>(2 * node) = own.segment<2>(2 * node);
  return analysis.residual(u);
}

void check_residual_derivatives(SectorCase c, const std::string& label) {
  for (const std::string material : {"MUSCLE", "FAT"})
    for (const auto& entry : material == "MUSCLE" ? c.muscle : c.fat)
      c.sensitivities.push_back("MATERIAL, " + material + ", " + entry.first);
  c.sensitivities.insert(c.sensitivities.end(), {"TENSION, SKIN", "REFERENCE, SKIN", "PROFILE, GARMENT, A1", "PROFILE, GARMENT, B1",
                                                 "PROFILE, GARMENT, B2", "PROFILE, GARMENT, A3", "VOLUME CHANGE, MUSCLE",
                                                 "AXIAL STRETCH", "RIGID MOTION, INNER, UX", "RIGID MOTION, INNER, UY",
                                                 "RIGID MOTION, INNER, ANGLE"});
  const Model model = read(c, label);
  StaticAnalysis analysis(model, SolverSettings{});
  const Eigen::VectorXd u = solve(model, analysis);
  const SensitivityAnalysis sensitivity(model, analysis);
  const Eigen::MatrixXd dR = sensitivity.residual_derivatives();
  CHECK(dR.cols() == static_cast<Eigen::Index>(model.sensitivity.parameters.size()));

  SectorCase plain = c;
  plain.sensitivities.clear();
  for (std::size_t j = 0; j < model.sensitivity.parameters.size(); ++j) {
    const std::string& name = model.sensitivity.parameters[j].name;
    const double theta = plain.value(name);
    const double h = 1e-4 * (theta != 0.0 ? std::abs(theta) : 0.1);
    // The deck rejects C20 < 0 and REFERENCE < 0, so at 0 the difference is one-sided: R is
    // affine in both, and the forward difference is exact up to round-off as well.
    const bool one_sided = theta == 0.0 && ((name.size() > 4 && name.substr(name.size() - 4) == ":C20") ||
                                            name.rfind("REFERENCE:", 0) == 0);
    SectorCase plus = plain, minus = plain;
    plus.value(name) = theta + h;
    minus.value(name) = one_sided ? theta : theta - h;
    const Eigen::VectorXd fd =
        (residual_of(plus, label + "-plus", u) - residual_of(minus, label + "-minus", u)) / ((one_sided ? 1.0 : 2.0) * h);
    const Eigen::VectorXd got = dR.col(static_cast<Eigen::Index>(j));
    const double scale = fd.cwiseAbs().maxCoeff(), error = (got - fd).cwiseAbs().maxCoeff();
    std::cout << label << " " << name << ": max |dR/dtheta| " << scale << ", relative difference " << error / scale << '\n';
    CHECK(scale > 0.0);
    CHECK(error <= 1e-6 * scale);
  }

  // The scoped path over the whole model is the full residual.
  ParameterScope everything;
  for (std::size_t e = 0; e < model.elements.size(); ++e) everything.elements.push_back(static_cast<int>(e));
  for (const Face& f : model.surfaces[model.surface("SKIN")]) everything.faces.emplace_back(f.element, f.face);
  const Eigen::VectorXd scoped = analysis.scoped_residual(model.parameter_state(), everything, u);
  const Eigen::VectorXd full = analysis.residual(u);
  CHECK((scoped - full).cwiseAbs().maxCoeff() <= 1e-12 * std::max(1.0, full.cwiseAbs().maxCoeff()));
}

void fourier_profile_tests() {
  TensionProfile p;
  p.type = TensionProfile::Type::Fourier;
  p.harmonics = {{1, {0.3, 0.0}}, {3, {0.0, -0.2}}};
  CHECK_NEAR(p.factor(0.0), 1.3, 1e-14);
  CHECK_NEAR(p.factor(90.0), 1.0 - 0.2 * std::sin(1.5 * kPi), 1e-14);
  double at = 0.0;
  const double smallest = p.minimum_factor(&at);
  double sampled = 1e300;
  for (int i = 0; i < 360000; ++i) sampled = std::min(sampled, p.factor(i * 1e-3));
  CHECK(smallest <= sampled + 1e-12 && smallest >= sampled - 1e-9);
  CHECK_NEAR(p.factor(at), smallest, 1e-12);

  // Read time: a factor that reaches 0 somewhere is an error on the keyword line.
  SectorCase c;
  c.muscle_law = c.fat_law = "NEO HOOKE";
  c.muscle = c.fat = {{"C10", 0.5}, {"D1", 0.1}};
  c.harmonics = {{2, {0.7, 0.7}}};  // 1 + 0.99 cos(2 theta - 45 deg) > 0 ...
  CHECK(read(c, "fourier-ok").profiles[0].minimum_factor() > 0.0);
  c.harmonics = {{2, {0.8, 0.8}}};  // ... 1 + 1.13 cos(...) is not
  try {
    read(c, "fourier-bad");
    CHECK(false);
  } catch (const DeckError& e) {
    std::cout << e.what() << '\n';
    CHECK(std::string(e.what()).find("fourier-bad.inp:") != std::string::npos);
    CHECK(std::string(e.what()).find("must stay > 0") != std::string::npos);
  }
}

void refined_solve_test() {
  // 1D Laplacian chain, factorized; then the matrix changes by 1e-4 relative and the
  // old factorization, refined, must solve the new system to round-off.
  const int n = 40;
  std::vector<std::vector<int>> dofs;
  for (int e = 0; e + 1 < n; ++e) dofs.push_back({e, e + 1});
  std::vector<char> free(n, 1);
  free[0] = 0;
  SparseSystem system(dofs, free);
  auto assemble = [&](double stiffening) {
    system.set_zero();
    for (int e = 0; e + 1 < n; ++e) {
      const double k = 1.0 + 0.5 * std::sin(e) + stiffening * e;
      Eigen::Matrix2d K;
      K << k, -k, -k, k;
      system.add(e, K);
    }
  };
  assemble(0.0);
  Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(n - 1, 1.0, 2.0), x;
  CHECK(system.solve(b, x));
  assemble(1e-4);
  Eigen::MatrixXd B(n - 1, 3), X;
  B << b, Eigen::VectorXd::Ones(n - 1), Eigen::VectorXd::LinSpaced(n - 1, -1.0, 3.0);
  CHECK(system.solve_refined(B, X, 1e-12));
  Eigen::VectorXd exact;
  for (int j = 0; j < 3; ++j) {
    CHECK(system.solve(B.col(j), exact));  // a fresh factorization of the changed matrix
    CHECK((X.col(j) - exact).norm() <= 1e-10 * exact.norm());
  }
}

// A chain of springs with a skew coupling w per element, as a follower load adds to a tangent: K = S + W.
Eigen::MatrixXd assemble_skew_chain(SparseSystem& system, int n, double skew, double stiffening) {
  Eigen::MatrixXd dense = Eigen::MatrixXd::Zero(n - 1, n - 1);
  system.set_zero();
  for (int e = 0; e + 1 < n; ++e) {
    const double k = 1.0 + 0.5 * std::sin(e) + stiffening * e;
    Eigen::Matrix2d K;
    K << k, -k + skew * k, -k - skew * k, k;
    system.add(e, K);
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j)
        if (e + i > 0 && e + j > 0) dense(e + i - 1, e + j - 1) += K(i, j);
  }
  return dense;
}

void split_solve_test() {
  // An unsymmetric tangent with a small skew part is solved on the Cholesky factor of its symmetric part (GMRES),
  // as accurately as a dense LU; a skew part as large as the stiffness falls back to UMFPACK, still exact; a
  // slightly changed tangent reuses the factor of the earlier one.
  const int n = 60;
  std::vector<std::vector<int>> dofs;
  for (int e = 0; e + 1 < n; ++e) dofs.push_back({e, e + 1});
  std::vector<char> free(n, 1);
  free[0] = 0;
  const Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(n - 1, 1.0, 2.0);
  Eigen::VectorXd x;
  SparseSystem split(dofs, free);
  Eigen::MatrixXd dense = assemble_skew_chain(split, n, 0.01, 0.0);
  CHECK(split.solve(b, x));
  CHECK(split.solver_name() == "cholmod-split");
  CHECK((x - dense.partialPivLu().solve(b)).norm() <= 1e-9 * x.norm());

  SparseSystem lu(dofs, free);
  dense = assemble_skew_chain(lu, n, 3.0, 0.0);
  CHECK(lu.solve(b, x));
  CHECK(lu.solver_name() == "umfpack");
  CHECK((x - dense.partialPivLu().solve(b)).norm() <= 1e-9 * x.norm());

  SparseSystem reuse(dofs, free);
  assemble_skew_chain(reuse, n, 0.0, 0.0);
  CHECK(reuse.solve(b, x) && reuse.solver_name() == "cholmod" && reuse.reused_factorizations() == 0);
  dense = assemble_skew_chain(reuse, n, 0.0, 1e-5);
  CHECK(reuse.solve(b, x));
  CHECK(reuse.reused_factorizations() == 1);
  CHECK((x - dense.partialPivLu().solve(b)).norm() <= 1e-9 * x.norm());
}

}  // namespace

int main() {
  fourier_profile_tests();
  refined_solve_test();
  split_solve_test();

  SectorCase a;
  a.muscle_law = "MOONEY-RIVLIN";
  a.muscle = {{"C10", 0.4}, {"C01", 0.1}, {"D1", 0.2}};
  a.fat_law = "AVRIL";
  a.fat = {{"C10", 0.3}, {"KV", 2.0}, {"C20", 0.0}};  // C20 = 0: the derivative where the term is off
  check_residual_derivatives(a, "mooney-avril-cpe6");
  a.element_type = "CPE6H";
  check_residual_derivatives(a, "mooney-avril-cpe6h");

  // The project kinematics given (a moved inner arc instead of a clamped one), AVRIL with C20 > 0.
  a.element_type = "CPE6";
  a.fat.at("C20") = 0.05;
  a.muscle_dv = -0.04;
  a.axial_stretch = 0.98;
  a.inner_motion = std::array<double, 3>{0.03, -0.02, 4.0};
  a.reference = 0.6;  // both shares of the garment's load
  check_residual_derivatives(a, "kinematics-cpe6");
  a.element_type = "CPE6H";
  check_residual_derivatives(a, "kinematics-cpe6h");

  SectorCase b;
  b.muscle_law = "REDUCED POLYNOMIAL, N=2";
  b.muscle = {{"C10", 0.4}, {"C20", 0.05}, {"D1", 0.2}, {"D2", 0.5}};
  b.fat_law = "ARRUDA-BOYCE";
  b.fat = {{"MU", 0.6}, {"LAMBDA_M", 3.0}, {"D", 0.3}};
  b.reference = 0.3;
  check_residual_derivatives(b, "polynomial-arruda-cpe6");
  b.element_type = "CPE6H";
  check_residual_derivatives(b, "polynomial-arruda-cpe6h");

  // POLYNOMIAL with every term (N = 3: two data lines) and with the three-term Mooney-Rivlin of N = 2
  // (C20 < 0, C11 = C02 = 0: the mixed terms at 0).
  SectorCase d;
  d.muscle_law = "POLYNOMIAL, N=3";
  d.muscle = {{"C10", 0.4},   {"C01", 0.1},   {"C20", -0.02}, {"C11", 0.03}, {"C02", 0.01}, {"C30", 0.005},
              {"C21", -0.01}, {"C12", 0.004}, {"C03", 0.002}, {"D1", 0.2},   {"D2", 0.5},   {"D3", 1.0}};
  d.fat_law = "POLYNOMIAL, N=2";
  d.fat = {{"C10", 0.3}, {"C01", 0.05}, {"C20", -0.01}, {"C11", 0.0}, {"C02", 0.0}, {"D1", 0.3}, {"D2", 1.0}};
  check_residual_derivatives(d, "polynomial-cpe6");
  d.element_type = "CPE6H";
  check_residual_derivatives(d, "polynomial-cpe6h");

  SectorCase c;
  c.muscle_law = "NEO HOOKE";
  c.muscle = {{"C10", 0.4}, {"D1", 0.2}};
  c.fat_law = "ELASTIC";
  c.fat = {{"E", 5.0}, {"NU", 0.3}};
  c.tension = 0.05;  // St Venant-Kirchhoff softens in compression: a lighter garment
  check_residual_derivatives(c, "neohooke-elastic-cpe6");
  return calfit::testing::tally().finish();
}
