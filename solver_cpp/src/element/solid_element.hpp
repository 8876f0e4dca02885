// Plane-strain, total Lagrangian, finite-strain displacement element (T3 / T6).
//
// Weak form (Bonet & Wood, Nonlinear Continuum Mechanics for FEA, eq. 8.7 and 8.31):
//   f_a = integral over V0 of P grad0 N_a, with P = F S, F = I + grad0 u (F33 = 1),
//   K_ab = integral of [ (grad0 N_a . S grad0 N_b) I + B_a^T D B_b ],
// B_a mapping nodal displacement increments to the Green-Lagrange strain increment
// (engineering shear) and D the material tangent (Voigt 11, 22, 12 block).
// Generalized plane strain (F33 = lambda_z, fixed per step) and a growth eigenstrain
// (F = F_e g I) change only the stress and tangent that enter these integrals (see
// ElementKinematics): E33 is prescribed, so it is not varied.
#pragma once

#include "element/element.hpp"
#include "element/triangle.hpp"

#include <Eigen/Dense>
#include <vector>

namespace calfit {

// Integration points of a T3/T6 in the reference configuration, shared by the
// displacement and the mixed elements.
struct ReferencePoint {
  NodeMatrix dN_dX;       // nodes x 2
  Eigen::Vector3d L;      // area coordinates (the P1 pressure shape functions)
  double weight;          // quadrature weight x det J0 x thickness
};
std::vector<ReferencePoint> reference_points(ElementShape shape, const NodeMatrix& X, double thickness,
                                             int quadrature_degree, double* min_det);
Eigen::Matrix2d deformation_gradient(const NodeMatrix& u, const NodeMatrix& dN_dX);
// C = F^T F of F = [F2 0; 0 lambda_z].
Mat3 right_cauchy_green(const Eigen::Matrix2d& F, double axial_stretch = 1.0);
// Stress S and tangent D of a material whose stress-free state has grown by F_g = g I:
// W(C) = g^3 W_e(C / g^2), so S = 2 dW/dC = g S_e(C / g^2) and D = 4 d2W/dCdC = D_e(C / g^2) / g
// (Rodriguez, Hoger & McCulloch 1994; Holzapfel, Nonlinear Solid Mechanics, sec. 6.1
// for S = 2 dW/dC). elastic(C, S, D) evaluates S_e and D_e.
template <typename ElasticStress>
void stress_with_growth(ElasticStress elastic, const Mat3& C, double g, Mat3& S, Mat6* D) {
  if (g == 1.0) {
    elastic(C, S, D);
    return;
  }
  elastic(Mat3(C / (g * g)), S, D);
  S *= g;
  if (D) *D /= g;
}
// Rows dE11, dE22, 2 dE12 per nodal displacement component (3 x 2n).
Eigen::Matrix<double, 3, Eigen::Dynamic, Eigen::RowMajor, 3, 12> strain_operator(const Eigen::Matrix2d& F,
                                                                                 const NodeMatrix& dN_dX);
// Adds w [B^T D B + geometric stiffness of S] into the displacement block of K.
void add_displacement_tangent(const ReferencePoint& p, const Eigen::Matrix2d& F, const Mat3& S, const Mat6& D,
                              ElementMatrix& K);
// Nodal displacements (nodes x 2) from the interleaved local vector.
NodeMatrix nodal_displacements(const ElementVector& ue, int n_nodes);

// Volume averages of the Cauchy stress sigma = F S F^T / J and of J = lambda_z det F2 over
// the points (F the 3x3 gradient with F33 = lambda_z); second_pk(point, C) gives the
// second Piola-Kirchhoff stress S at a point.
template <typename SecondPK>
ElementState average_state(const std::vector<ReferencePoint>& points, const NodeMatrix& u, double axial_stretch,
                           SecondPK second_pk) {
  ElementState out;
  out.J = 0.0;
  double volume = 0.0;
  bool first = true;
  for (const ReferencePoint& p : points) {
    const Eigen::Matrix2d F2 = deformation_gradient(u, p.dN_dX);
    Mat3 F = Mat3::Zero();
    F.topLeftCorner<2, 2>() = F2;
    F(2, 2) = axial_stretch;
    const double J = axial_stretch * F2.determinant();
    out.min_J = first ? J : std::min(out.min_J, J);
    first = false;
    if (J <= 0.0) continue;
    const Mat3 S = second_pk(p, right_cauchy_green(F2, axial_stretch));
    out.cauchy += p.weight * (F * S * F.transpose()) / J;
    out.J += p.weight * J;
    volume += p.weight;
  }
  if (volume > 0.0) {
    out.cauchy /= volume;
    out.J /= volume;
  }
  return out;
}

class SolidElement final : public Element {
public:
  // X: reference coordinates of the element's nodes (nodes x 2).
  SolidElement(ElementShape shape, const NodeMatrix& X, const Material& material, double thickness,
               int quadrature_degree);

  ElementShape shape() const { return shape_; }
  int dof_count() const override { return 2 * node_count(shape_); }
  // Smallest det(dX/dxi) over the integration points, for mesh checks.
  double min_reference_jacobian() const { return min_det_; }
  double reference_area() const;

  bool internal_force(const ElementVector& ue, const ElementKinematics& kin, ElementVector& f,
                      ElementMatrix* K) const override;
  ElementState state(const ElementVector& ue, const ElementKinematics& kin) const override;

private:
  ElementShape shape_;
  const Material* material_;
  double min_det_ = 0;  // before points_: set while they are built
  std::vector<ReferencePoint> points_;
};

}  // namespace calfit
