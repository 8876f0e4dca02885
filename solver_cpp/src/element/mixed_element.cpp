// Mixed u/p elements: see mixed_element.hpp for the formulation.
#include "element/mixed_element.hpp"

namespace calfit {
namespace {

// d(J C^-1)/dE in Voigt form (Holzapfel eq. 6.166 with dJ/dC = J C^-1 / 2).
Mat6 jacobian_inverse_tangent(const Mat3& Cinv, double J) {
  Mat6 D;
  for (int a = 0; a < 6; ++a)
    for (int b = 0; b < 6; ++b) {
      const int i = kVoigtI[a], j = kVoigtJ[a], k = kVoigtI[b], l = kVoigtJ[b];
      D(a, b) = J * (Cinv(i, j) * Cinv(k, l) - (Cinv(i, k) * Cinv(j, l) + Cinv(i, l) * Cinv(j, k)));
    }
  return D;
}

}  // namespace

MixedElement::MixedElement(ElementShape shape, const NodeMatrix& X, const SplitHyperelastic& material,
                           double thickness, int quadrature_degree)
    : shape_(shape), material_(&material), points_(reference_points(shape, X, thickness, quadrature_degree, nullptr)) {}

Eigen::VectorXd MixedElement::pressure_shape(const ReferencePoint& p) const {
  if (shape_ == ElementShape::T6) return p.L;
  return Eigen::VectorXd::Ones(1);
}

bool MixedElement::internal_force(const ElementVector& ue, const ElementKinematics& kin, ElementVector& f,
                                  ElementMatrix* K) const {
  const int n = node_count(shape_), nu = 2 * n, np = pressure_count();
  const NodeMatrix u = nodal_displacements(ue, n);
  const Eigen::VectorXd pressures = ue.segment(nu, np);
  const VolumetricEnergy& volumetric = material_->volumetric();
  const double g = kin.growth, grown_volume = g * g * g;  // J_g = g^3
  const auto isochoric = [this](const Mat3& C, Mat3& S, Mat6* D) { material_->isochoric_stress(C, S, D); };
  f.setZero(nu + np);
  if (K) K->setZero(nu + np, nu + np);
  Mat3 S;
  Mat6 D;
  for (const ReferencePoint& q : points_) {
    const Eigen::Matrix2d F = deformation_gradient(u, q.dN_dX);
    const double J = kin.axial_stretch * F.determinant();
    if (J <= 0.0) return false;
    const Mat3 C = right_cauchy_green(F, kin.axial_stretch);
    const Mat3 Cinv = C.inverse();
    const Eigen::VectorXd Np = pressure_shape(q);
    const double p = Np.dot(pressures);
    stress_with_growth(isochoric, C, g, S, K ? &D : nullptr);
    S += p * J * Cinv;
    const Eigen::Matrix2d P = F * S.topLeftCorner<2, 2>();
    for (int a = 0; a < n; ++a) f.segment<2>(2 * a) += q.weight * P * q.dN_dX.row(a).transpose();
    const double theta = volumetric.dilatation(p);  // J_e at which U'(J_e) = p
    f.segment(nu, np) += q.weight * (J - grown_volume * theta) * Np;
    if (!K) continue;

    D += p * jacobian_inverse_tangent(Cinv, J);
    add_displacement_tangent(q, F, S, D, *K);
    const auto B = strain_operator(F, q.dN_dX);
    const Eigen::Vector3d JCinv(J * Cinv(0, 0), J * Cinv(1, 1), J * Cinv(0, 1));
    const Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 12, 1> dJ_du = B.transpose() * JCinv;
    K->block(0, nu, nu, np) += q.weight * dJ_du * Np.transpose();
    K->block(nu, 0, np, nu) += q.weight * Np * dJ_du.transpose();
    if (!volumetric.is_constraint())
      K->block(nu, nu, np, np) -= q.weight * grown_volume / volumetric.evaluate(theta).d2U * Np * Np.transpose();
  }
  return true;
}

ElementState MixedElement::state(const ElementVector& ue, const ElementKinematics& kin) const {
  const int n = node_count(shape_);
  const Eigen::VectorXd pressures = ue.segment(2 * n, pressure_count());
  const auto isochoric = [this](const Mat3& C, Mat3& S, Mat6* D) { material_->isochoric_stress(C, S, D); };
  return average_state(points_, nodal_displacements(ue, n), kin.axial_stretch, [&](const ReferencePoint& q, const Mat3& C) {
    Mat3 S;
    stress_with_growth(isochoric, C, kin.growth, S, nullptr);
    return Mat3(S + pressure_shape(q).dot(pressures) * std::sqrt(C.determinant()) * C.inverse());
  });
}

}  // namespace calfit
