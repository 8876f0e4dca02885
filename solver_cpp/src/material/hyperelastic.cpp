// Stress and tangent of W = W_iso(I1bar, I2bar) + U(J) through the invariants of C.
//
// With psi(I1, I2, I3) = W_iso(I1 I3^(-1/3), I2 I3^(-2/3)) + U(I3^(1/2)) and
//   dI1/dC = I,  dI2/dC = I1 I - C,  dI3/dC = I3 C^-1          (Holzapfel eq. 2.169-2.171)
// the second Piola-Kirchhoff stress is S = 2 sum_i psi_i A_i (Holzapfel eq. 6.32) and
// the tangent CC = 4 [ sum_ij psi_ij A_i (x) A_j + psi_2 (I (x) I - II)
//                    + psi_3 I3 (C^-1 (x) C^-1 - C^-1 (.) C^-1) ]      (Holzapfel eq. 6.193)
// where II is the symmetric fourth-order identity and (C^-1 (.) C^-1)_ijkl =
// (Cinv_ik Cinv_jl + Cinv_il Cinv_jk) / 2. The derivatives psi_i, psi_ij follow from
// the chain rule through I1bar, I2bar and J below.
#include "material/material.hpp"

#include <cmath>
#include <sstream>

namespace calfit {
namespace {

double delta(int i, int j) { return i == j ? 1.0 : 0.0; }

struct InvariantDerivatives {
  Eigen::Vector3d first;   // psi_1, psi_2, psi_3
  Eigen::Matrix3d second;  // psi_ij
  double energy = 0;
};

InvariantDerivatives chain_rule(const IsochoricEnergy& iso, const VolumetricEnergy& vol, double I1, double I2,
                                double I3) {
  const double J = std::sqrt(I3);
  const double s = std::pow(I3, -1.0 / 3.0);  // I1bar = I1 s
  const double q = s * s;                     // I2bar = I2 q
  const double ds = -s / (3.0 * I3), d2s = 4.0 * s / (9.0 * I3 * I3);
  const double dq = -2.0 * q / (3.0 * I3), d2q = 10.0 * q / (9.0 * I3 * I3);

  const IsochoricDerivatives w = iso.evaluate(I1 * s, I2 * q);
  const VolumetricDerivatives u = vol.evaluate(J);

  const Eigen::Vector3d g1(s, 0.0, I1 * ds);           // d I1bar / d(I1, I2, I3)
  const Eigen::Vector3d g2(0.0, q, I2 * dq);           // d I2bar / d(I1, I2, I3)
  const Eigen::Vector3d gJ(0.0, 0.0, 0.5 / J);         // d J / d(I1, I2, I3)
  Eigen::Matrix3d h1 = Eigen::Matrix3d::Zero(), h2 = Eigen::Matrix3d::Zero(), hJ = Eigen::Matrix3d::Zero();
  h1(0, 2) = h1(2, 0) = ds;
  h1(2, 2) = I1 * d2s;
  h2(1, 2) = h2(2, 1) = dq;
  h2(2, 2) = I2 * d2q;
  hJ(2, 2) = -0.25 / (J * J * J);

  InvariantDerivatives d;
  d.energy = w.W + u.U;
  d.first = w.W1 * g1 + w.W2 * g2 + u.dU * gJ;
  d.second = w.W11 * g1 * g1.transpose() + w.W12 * (g1 * g2.transpose() + g2 * g1.transpose()) +
             w.W22 * g2 * g2.transpose() + u.d2U * gJ * gJ.transpose() + w.W1 * h1 + w.W2 * h2 + u.dU * hJ;
  return d;
}

}  // namespace

double SplitHyperelastic::energy(const Mat3& C) const {
  const double I1 = C.trace();
  const double I2 = 0.5 * (I1 * I1 - (C * C).trace());
  const double I3 = C.determinant();
  return iso_->evaluate(I1 * std::pow(I3, -1.0 / 3.0), I2 * std::pow(I3, -2.0 / 3.0)).W +
         vol_->evaluate(std::sqrt(I3)).U;
}

namespace {

// U = 0: the isochoric response alone.
class NoVolumetricEnergy final : public VolumetricEnergy {
public:
  VolumetricDerivatives evaluate(double) const override { return {}; }
  std::string description() const override { return "none"; }
};

void invariant_stress(const IsochoricEnergy& iso, const VolumetricEnergy& vol, const Mat3& C, Mat3& S, Mat6* tangent) {
  const Mat3 I = Mat3::Identity();
  const double I1 = C.trace();
  const double I2 = 0.5 * (I1 * I1 - (C * C).trace());
  const double I3 = C.determinant();
  const Mat3 Cinv = C.inverse();
  const InvariantDerivatives d = chain_rule(iso, vol, I1, I2, I3);

  const Mat3 A[3] = {I, I1 * I - C, I3 * Cinv};
  S = 2.0 * (d.first(0) * A[0] + d.first(1) * A[1] + d.first(2) * A[2]);
  if (!tangent) return;

  // Av(m, a) = A_m in Voigt position a, so that sum_mn psi_mn A_m (x) A_n = Av^T psi Av.
  Eigen::Matrix<double, 3, 6> Av;
  for (int m = 0; m < 3; ++m)
    for (int a = 0; a < 6; ++a) Av(m, a) = A[m](kVoigtI[a], kVoigtJ[a]);
  Mat6& D = *tangent;
  D.noalias() = Av.transpose() * d.second * Av;
  for (int a = 0; a < 6; ++a) {
    const int i = kVoigtI[a], j = kVoigtJ[a];
    for (int b = 0; b < 6; ++b) {
      const int k = kVoigtI[b], l = kVoigtJ[b];
      const double sym_identity = 0.5 * (delta(i, k) * delta(j, l) + delta(i, l) * delta(j, k));
      D(a, b) += d.first(1) * (delta(i, j) * delta(k, l) - sym_identity) +
                 d.first(2) * I3 *
                     (Cinv(i, j) * Cinv(k, l) - 0.5 * (Cinv(i, k) * Cinv(j, l) + Cinv(i, l) * Cinv(j, k)));
    }
  }
  D *= 4.0;
}

}  // namespace

void SplitHyperelastic::stress(const Mat3& C, Mat3& S, Mat6* tangent) const {
  invariant_stress(*iso_, *vol_, C, S, tangent);
}

void SplitHyperelastic::isochoric_stress(const Mat3& C, Mat3& S, Mat6* tangent) const {
  static const NoVolumetricEnergy none;
  invariant_stress(*iso_, none, C, S, tangent);
}

double VolumetricEnergy::dilatation(double p) const {
  if (is_constraint()) return 1.0;
  double theta = 1.0;
  for (int it = 0; it < 50; ++it) {
    const VolumetricDerivatives u = evaluate(theta);
    const double step = (u.dU - p) / u.d2U;
    double next = theta - step;
    if (next <= 0.0) next = 0.5 * theta;  // U is convex with U -> infinity as Theta -> 0
    if (std::abs(next - theta) <= 1e-15 * theta) return next;
    theta = next;
  }
  return theta;
}

StVenantKirchhoff::StVenantKirchhoff(double young, double poisson)
    : young_(young),
      poisson_(poisson),
      lambda_(young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))),
      mu_(young / (2.0 * (1.0 + poisson))) {}

double StVenantKirchhoff::energy(const Mat3& C) const {
  const Mat3 E = 0.5 * (C - Mat3::Identity());
  const double trE = E.trace();
  return 0.5 * lambda_ * trE * trE + mu_ * (E.array() * E.array()).sum();
}

void StVenantKirchhoff::stress(const Mat3& C, Mat3& S, Mat6* tangent) const {
  const Mat3 E = 0.5 * (C - Mat3::Identity());
  S = lambda_ * E.trace() * Mat3::Identity() + 2.0 * mu_ * E;
  if (!tangent) return;
  Mat6& D = *tangent;
  D.setZero();
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) D(a, b) = lambda_;
    D(a, a) += 2.0 * mu_;
    D(a + 3, a + 3) = mu_;
  }
}

std::string StVenantKirchhoff::description() const {
  std::ostringstream out;
  out << "St Venant-Kirchhoff (E=" << young_ << ", nu=" << poisson_ << ")";
  return out.str();
}

}  // namespace calfit
