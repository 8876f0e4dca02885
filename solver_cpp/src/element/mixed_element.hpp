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
//
// Growth eigenstrain and axial stretch (ElementKinematics). With F = F_e g I and
// W = g^3 [W_iso(C_e) + U(J_e)], C_e = C / g^2, J_e = J / g^3 (J = lambda_z det F2), the
// same Legendre transform applied to g^3 U(J / g^3) gives
//   Pi(u, p) = integral [ g^3 W_iso(C / g^2) + p J - g^3 G(p) ] dV,
// since sup_p [p J - g^3 G(p)] = g^3 sup_p [p J_e - G(p)] = g^3 U(J_e). Hence
//   R_u = integral F (g S_iso(C / g^2) + p J C^-1) grad N,   R_p = integral N_p (J - g^3 G'(p)),
//   K_pp = -integral g^3 N_p N_p / U''(Theta),  isochoric tangent D_iso(C / g^2) / g,
// i.e. the constraint acts on J_e = J / g^3 (J_e = 1 when D1 = 0) and the volumes scale
// with g^3; p stays the mean Cauchy stress. (Growth split of Rodriguez, Hoger &
// McCulloch 1994, J. Biomech. 27:455; isotropic growth in FE: Himpel, Kuhl, Menzel &
// Steinmann 2005, CMES 8:119; the mixed form above is Simo & Taylor's with W_e.)
//
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
  bool internal_force(const ElementVector& ue, const ElementKinematics& kin, ElementVector& f,
                      ElementMatrix* K) const override;
  ElementState state(const ElementVector& ue, const ElementKinematics& kin) const override;

private:
  Eigen::VectorXd pressure_shape(const ReferencePoint& p) const;
  ElementShape shape_;
  const SplitHyperelastic* material_;
  std::vector<ReferencePoint> points_;
};

}  // namespace calfit
