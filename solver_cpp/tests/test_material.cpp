// Material unit tests: stress against central finite differences of the energy,
// tangent against central finite differences of the stress, and a stress-free
// reference state, for every law calfit-fe reads, at plane-strain and general C; and the
// polynomial law against the Mooney-Rivlin and reduced polynomial laws it contains.
#include "check.hpp"
#include "material/laws.hpp"

#include <memory>
#include <string>
#include <vector>

using namespace calfit;

namespace {

struct Law {
  std::string name;
  std::shared_ptr<const Material> material;
};

std::vector<Law> laws() {
  using std::make_shared;
  auto split = [](std::shared_ptr<const IsochoricEnergy> iso, std::shared_ptr<const VolumetricEnergy> vol) {
    return make_shared<SplitHyperelastic>(std::move(iso), std::move(vol));
  };
  return {
      {"neo-Hooke", split(make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.0}),
                          make_shared<PolynomialVolumetric>(std::vector<double>{0.1}))},
      {"Mooney-Rivlin", split(make_shared<MooneyRivlinIsochoric>(0.8, 0.3),
                              make_shared<PolynomialVolumetric>(std::vector<double>{0.05}))},
      {"reduced polynomial N=3",
       split(make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.0, 0.4, 0.2}),
             make_shared<PolynomialVolumetric>(std::vector<double>{0.1, 0.5, 2.0}))},
      {"Arruda-Boyce", split(make_shared<ArrudaBoyceIsochoric>(2.0, 1.5), make_shared<LogVolumetric>(10.0))},
      {"Avril", split(make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.0}), make_shared<LogVolumetric>(10.0))},
      // Avril with the C20 (I1bar - 3)^2 term of the `stiffening` effect (*HYPERELASTIC, AVRIL: C10, Kv, C20).
      {"Avril with C20",
       split(make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.0, 0.35}), make_shared<LogVolumetric>(10.0))},
      {"St Venant-Kirchhoff", make_shared<StVenantKirchhoff>(10.0, 0.3)},
      // Every term of the polynomial law, a softening C20 < 0 and negative mixed terms among them.
      {"polynomial N=3", make_law({"POLYNOMIAL", law_constant_names("POLYNOMIAL", 3),
                                   {0.8, 0.3, -0.04, 0.05, 0.02, 0.01, -0.03, 0.015, 0.006, 0.1, 0.5, 2.0}})},
  };
}

constexpr const int* I = kVoigtI;
constexpr const int* J = kVoigtJ;

Mat3 symmetric_perturbation(int a, double h) {
  Mat3 d = Mat3::Zero();
  d(I[a], J[a]) += h;
  if (I[a] != J[a]) d(J[a], I[a]) += h;
  return d;
}

void check_law(const Law& law, const Mat3& F) {
  const Mat3 C = F.transpose() * F;
  Mat3 S;
  Mat6 D;
  law.material->stress(C, S, &D);
  const double scale = std::max(1.0, S.cwiseAbs().maxCoeff());

  // S_ij = 2 dW/dC_ij: a symmetric perturbation h of (ij, ji) changes W by S_ij h
  // (by S_ii h / 2 on the diagonal).
  const double h = 1e-6;
  for (int a = 0; a < 6; ++a) {
    const Mat3 dC = symmetric_perturbation(a, h);
    const double dW = law.material->energy(C + dC) - law.material->energy(C - dC);
    CHECK_NEAR(dW / (2.0 * h), (I[a] == J[a] ? 0.5 : 1.0) * S(I[a], J[a]), 1e-6 * scale);
  }
  // dS = D dE (Voigt, engineering shear): dE_ii = h is dC_ii = 2h, gamma_ij = h is dC_ij = h.
  for (int b = 0; b < 6; ++b) {
    const Mat3 dC = symmetric_perturbation(b, b < 3 ? 2.0 * h : h);
    Mat3 Sp, Sm;
    law.material->stress(C + dC, Sp, nullptr);
    law.material->stress(C - dC, Sm, nullptr);
    const Mat3 dS = (Sp - Sm) / (2.0 * h);
    double worst = 0.0;
    for (int a = 0; a < 6; ++a) worst = std::max(worst, std::abs(dS(I[a], J[a]) - D(a, b)));
    const double tscale = std::max(1.0, D.cwiseAbs().maxCoeff());
    if (worst > 1e-5 * tscale) std::cerr << law.name << ": tangent column " << b << " off by " << worst << '\n';
    CHECK(worst <= 1e-5 * tscale);
  }
  // Symmetric tangent (hyperelastic: D = 4 d2W/dCdC).
  CHECK((D - D.transpose()).cwiseAbs().maxCoeff() <= 1e-10 * std::max(1.0, D.cwiseAbs().maxCoeff()));
}

}  // namespace

int main() {
  Mat3 plane = Mat3::Identity();
  plane.topLeftCorner<2, 2>() << 1.12, 0.07, -0.04, 0.93;
  Mat3 general;
  general << 1.05, 0.10, -0.03, 0.02, 0.91, 0.06, -0.05, 0.04, 1.08;
  for (const Law& law : laws()) {
    check_law(law, plane);
    check_law(law, general);
    Mat3 S;
    law.material->stress(Mat3::Identity(), S, nullptr);
    CHECK(S.cwiseAbs().maxCoeff() < 1e-12);  // stress-free reference
    CHECK(std::abs(law.material->energy(Mat3::Identity())) < 1e-12);
  }
  // Small-strain limit of neo-Hooke: mu = 2 C10, K = 2 / D1 (CalculiX manual).
  {
    const SplitHyperelastic nh(std::make_shared<ReducedPolynomialIsochoric>(std::vector<double>{1.5}),
                               std::make_shared<PolynomialVolumetric>(std::vector<double>{0.2}));
    Mat3 S;
    Mat6 D;
    nh.stress(Mat3::Identity(), S, &D);
    const double mu = 3.0, K = 10.0;
    CHECK_NEAR(D(0, 0), K + 4.0 * mu / 3.0, 1e-10);
    CHECK_NEAR(D(0, 1), K - 2.0 * mu / 3.0, 1e-10);
    CHECK_NEAR(D(3, 3), mu, 1e-10);
  }
  // POLYNOMIAL: C10, C01, C20, C11, C02, ... in CalculiX's order; N = 1 is MOONEY-RIVLIN and, with
  // C01 = C11 = C02 = 0, N = 2 is REDUCED POLYNOMIAL, N = 2: the same stress and tangent to round-off.
  {
    CHECK(law_constant_names("POLYNOMIAL", 2) ==
          std::vector<std::string>({"C10", "C01", "C20", "C11", "C02", "D1", "D2"}));
    CHECK(law_constant_names("POLYNOMIAL", 3).size() == 12 && law_constant_names("POLYNOMIAL", 3)[8] == "C03");
    auto same = [](const Material& a, const Material& b, const Mat3& F) {
      const Mat3 C = F.transpose() * F;
      Mat3 Sa, Sb;
      Mat6 Da, Db;
      a.stress(C, Sa, &Da);
      b.stress(C, Sb, &Db);
      CHECK((Sa - Sb).cwiseAbs().maxCoeff() <= 1e-13 * Sa.cwiseAbs().maxCoeff());
      CHECK((Da - Db).cwiseAbs().maxCoeff() <= 1e-13 * Da.cwiseAbs().maxCoeff());
      CHECK_NEAR(a.energy(C), b.energy(C), 1e-14);
    };
    const auto polynomial1 = make_law({"POLYNOMIAL", law_constant_names("POLYNOMIAL", 1), {0.8, 0.3, 0.05}});
    const auto mooney = make_law({"MOONEY-RIVLIN", law_constant_names("MOONEY-RIVLIN"), {0.8, 0.3, 0.05}});
    const auto polynomial2 =
        make_law({"POLYNOMIAL", law_constant_names("POLYNOMIAL", 2), {1.0, 0.0, 0.4, 0.0, 0.0, 0.1, 0.5}});
    const auto reduced = make_law({"REDUCED POLYNOMIAL", law_constant_names("REDUCED POLYNOMIAL", 2), {1.0, 0.4, 0.1, 0.5}});
    same(*polynomial1, *mooney, plane);
    same(*polynomial1, *mooney, general);
    same(*polynomial2, *reduced, plane);
    same(*polynomial2, *reduced, general);
  }
  return calfit::testing::tally().finish();
}
