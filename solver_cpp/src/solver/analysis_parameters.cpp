// StaticAnalysis: what the parameter sensitivities (solver/sensitivity.hpp) need of the analysis: residuals
// with perturbed parameters, scoped to the elements a parameter touches, and solves with the converged tangent.
#include "solver/analysis_support.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace calfit {

using namespace analysis_support;

// ---- parameter sensitivities ------------------------------------------------------------

Eigen::VectorXd StaticAnalysis::residual(const Eigen::VectorXd& u) {
  if (!evaluate(u, 1.0, false).ok) throw std::runtime_error("the residual is not defined here: an element is inverted (det F <= 0)");
  return residual_;
}

StaticAnalysis::ParameterElement StaticAnalysis::element_for(const ParameterState& state, int e) const {
  const auto dv = state.loads.volume_change.find(e);
  return {make_element(model_, state.materials, e),
          ElementKinematics::from_volume_change(dv == state.loads.volume_change.end() ? 0.0 : dv->second,
                                                state.loads.axial_stretch)};
}

std::map<int, double> StaticAnalysis::prescribed_values(const LoadState& loads) const {
  std::map<int, double> values = loads.prescribed;
  // A rigid motion takes over both dofs of its nodes (the deck reader drops a *BOUNDARY
  // on them; a sensitivity copy may add a motion to a clamped set).
  for (const auto& [name, motion] : loads.rigid_motions)
    for (int node : motion.nodes) {
      const Eigen::Vector2d d = motion.displacement(model_.coordinates[node]);
      values[2 * node] = d.x();
      values[2 * node + 1] = d.y();
    }
  return values;
}

Eigen::VectorXd StaticAnalysis::scoped_residual(const ParameterState& state, const ParameterScope& scope,
                                                const Eigen::VectorXd& u_given) const {
  Eigen::VectorXd u = u_given;
  if (scope.prescribed)
    for (const auto& [dof, value] : prescribed_values(state.loads)) u[dof] = value;
  Eigen::VectorXd R = Eigen::VectorXd::Zero(n_dofs_);

  // Internal forces of the elements in scope, rebuilt with the state's materials.
  const int n = static_cast<int>(scope.elements.size());
  std::vector<ElementVector> forces(scope.elements.size());
  int failures = 0;
  // A thread team for a handful of elements costs more than it saves (and waits for
  // descheduled threads on a loaded machine).
#pragma omp parallel for schedule(static) reduction(+ : failures) if (n > 256)
  for (int k = 0; k < n; ++k) {
    const int e = scope.elements[k];
    if (!element_for(state, e).internal_force(local_unknowns(u, e), forces[k])) ++failures;
  }
  if (failures > 0)
    throw std::runtime_error("an element turns inside out (det F <= 0) where a sensitivity parameter moves the prescribed displacements");
  for (int k = 0; k < n; ++k) {
    const std::vector<int>& dofs = element_dofs_[scope.elements[k]];
    for (std::size_t i = 0; i < dofs.size(); ++i) R[dofs[i]] += forces[k][static_cast<Eigen::Index>(i)];
  }

  subtract_face_loads(state, scope.faces, u, R);
  return R;
}

Eigen::VectorXd StaticAnalysis::converged_scoped_residual(const ParameterScope& scope) {
  if (forces_lambda_ != last_lambda_ || forces_u_.size() != u_.size() || forces_u_ != u_) evaluate(u_, last_lambda_, false);
  Eigen::VectorXd R = Eigen::VectorXd::Zero(n_dofs_);
  for (int e : scope.elements) {
    const std::vector<int>& dofs = element_dofs_[e];
    for (std::size_t i = 0; i < dofs.size(); ++i) R[dofs[i]] += element_force_[e][static_cast<Eigen::Index>(i)];
  }
  subtract_face_loads(model_.parameter_state(), scope.faces, u_, R);
  return R;
}

void StaticAnalysis::subtract_face_loads(const ParameterState& state, const std::vector<std::pair<int, int>>& faces,
                                         const Eigen::VectorXd& u, Eigen::VectorXd& R) const {
  if (faces.empty()) return;
  const auto garment = laplace_faces(state.loads, state.profiles);
  for (const std::pair<int, int>& key : faces) {
    const FaceLoad f = unloaded_face(key);
    const std::vector<int>& dofs = element_dofs_[f.element];
    const std::vector<int> local = local_dofs(f.local);
    const EdgeNodes x = face_positions(f, u);
    EdgeVector fe;
    auto subtract = [&] {
      for (std::size_t k = 0; k < local.size(); ++k) R[dofs[local[k]]] -= fe[static_cast<Eigen::Index>(k)];
    };
    if (const auto p = state.loads.pressures.find(key); p != state.loads.pressures.end()) {
      follower_pressure_load(x, p->second, fe, nullptr);
      subtract();
    }
    if (const auto g = garment.find(key); g != garment.end()) {
      garment_load(x, g->second.tension, g->second.reference_pressure, fe, nullptr);
      subtract();
    }
  }
}

Eigen::VectorXd StaticAnalysis::element_pressures(const ParameterState& state, const ParameterScope& scope,
                                                  const Eigen::VectorXd& u) const {
  const int n = static_cast<int>(elements_.size());
  std::vector<char> in_scope(elements_.size(), 0);
  for (int e : scope.elements) in_scope[e] = 1;
  Eigen::VectorXd pressure(n);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < n; ++e) {
    const ElementVector ue = local_unknowns(u, e);
    const ElementState s = in_scope[e] ? element_for(state, e).state(ue) : elements_[e]->state(ue, kinematics(e, last_lambda_));
    pressure[e] = -s.cauchy.trace() / 3.0;
  }
  return pressure;
}

// Relative residual of the sensitivity solves. Its error in X is about as large (the
// residual is a smooth operator perturbation, (K_old - K) X, that K^-1 does not amplify
// much: 1e-7 residuals gave 1e-9 to 3e-7 errors on the leg slice), well inside the 1e-4
// the sensitivities are held to; near a converged Newton state the factorization of the
// last iteration usually meets it without a correction.
constexpr double kTangentSolveTolerance = 1e-6;

bool StaticAnalysis::solve_tangent(const Eigen::MatrixXd& B, Eigen::MatrixXd& X) {
  // Newton re-evaluates every accepted iterate with its tangent, so the matrix in
  // system_ is normally the converged state's already; anything evaluated since
  // (another tangent) is undone here.
  if (tangent_lambda_ != last_lambda_ || tangent_u_.size() != u_.size() || tangent_u_ != u_)
    if (!evaluate(u_, last_lambda_, true).ok) return false;
  const int n = system_->size();
  Eigen::MatrixXd rhs(n, B.cols()), x;
  for (int d = 0; d < n_dofs_; ++d)
    if (system_->equation(d) >= 0) rhs.row(system_->equation(d)) = B.row(d);
  if (!system_->solve_refined(rhs, x, kTangentSolveTolerance)) return false;
  X = Eigen::MatrixXd::Zero(n_dofs_, B.cols());
  for (int d = 0; d < n_dofs_; ++d)
    if (system_->equation(d) >= 0) X.row(d) = x.row(system_->equation(d));
  return true;
}

}  // namespace calfit
