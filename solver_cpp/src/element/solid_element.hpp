// Plane-strain, total Lagrangian, finite-strain displacement element (T3 / T6).
//
// Weak form (Bonet & Wood, Nonlinear Continuum Mechanics for FEA, eq. 8.7 and 8.31):
//   f_a = integral over V0 of P grad0 N_a, with P = F S, F = I + grad0 u (F33 = 1),
//   K_ab = integral of [ (grad0 N_a . S grad0 N_b) I + B_a^T D B_b ],
// B_a mapping nodal displacement increments to the Green-Lagrange strain increment
// (engineering shear) and D the material tangent (Voigt 11, 22, 12 block).
#pragma once

#include "element/triangle.hpp"
#include "material/material.hpp"

#include <Eigen/Dense>
#include <vector>

namespace calfit {

using NodeMatrix = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::ColMajor, 6, 2>;      // nodes x 2
using ElementVector = Eigen::Matrix<double, Eigen::Dynamic, 1, Eigen::ColMajor, 12, 1>;   // 2 nodes
using ElementMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::ColMajor, 12, 12>;

// State at the integration points, for output.
struct ElementState {
  Mat3 cauchy = Mat3::Zero();  // volume average of the Cauchy stress
  double J = 1.0;              // volume average of det F
  double min_J = 1.0;
};

class SolidElement {
public:
  // X: reference coordinates of the element's nodes (nodes x 2).
  SolidElement(ElementShape shape, const NodeMatrix& X, const Material& material, double thickness,
               int quadrature_degree);

  ElementShape shape() const { return shape_; }
  int dof_count() const { return 2 * node_count(shape_); }
  // Smallest det(dX/dxi) over the integration points, for mesh checks.
  double min_reference_jacobian() const { return min_det_; }
  double reference_area() const;

  // Internal force f (dof_count) and, if K is given, the tangent, for nodal
  // displacements u (nodes x 2). Returns false when det F <= 0 at a point.
  bool internal_force(const NodeMatrix& u, ElementVector& f, ElementMatrix* K) const;
  ElementState state(const NodeMatrix& u) const;

private:
  struct Point {
    Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::ColMajor, 6, 2> dN_dX;
    double weight;  // quadrature weight x det J0 x thickness
  };
  ElementShape shape_;
  const Material* material_;
  std::vector<Point> points_;
  double min_det_ = 0;
};

}  // namespace calfit
