// Plane-strain, total Lagrangian, finite-strain displacement element (T3 / T6).
//
// Weak form (Bonet & Wood, Nonlinear Continuum Mechanics for FEA, eq. 8.7 and 8.31):
//   f_a = integral over V0 of P grad0 N_a, with P = F S, F = I + grad0 u (F33 = 1),
//   K_ab = integral of [ (grad0 N_a . S grad0 N_b) I + B_a^T D B_b ],
// B_a mapping nodal displacement increments to the Green-Lagrange strain increment
// (engineering shear) and D the material tangent (Voigt 11, 22, 12 block).
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
Mat3 right_cauchy_green(const Eigen::Matrix2d& F);
// Rows dE11, dE22, 2 dE12 per nodal displacement component (3 x 2n).
Eigen::Matrix<double, 3, Eigen::Dynamic, Eigen::RowMajor, 3, 12> strain_operator(const Eigen::Matrix2d& F,
                                                                                 const NodeMatrix& dN_dX);
// Adds w [B^T D B + geometric stiffness of S] into the displacement block of K.
void add_displacement_tangent(const ReferencePoint& p, const Eigen::Matrix2d& F, const Mat3& S, const Mat6& D,
                              ElementMatrix& K);
// Nodal displacements (nodes x 2) from the interleaved local vector.
NodeMatrix nodal_displacements(const ElementVector& ue, int n_nodes);

// Volume averages of the Cauchy stress sigma = F S F^T / J and of J over the points;
// second_pk(point, C) gives the second Piola-Kirchhoff stress S at a point.
template <typename SecondPK>
ElementState average_state(const std::vector<ReferencePoint>& points, const NodeMatrix& u, SecondPK second_pk) {
  ElementState out;
  out.J = 0.0;
  double volume = 0.0;
  bool first = true;
  for (const ReferencePoint& p : points) {
    const Eigen::Matrix2d F2 = deformation_gradient(u, p.dN_dX);
    Mat3 F = Mat3::Identity();
    F.topLeftCorner<2, 2>() = F2;
    const double J = F2.determinant();
    out.min_J = first ? J : std::min(out.min_J, J);
    first = false;
    if (J <= 0.0) continue;
    const Mat3 S = second_pk(p, right_cauchy_green(F2));
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

  bool internal_force(const ElementVector& ue, ElementVector& f, ElementMatrix* K) const override;
  ElementState state(const ElementVector& ue) const override;

private:
  ElementShape shape_;
  const Material* material_;
  double min_det_ = 0;  // before points_: set while they are built
  std::vector<ReferencePoint> points_;
};

}  // namespace calfit
