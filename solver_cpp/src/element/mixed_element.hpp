// Mixed u/p (hybrid) plane-strain elements for nearly and fully incompressible tissue.
//
// Two-field form of Simo & Taylor (1991, CMAME 85:273) with the pressure p a Lagrange
// multiplier of the volume constraint (Sussman & Bathe 1987, the formulation of the
// second paper, sec. 2.5):
//   Pi(u, p) = integral [ W_iso(C) + p J - G(p) ] dV,
//   G(p) = sup_Theta [ p Theta - U(Theta) ]  (Legendre transform of U; G = p when D1 = 0),
// so that stationarity in p gives J = G'(p), i.e. U'(J) = p, and p is the mean Cauchy
// stress (tension positive; the written "pressure" is -p). Residuals:
//   R_u = integral F (S_iso + p J C^-1) grad N,   R_p = integral N_p (J - G'(p)),
// tangent blocks K_uu (with p J C^-1 in S and d(J C^-1)/dE = J C^-1 (x) C^-1 - 2 J C^-1 (.) C^-1),
// K_up = K_pu^T = integral B^T (J C^-1) N_p, K_pp = -integral N_p N_p / U''(Theta): a
// symmetric saddle-point system.
//   CPE6H: T6 displacement, continuous linear pressure on the corner nodes (Taylor-Hood).
//   CPE3H: T3 displacement, constant pressure per element (as Abaqus CPE3H); it is the
//          "linear mixed element" whose pressure the second paper found oscillating.
#pragma once

#include "element/solid_element.hpp"

namespace calfit {

class MixedElement final : public Element {
public:
  MixedElement(ElementShape shape, const NodeMatrix& X, const SplitHyperelastic& material, double thickness,
               int quadrature_degree);
  // Pressure unknowns: 3 (linear, at the corners) for T6, 1 (constant) for T3.
  int pressure_count() const { return shape_ == ElementShape::T6 ? 3 : 1; }
  int dof_count() const override { return 2 * node_count(shape_) + pressure_count(); }
  bool internal_force(const ElementVector& ue, ElementVector& f, ElementMatrix* K) const override;
  ElementState state(const ElementVector& ue) const override;

private:
  Eigen::VectorXd pressure_shape(const ReferencePoint& p) const;
  ElementShape shape_;
  const SplitHyperelastic* material_;
  std::vector<ReferencePoint> points_;
};

}  // namespace calfit
