// StaticAnalysis: the residual and tangent of the model at a state (elements, face loads, contact) and the
// field output of the converged state.
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

ElementVector StaticAnalysis::local_unknowns(const Eigen::VectorXd& u, int element) const {
  const std::vector<int>& dofs = element_dofs_[element];
  ElementVector ue(static_cast<Eigen::Index>(dofs.size()));
  for (std::size_t k = 0; k < dofs.size(); ++k) ue[static_cast<Eigen::Index>(k)] = u[dofs[k]];
  return ue;
}

StaticAnalysis::Evaluation StaticAnalysis::evaluate(const Eigen::VectorXd& u, double lambda, bool tangent) {
  const ScopedTimer timer(timings_.assembly_s);
  const int n_elements = static_cast<int>(elements_.size());
  // The element forces at (u, lambda) are a function of them alone: when the last evaluation left them there (the
  // output's residual at the converged state, which Newton's last line-search step evaluated), they are kept.
  const bool forces_held = !tangent && forces_lambda_ == lambda && forces_u_.size() == u.size() && forces_u_ == u;
  int failures = 0;
#pragma omp parallel for schedule(static) reduction(+ : failures) if (!forces_held)
  for (int e = 0; e < n_elements; ++e) {
    if (forces_held) continue;
    if (!elements_[e]->internal_force(local_unknowns(u, e), kinematics(e, lambda), element_force_[e],
                                      tangent ? &element_tangent_[e] : nullptr))
      ++failures;
  }
  Evaluation ev;
  if (failures > 0) return ev;
  forces_u_ = u;
  forces_lambda_ = lambda;

  residual_.setZero(n_dofs_);
  // Contact first: new contact couplings change the matrix pattern before assembly.
  std::vector<ContactElement> contact;
  if (!contacts_.empty()) {
    contact_residual(u, tangent, contact);
    // The pattern keeps every coupling it was built with: it is rebuilt only when a contact element couples dofs
    // it does not hold yet (a slave node meeting a new master segment), not whenever one opens or closes, so that
    // the ordering, the symbolic analysis and a factorization for Newton to iterate on outlive such changes.
    if (tangent) {
      std::vector<ContactElement> uncovered;
      for (const ContactElement& c : contact)
        if (!system_->holds(c.dofs)) uncovered.push_back(c);
      if (!uncovered.empty()) rebuild_system(uncovered);
    }
  }
  // The reference force of the convergence test is the internal force of the bodies;
  // contact forces balance it and would otherwise vanish from it at equilibrium.
  const double contact_norm = residual_.norm();
  if (tangent) system_->set_zero();
  for (std::size_t c = 0; c < contact.size() && tangent; ++c) system_->add_coupled(contact[c].dofs, contact[c].K);
  for (int e = 0; e < n_elements; ++e) {
    const std::vector<int>& dofs = element_dofs_[e];
    for (std::size_t k = 0; k < dofs.size(); ++k) residual_[dofs[k]] += element_force_[e][static_cast<Eigen::Index>(k)];
    if (tangent) system_->add(e, element_tangent_[e]);
  }

  f_ext_.setZero(n_dofs_);
  for (const Ramp& r : forces_) f_ext_[r.dof] += ramp(r.start, r.end, lambda);

  // Face loads act on the current configuration; their stiffness enters with a minus
  // sign because R = f_int - f_ext.
  auto face_load = [&](const FaceLoad& f, bool laplace) {
    const std::vector<int>& dofs = element_dofs_[f.element];
    const EdgeNodes x = face_positions(f, u);
    EdgeVector fe;
    EdgeMatrix dfe;
    if (laplace) {
      garment_load(x, f.tension(lambda), f.reference_pressure(lambda), fe, tangent ? &dfe : nullptr);
    } else {
      follower_pressure_load(x, ramp(f.start, f.end, lambda), fe, tangent ? &dfe : nullptr);
    }
    const std::vector<int> local = local_dofs(f.local);
    for (std::size_t k = 0; k < local.size(); ++k) f_ext_[dofs[local[k]]] += fe[static_cast<Eigen::Index>(k)];
    if (tangent) {
      const EdgeMatrix minus = -dfe;
      system_->add(f.element, minus, local.data(), static_cast<int>(local.size()));
    }
  };
  for (const FaceLoad& f : pressure_faces_) face_load(f, false);
  for (const FaceLoad& f : laplace_faces_) face_load(f, true);

  const double internal_norm = std::max(residual_.norm(), contact_norm);
  residual_ -= f_ext_;
  double free_norm2 = 0.0;
  for (int d = 0; d < n_dofs_; ++d)
    if (system_->equation(d) >= 0) free_norm2 += residual_[d] * residual_[d];
  ev.ok = std::isfinite(free_norm2);
  ev.norm = std::sqrt(free_norm2);
  if (tangent) {
    tangent_u_ = u;
    tangent_lambda_ = lambda;
  }
  ev.reference = std::max({f_ext_.norm(), internal_norm, 1e-300});
  return ev;
}

FieldOutput StaticAnalysis::output() {
  FieldOutput out;
  const int n_displacements = model_.dof_count();
  out.displacement = u_.head(n_displacements);
  evaluate(u_, last_lambda_, false);
  out.reaction = residual_.head(n_displacements);
  for (std::size_t e = 0; e < elements_.size(); ++e)
    out.element_states.push_back(
        elements_[e]->state(local_unknowns(u_, static_cast<int>(e)), kinematics(static_cast<int>(e), last_lambda_)));
  // Nodal garment pressure: the deformed-contour share's nodal force over the node's consistent
  // length, along the node's outward normal (T / r), plus the reference-contour share's follower
  // pressure at the node (alpha p0; its length-weighted mean where faces of several surfaces meet).
  const int n_nodes = static_cast<int>(model_.coordinates.size());
  out.laplace_pressure = Eigen::VectorXd::Zero(n_nodes);
  Eigen::MatrixXd force = Eigen::MatrixXd::Zero(n_nodes, 2), normal = Eigen::MatrixXd::Zero(n_nodes, 2);
  Eigen::VectorXd length = Eigen::VectorXd::Zero(n_nodes), reference_force = Eigen::VectorXd::Zero(n_nodes);
  for (const FaceLoad& f : laplace_faces_) {
    const ElementDef& e = model_.elements[f.element];
    const EdgeNodes x = face_positions(f, u_);
    EdgeVector fe;
    laplace_membrane_load(x, f.tension(last_lambda_), fe, nullptr);
    const Eigen::VectorXd reference_pressure = f.reference_pressure(last_lambda_);
    Eigen::VectorXd w;
    EdgeNodes nw;
    face_weights(x, w, nw);
    for (std::size_t k = 0; k < f.local.size(); ++k) {
      const int node = e.nodes[f.local[k]];
      const auto kk = static_cast<Eigen::Index>(k);
      force.row(node) += fe.segment<2>(2 * kk).transpose();
      normal.row(node) += nw.row(kk);
      length[node] += w[kk];
      reference_force[node] += w[kk] * reference_pressure[kk];
    }
  }
  for (int node = 0; node < n_nodes; ++node) {
    if (length[node] > 0.0 && normal.row(node).norm() > 0.0)
      out.laplace_pressure[node] = -force.row(node).dot(normal.row(node).normalized()) / length[node];
    if (reference_force[node] != 0.0) out.laplace_pressure[node] += reference_force[node] / length[node];
  }

  // Contact tractions: as computed on the slave nodes, and on the master nodes the
  // slave forces they receive over their tributary length.
  out.contact_pressure = Eigen::VectorXd::Zero(n_nodes);
  out.contact_shear = Eigen::VectorXd::Zero(n_nodes);
  out.contact_status = Eigen::VectorXd::Zero(n_nodes);
  out.contact_slip = Eigen::VectorXd::Zero(n_nodes);
  for (const ContactState& c : contacts_) {
    Eigen::VectorXd master_normal = Eigen::VectorXd::Zero(n_nodes), master_shear = Eigen::VectorXd::Zero(n_nodes);
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      const ContactPoint& p = c.points[i];
      out.contact_slip[c.slave_nodes[i]] = c.history[i].slip + p.tangential_motion;
      if (!p.touching) continue;
      out.contact_status[c.slave_nodes[i]] = (c.law.friction > 0.0 && p.slip == 0) ? 1.0 : 2.0;
      out.contact_pressure[c.slave_nodes[i]] = p.pressure;
      out.contact_shear[c.slave_nodes[i]] = p.shear;
      const double xi = std::clamp(p.xi, 0.0, 1.0), w = c.slave_weight[i];
      const auto& seg = c.segments[p.segment];
      master_normal[seg[0]] += (1.0 - xi) * p.pressure * w;
      master_normal[seg[1]] += xi * p.pressure * w;
      master_shear[seg[0]] += (1.0 - xi) * p.shear * w;
      master_shear[seg[1]] += xi * p.shear * w;
    }
    for (int node = 0; node < n_nodes; ++node)
      if (c.master_weight[node] > 0.0) {
        out.contact_pressure[node] = master_normal[node] / c.master_weight[node];
        out.contact_shear[node] = -master_shear[node] / c.master_weight[node];
      }
  }
  return out;
}

}  // namespace calfit
