// StaticAnalysis: what the parameter sensitivities (solver/sensitivity.hpp) need of the analysis: residuals
// with perturbed parameters, scoped to the elements a parameter touches, and solves with the converged tangent.
#include "solver/analysis_support.hpp"
#include "solver/sensitivity.hpp"

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

ElementKinematics StaticAnalysis::end_of_step_kinematics(const ParameterState& state, int e) const {
  const auto dv = state.loads.volume_change.find(e);
  return ElementKinematics::from_volume_change(dv == state.loads.volume_change.end() ? 0.0 : dv->second,
                                               state.loads.axial_stretch);
}

StaticAnalysis::ParameterElement StaticAnalysis::element_for(const ParameterState& state, int e) const {
  return {make_element(model_, state.materials, e, &state.node_shifts), end_of_step_kinematics(state, e)};
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
  // Internal forces of the elements in scope, rebuilt with the state's materials.
  Eigen::VectorXd R = rebuilt_element_forces(
      state, scope.elements, [&](int e) { return end_of_step_kinematics(state, e); }, u,
      "an element turns inside out (det F <= 0) where a sensitivity parameter moves the prescribed displacements");
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

Eigen::VectorXd StaticAnalysis::rebuilt_element_forces(const ParameterState& state,
                                                       const std::vector<int>& elements,
                                                       const std::function<ElementKinematics(int)>& kinematics_of,
                                                       const Eigen::VectorXd& u, const char* inverted) const {
  const int n = static_cast<int>(elements.size());
  std::vector<ElementVector> forces(elements.size());
  int failures = 0;
  // A thread team for a handful of elements costs more than it saves (and waits for
  // descheduled threads on a loaded machine).
#pragma omp parallel for schedule(static) reduction(+ : failures) if (n > 256)
  for (int k = 0; k < n; ++k) {
    const int e = elements[k];
    if (!make_element(model_, state.materials, e, &state.node_shifts)
             ->internal_force(local_unknowns(u, e), kinematics_of(e), forces[k], nullptr))
      ++failures;
  }
  if (failures > 0) throw std::runtime_error(inverted);
  Eigen::VectorXd R = Eigen::VectorXd::Zero(n_dofs_);
  for (int k = 0; k < n; ++k) {
    const std::vector<int>& dofs = element_dofs_[elements[k]];
    for (std::size_t i = 0; i < dofs.size(); ++i) R[dofs[i]] += forces[k][static_cast<Eigen::Index>(i)];
  }
  return R;
}

Eigen::VectorXd StaticAnalysis::increment_residual(const ParameterState& state, const std::vector<int>& elements,
                                                   const Eigen::VectorXd& u) const {
  // state's loads are the last step's: before it they do not act, and in it they ramp from the step's start
  const bool last_step = current_step_ + 1 == static_cast<int>(model_.steps.size());
  auto kinematics_of = [&](int e) {
    if (!last_step) return kinematics(e, last_lambda_);
    const auto dv = state.loads.volume_change.find(e);
    return ElementKinematics::from_volume_change(
        ramp(volume_change_start_[e], dv == state.loads.volume_change.end() ? 0.0 : dv->second, last_lambda_),
        ramp(axial_stretch_start_, state.loads.axial_stretch, last_lambda_));
  };
  return rebuilt_element_forces(state, elements, kinematics_of, u,
                                "an element is inverted (det F <= 0) at a converged state");
}

// sensitivity.hpp, (4)-(5). The parameters are material constants, or a volume change or the axial stretch that
// the last step brings in (deck/keywords_sensitivity.cpp refuses others with friction): dR/dtheta at fixed u and
// history is that of the elements they act on, (2) under this increment's kinematics.
void StaticAnalysis::propagate_path_sensitivities() {
  const std::vector<SensitivityParameter>& parameters = model_.sensitivity.parameters;
  const auto n_parameters = static_cast<Eigen::Index>(parameters.size());
  const ParameterState base = model_.parameter_state();
  Eigen::MatrixXd B = Eigen::MatrixXd::Zero(n_dofs_, n_parameters);
  for (Eigen::Index j = 0; j < n_parameters; ++j) {
    const SensitivityParameter& p = parameters[static_cast<std::size_t>(j)];
    const double theta = p.get(base);
    const double h = SensitivityAnalysis::kRelativeStep * (theta != 0.0 ? std::abs(theta) : p.scale);
    ParameterState plus = base, minus = base;
    p.set(plus, theta + h);
    p.set(minus, theta - h);
    B.col(j) = -(increment_residual(plus, p.scope.elements, u_) - increment_residual(minus, p.scope.elements, u_)) /
               (2.0 * h);
  }
  auto positions = [&](const std::vector<int>& nodes) {
    Eigen::VectorXd x(2 * static_cast<Eigen::Index>(nodes.size()));
    for (std::size_t k = 0; k < nodes.size(); ++k)
      x.segment<2>(2 * static_cast<Eigen::Index>(k)) =
          model_.coordinates[nodes[k]] + u_.segment<2>(2 * static_cast<Eigen::Index>(nodes[k]));
    return x;
  };
  // The history's part of dR/dtheta: -dr/dh dh_n/dtheta over the touching slave nodes, (4); and the contact's own
  // part for GAP PROFILE and SHAPE parameters.
  const bool contact_parameters = has_contact_parameters();
  std::vector<std::vector<ContactHistoryDerivatives>> derivatives(contacts_.size());
  for (std::size_t ci = 0; ci < contacts_.size(); ++ci) {
    ContactState& c = contacts_[ci];
    if (c.law.friction <= 0.0) continue;
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      const std::vector<int>& nodes = c.element_nodes[i];
      if (nodes.empty()) {
        derivatives[ci].push_back({});
        continue;
      }
      derivatives[ci].push_back(contact_history_derivatives(positions(nodes), c.law, c.history[i], c.element_segment[i],
                                                            c.slave_weight[i], c.slave_offset[i]));
      if (!c.points[i].touching) continue;
      const ContactHistoryDerivatives& D = derivatives[ci].back();
      const Eigen::MatrixXd& dh = c.history_sensitivity[i];
      Eigen::MatrixXd dr = Eigen::MatrixXd::Zero(D.dr_dh.rows(), n_parameters);
      if (dh.size() != 0) dr += D.dr_dh * dh;
      if (contact_parameters) {
        Eigen::MatrixXd own, unused;
        contact_parameter_parts(c, i, D, own, unused);
        dr += own;
      }
      for (std::size_t k = 0; k < nodes.size(); ++k)
        for (int d = 0; d < 2; ++d) B.row(2 * nodes[k] + d) -= dr.row(2 * static_cast<Eigen::Index>(k) + d);
    }
  }
  if (contact_parameters) B -= contact_derivatives(true);
  if (!solve_tangent(B, path_du_))
    throw std::runtime_error("the tangent at a converged increment is singular: no sensitivities through friction");
  // The history each node leaves, (5).
  for (std::size_t ci = 0; ci < contacts_.size(); ++ci) {
    ContactState& c = contacts_[ci];
    if (c.law.friction <= 0.0) continue;
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      const std::vector<int>& nodes = c.element_nodes[i];
      if (nodes.empty() || !c.trial[i].anchored()) {
        c.history_sensitivity[i].resize(0, 0);
        continue;
      }
      const ContactHistoryDerivatives& D = derivatives[ci][i];
      Eigen::MatrixXd du_local(2 * static_cast<Eigen::Index>(nodes.size()), n_parameters);
      for (std::size_t k = 0; k < nodes.size(); ++k)
        du_local.middleRows(2 * static_cast<Eigen::Index>(k), 2) = path_du_.middleRows(2 * nodes[k], 2);
      Eigen::MatrixXd dh = D.dh_dx * du_local;
      if (c.history_sensitivity[i].size() != 0) dh += D.dh_dh * c.history_sensitivity[i];
      if (contact_parameters) {
        Eigen::MatrixXd unused, own;
        contact_parameter_parts(c, i, D, unused, own);
        dh += own;
      }
      c.history_sensitivity[i] = std::move(dh);
    }
  }
}

Eigen::MatrixXd StaticAnalysis::contact_parameter_derivatives() {
  if (!has_contact_parameters()) return Eigen::MatrixXd::Zero(n_dofs_, static_cast<Eigen::Index>(model_.sensitivity.parameters.size()));
  if (forces_lambda_ != last_lambda_ || forces_u_.size() != u_.size() || forces_u_ != u_) evaluate(u_, last_lambda_, false);
  return contact_derivatives(false);
}

bool StaticAnalysis::has_contact_parameters() const {
  return !shape_of_node_.empty() ||
         std::any_of(contacts_.begin(), contacts_.end(), [](const ContactState& c) { return c.gap_factors.size() != 0; });
}

void StaticAnalysis::contact_parameter_parts(const ContactState& c, std::size_t i, const ContactHistoryDerivatives& D,
                                             Eigen::MatrixXd& dr, Eigen::MatrixXd& dh) const {
  const auto n_parameters = static_cast<Eigen::Index>(model_.sensitivity.parameters.size());
  const std::vector<int>& nodes = c.element_nodes[i];
  // the positions' change per unit theta (SHAPE), the node's offset's (GAP PROFILE)
  Eigen::MatrixXd dx = Eigen::MatrixXd::Zero(2 * static_cast<Eigen::Index>(nodes.size()), n_parameters);
  for (std::size_t k = 0; k < nodes.size(); ++k)
    if (const auto moved = shape_of_node_.find(nodes[k]); moved != shape_of_node_.end())
      for (const auto& [j, direction] : moved->second) dx.block(2 * static_cast<Eigen::Index>(k), j, 2, 1) = direction;
  dr = D.dr_dx * dx;
  dh = D.dh_dx * dx;
  if (c.weight_derivatives.size() != 0)   // the residual is linear in the slave's weight
    dr += D.r / c.slave_weight[i] * c.weight_derivatives.row(static_cast<Eigen::Index>(i));
  if (c.gap_factors.size() != 0) {
    dr += D.dr_doffset * c.gap_factors.row(static_cast<Eigen::Index>(i));
    dh += D.dh_doffset * c.gap_factors.row(static_cast<Eigen::Index>(i));
  }
}

Eigen::MatrixXd StaticAnalysis::contact_derivatives(bool frictionless_only) const {
  Eigen::MatrixXd dR = Eigen::MatrixXd::Zero(n_dofs_, static_cast<Eigen::Index>(model_.sensitivity.parameters.size()));
  for (const ContactState& c : contacts_) {
    if (frictionless_only && c.law.friction > 0.0) continue;
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      const std::vector<int>& nodes = c.element_nodes[i];
      if (nodes.empty() || !c.points[i].touching) continue;
      Eigen::VectorXd x(2 * static_cast<Eigen::Index>(nodes.size()));
      for (std::size_t k = 0; k < nodes.size(); ++k)
        x.segment<2>(2 * static_cast<Eigen::Index>(k)) =
            model_.coordinates[nodes[k]] + u_.segment<2>(2 * static_cast<Eigen::Index>(nodes[k]));
      Eigen::MatrixXd dr, unused;
      contact_parameter_parts(c, i, contact_history_derivatives(x, c.law, c.history[i], c.element_segment[i],
                                                                c.slave_weight[i], c.slave_offset[i]),
                              dr, unused);
      for (std::size_t k = 0; k < nodes.size(); ++k)
        for (int d = 0; d < 2; ++d) dR.row(2 * nodes[k] + d) += dr.row(2 * static_cast<Eigen::Index>(k) + d);
    }
  }
  return dR;
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
