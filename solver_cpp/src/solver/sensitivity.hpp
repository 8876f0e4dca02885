// Parameter sensitivities du/dtheta of the converged solution, by direct differentiation.
//
// At the converged end of the last step, R(u(theta), theta) = 0 for every value of a
// parameter theta, so that (Kleiber, Antunez, Hien & Kowalczyk, Parameter Sensitivity
// in Nonlinear Mechanics, Wiley 1997, ch. 3)
//   K du/dtheta = -dR/dtheta |_u,      K = dR/du at the converged u,            (1)
// one back-substitution per parameter on the converged tangent; all parameters are the
// columns of one multi-right-hand-side solve (StaticAnalysis::solve_tangent). With
// hybrid elements u holds the pressure unknowns too and K is the saddle-point tangent.
//
// dR/dtheta is the semi-analytic central difference of the residual at fixed u,
//   dR/dtheta = [R(u; theta + h) - R(u; theta - h)] / 2h,  h = 1e-4 (|theta| or scale), (2)
// evaluated over the elements and faces the parameter touches (ParameterScope) with the
// model's materials, profiles and last-step loads replaced by a copy in which the
// parameter's setter changed theta; its error is O(h^2) ~ 1e-8. Where R is affine in
// theta (SensitivityParameter::affine: the C's, MU, E, TENSION, profile coefficients)
// one evaluation is exact up to round-off, with the converged residual that Newton
// already computed:
//   dR/dtheta = [R(u; theta + H) - R(u; theta)] / H,      H = |theta| or scale.      (3)
// A parameter that moves prescribed displacements (scope.prescribed) shifts u_p with
// theta in (2), which brings K_fp du_p/dtheta into the free rows, and du_p/dtheta is
// the difference of the prescribed values.
//
// Through Coulomb friction (Kleiber et al. ch. 5, path-dependent problems; Michaleris, Tortorelli & Vidal,
// IJNME 37 (1994) 2471-2499): the converged state of increment n+1 solves R(u_n+1, h_n; theta) = 0, where h_n is
// the contact history it started from (each slave node's anchor xi on the master, shear and open gap), and it
// leaves h_n+1 = H(u_n+1, h_n). Differentiated along the path, one solve per converged increment:
//   K du_n+1/dtheta = -dR/dtheta |_u,h - dR/dh dh_n/dtheta,                                 (4)
//   dh_n+1/dtheta = dH/du du_n+1/dtheta + dH/dh dh_n/dtheta,                                 (5)
// from dh_0/dtheta = 0 (the reference state), with the local derivatives of the contact element exact by complex
// step (contact_history_derivatives) and dR/dtheta by (2) under the increment's kinematics. The stick/slip states
// and the anchors' segments are those of the converged path, as in any direct differentiation of it. The
// parameters must act on the elements alone there: material constants, or a volume change or the axial stretch
// that the last step brings in, which ramps with it (the deck reader says so otherwise). du/dtheta of the last
// increment is (1)'s answer.
//
// Pressure sensitivities (*SENSITIVITY, PRESSURE=YES): the element pressure
// p_e = -tr(sigma)/3 differentiated along the solution path,
//   dp_e/dtheta = [p_e(u + h du/dtheta; theta + h) - p_e(u - h du/dtheta; theta - h)] / 2h.
#pragma once

#include "model/model.hpp"
#include "solver/static_analysis.hpp"

#include <Eigen/Dense>
#include <string>
#include <vector>

namespace calfit {

struct ParameterSensitivity {
  std::string name;
  double value = 0.0;         // the parameter's value in the model
  double step = 0.0;          // h of (2), also the step of the pressure difference
  Eigen::VectorXd du;         // du/dtheta: 2 n_nodes displacements, then hybrid pressures
  Eigen::VectorXd dpressure;  // dp_e/dtheta per element; empty unless asked
  double max_abs_du = 0.0;    // over the displacement components
};

class SensitivityAnalysis {
public:
  static constexpr double kRelativeStep = 1e-4;

  // `analysis` holds the converged last step of `model`.
  SensitivityAnalysis(const Model& model, StaticAnalysis& analysis);

  // dR/dtheta, (2) or (3), at the converged solution, one column per requested parameter.
  Eigen::MatrixXd residual_derivatives() const;
  // Solves (1) for every requested parameter (deck order), with dp/dtheta when the deck
  // asks. Throws std::runtime_error when the tangent is singular.
  std::vector<ParameterSensitivity> compute() const;

private:
  double step(const SensitivityParameter& p) const;
  ParameterState at(const SensitivityParameter& p, double value) const;  // a copy with theta = value

  const Model& model_;
  StaticAnalysis& analysis_;
  ParameterState base_;
};

}  // namespace calfit
