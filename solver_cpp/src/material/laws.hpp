// The strain-energy laws of calfit-fe, as CalculiX/Abaqus define them, and the
// compressible neo-Hookean law of Avril et al. (2010), eq. (2).
#pragma once

#include "material/material.hpp"

#include <memory>
#include <string>
#include <utility>
#include <vector>

namespace calfit {

// Reduced polynomial W_iso = sum_i Ci0 (I1bar - 3)^i, i = 1..N (N = 1: neo-Hooke).
class ReducedPolynomialIsochoric final : public IsochoricEnergy {
public:
  explicit ReducedPolynomialIsochoric(std::vector<double> coefficients) : c_(std::move(coefficients)) {}
  IsochoricDerivatives evaluate(double I1bar, double I2bar) const override;
  std::string description() const override;

private:
  std::vector<double> c_;
};

// Mooney-Rivlin W_iso = C10 (I1bar - 3) + C01 (I2bar - 3).
class MooneyRivlinIsochoric final : public IsochoricEnergy {
public:
  MooneyRivlinIsochoric(double c10, double c01) : c10_(c10), c01_(c01) {}
  IsochoricDerivatives evaluate(double I1bar, double I2bar) const override;
  std::string description() const override;

private:
  double c10_, c01_;
};

// Polynomial W_iso = sum_{i+j=1..N} Cij (I1bar - 3)^i (I2bar - 3)^j (CalculiX manual, *HYPERELASTIC,
// the polynomial strain energy potential; N <= 3 there). N = 1 is Mooney-Rivlin, C01 = C11 = C02 = ... = 0
// the reduced polynomial. Any Cij may be negative, as in CalculiX (a softening C20, e.g.): the deck
// reader only asks C10 + C01 > 0, the initial shear modulus / 2.
class PolynomialIsochoric final : public IsochoricEnergy {
public:
  struct Term {
    int i, j;  // exponents of (I1bar - 3) and (I2bar - 3)
    double c;  // Cij
  };
  explicit PolynomialIsochoric(std::vector<Term> terms) : terms_(std::move(terms)) {}
  IsochoricDerivatives evaluate(double I1bar, double I2bar) const override;
  std::string description() const override;

private:
  std::vector<Term> terms_;
};

// The exponents (i, j) of the polynomial law's Cij for i + j = 1..order, in CalculiX's data-line order:
// by degree, then i from high to low (C10, C01, C20, C11, C02, C30, C21, C12, C03).
std::vector<std::pair<int, int>> polynomial_exponents(int order);

// Arruda-Boyce W_iso = mu sum_i a_i / lambda_m^(2i-2) (I1bar^i - 3^i), i = 1..5, with
// a = 1/2, 1/20, 11/1050, 19/7000, 519/673750 (CalculiX manual, *HYPERELASTIC).
class ArrudaBoyceIsochoric final : public IsochoricEnergy {
public:
  ArrudaBoyceIsochoric(double mu, double lambda_m);
  IsochoricDerivatives evaluate(double I1bar, double I2bar) const override;
  std::string description() const override;

private:
  double mu_, lambda_m_;
  double a_[5];
};

// U = sum_i (J - 1)^(2i) / Di (CalculiX polynomial forms); D1 = 0 is the
// incompressible constraint, Di = 0 for i > 1 drops the term.
class PolynomialVolumetric final : public VolumetricEnergy {
public:
  explicit PolynomialVolumetric(std::vector<double> d) : d_(std::move(d)) {}
  VolumetricDerivatives evaluate(double J) const override;
  bool is_constraint() const override { return d_.empty() || d_[0] == 0.0; }
  double dilatation(double p) const override;
  std::string description() const override;

private:
  std::vector<double> d_;
};

// U = K [(J^2 - 1)/2 - ln J]: Avril et al. eq. (2) with K = Kv, and the volumetric
// part of CalculiX's Arruda-Boyce law with K = 1/D.
class LogVolumetric final : public VolumetricEnergy {
public:
  explicit LogVolumetric(double bulk) : k_(bulk) {}
  VolumetricDerivatives evaluate(double J) const override;
  bool is_constraint() const override { return k_ == 0.0; }
  double dilatation(double p) const override;
  std::string description() const override;

private:
  double k_;
};

// A constitutive law as the deck gives it: the law's name (AVRIL, NEO HOOKE, MOONEY-RIVLIN,
// POLYNOMIAL, REDUCED POLYNOMIAL, ARRUDA-BOYCE, ELASTIC) and its data-line constants, named as
// solver_cpp/README.md names them (C10, D1, KV, ...), in data-line order. Kept with the
// material so that a sensitivity parameter can rebuild the law with one constant changed.
struct LawConstants {
  std::string law;
  std::vector<std::string> names;
  std::vector<double> values;
  int index(const std::string& name) const;  // -1 when the law has no constant of that name
};

// The constant names of a law in data-line order; POLYNOMIAL and REDUCED POLYNOMIAL take their order N.
std::vector<std::string> law_constant_names(const std::string& law, int order = 1);

// The law built from its constants. No range checks: the deck reader checks the values
// where it reads them, and sensitivities evaluate slightly perturbed copies.
std::shared_ptr<const Material> make_law(const LawConstants& constants);

}  // namespace calfit
