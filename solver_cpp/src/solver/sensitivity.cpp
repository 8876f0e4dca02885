// Direct-differentiation sensitivities: see sensitivity.hpp for the equations.
#include "solver/sensitivity.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace calfit {

SensitivityAnalysis::SensitivityAnalysis(const Model& model, StaticAnalysis& analysis)
    : model_(model), analysis_(analysis), base_(model.parameter_state()) {}

double SensitivityAnalysis::step(const SensitivityParameter& p) const {
  const double value = std::abs(p.get(base_));
  return kRelativeStep * (value > 0.0 ? value : p.scale);
}

ParameterState SensitivityAnalysis::at(const SensitivityParameter& p, double value) const {
  ParameterState state = base_;
  p.set(state, value);
  return state;
}

Eigen::MatrixXd SensitivityAnalysis::residual_derivatives() const {
  const std::vector<SensitivityParameter>& parameters = model_.sensitivity.parameters;
  const Eigen::VectorXd& u = analysis_.solution();
  Eigen::MatrixXd dR = analysis_.contact_parameter_derivatives();  // the contact's part (GAP PROFILE, SHAPE)
  for (std::size_t j = 0; j < parameters.size(); ++j) {
    const SensitivityParameter& p = parameters[j];
    const double theta = p.get(base_);
    auto column = dR.col(static_cast<Eigen::Index>(j));
    if (p.gap_surface >= 0) continue;  // the contact's alone
    if (!p.shape.empty()) {  // the elements' part (2) added to the contact's
      const double h = step(p);
      column += (analysis_.scoped_residual(at(p, theta + h), p.scope, u) -
                 analysis_.scoped_residual(at(p, theta - h), p.scope, u)) /
                (2.0 * h);
      continue;
    }
    if (p.affine) {  // (3): one evaluation, the converged residual kept from Newton
      const double h = theta != 0.0 ? std::abs(theta) : p.scale;
      column = (analysis_.scoped_residual(at(p, theta + h), p.scope, u) - analysis_.converged_scoped_residual(p.scope)) / h;
    } else {  // (2)
      const double h = step(p);
      column = (analysis_.scoped_residual(at(p, theta + h), p.scope, u) -
                analysis_.scoped_residual(at(p, theta - h), p.scope, u)) /
               (2.0 * h);
    }
  }
  return dR;
}

std::vector<ParameterSensitivity> SensitivityAnalysis::compute() const {
  const std::vector<SensitivityParameter>& parameters = model_.sensitivity.parameters;
  Eigen::MatrixXd du;
  if (analysis_.carries_path_sensitivities())  // (4), carried to the last increment
    du = analysis_.path_sensitivities();
  else if (!analysis_.solve_tangent(-residual_derivatives(), du))
    throw std::runtime_error("the tangent at the converged state is singular: no sensitivities");

  std::vector<ParameterSensitivity> out;
  const Eigen::VectorXd& u = analysis_.solution();
  for (std::size_t j = 0; j < parameters.size(); ++j) {
    const SensitivityParameter& p = parameters[j];
    ParameterSensitivity s;
    s.name = p.name;
    s.value = p.get(base_);
    s.step = step(p);
    s.du = du.col(static_cast<Eigen::Index>(j));
    const ParameterState plus = at(p, s.value + s.step), minus = at(p, s.value - s.step);
    if (p.scope.prescribed) {  // du_p/dtheta: the solve leaves prescribed rows at 0
      const auto high = analysis_.prescribed_values(plus.loads), low = analysis_.prescribed_values(minus.loads);
      for (const auto& [dof, value] : high) s.du[dof] = (value - low.at(dof)) / (2.0 * s.step);
    }
    s.max_abs_du = s.du.head(model_.dof_count()).cwiseAbs().maxCoeff();
    if (model_.sensitivity.pressure)
      s.dpressure = (analysis_.element_pressures(plus, p.scope, u + s.step * s.du) -
                     analysis_.element_pressures(minus, p.scope, u - s.step * s.du)) /
                    (2.0 * s.step);
    out.push_back(std::move(s));
  }
  return out;
}

}  // namespace calfit
