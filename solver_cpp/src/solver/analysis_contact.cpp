// StaticAnalysis: garment contact (penalty, Coulomb friction): the contact pairs, their residual and tangent,
// and the system rebuilt when the contact couplings change.
#include "solver/analysis_support.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

namespace calfit {

using namespace analysis_support;

void StaticAnalysis::rebuild_system(const std::vector<ContactElement>& contact) {
  for (const ContactElement& c : contact) system_contact_dofs_.push_back(c.reach);
  auto rebuilt = std::make_unique<SparseSystem>(element_dofs_, free_, saddle_point_, system_contact_dofs_);
  if (system_) rebuilt->inherit_solver_choices(*system_);
  system_ = std::move(rebuilt);
}

void StaticAnalysis::build_contacts() {
  for (std::size_t k = 0; k < model_.contact_pairs.size(); ++k) {
    const ContactPairDef& pair = model_.contact_pairs[k];
    ContactState state;
    state.pair = static_cast<int>(k);
    state.law = model_.interactions[pair.interaction].law;
    // Consistent nodal weights (integral of N_a ds x thickness) on both sides, so that a
    // uniform pressure transferred between matching T6 faces reads uniform; on the reference positions moved by
    // `along` times `h` (node -> shift: a SHAPE parameter's, whose change of the weights the contact's
    // sensitivities need).
    auto surface_weights = [&](int surface, const std::map<int, Eigen::Vector2d>& along = {}, double h = 0.0) {
      std::map<int, double> weights;
      for (const Face& f : model_.surfaces[surface]) {
        const ElementDef& e = model_.elements[f.element];
        const std::vector<int> local = face_nodes(e.shape, f.face);
        EdgeNodes X(static_cast<Eigen::Index>(local.size()), 2);
        for (std::size_t j = 0; j < local.size(); ++j) {
          const int node = e.nodes[local[j]];
          X.row(static_cast<Eigen::Index>(j)) = model_.coordinates[node].transpose();
          if (const auto moved = along.find(node); moved != along.end())
            X.row(static_cast<Eigen::Index>(j)) += h * moved->second.transpose();
        }
        Eigen::VectorXd w;
        EdgeNodes normals;
        face_weights(X, w, normals);
        const double thickness = model_.sections[e.section].thickness;
        for (std::size_t j = 0; j < local.size(); ++j) weights[e.nodes[local[j]]] += thickness * w[static_cast<Eigen::Index>(j)];
      }
      return weights;
    };
    for (const auto& [node, weight] : surface_weights(pair.slave)) {
      state.slave_nodes.push_back(node);
      state.slave_weight.push_back(weight);
    }
    state.master_weight.assign(model_.coordinates.size(), 0.0);
    for (const auto& [node, weight] : surface_weights(pair.master)) state.master_weight[node] = weight;
    for (const Face& f : model_.surfaces[pair.master]) {
      const ElementDef& e = model_.elements[f.element];
      const std::vector<int> local = face_nodes(e.shape, f.face);
      for (std::size_t j = 0; j + 1 < local.size(); ++j) state.segments.push_back({e.nodes[local[j]], e.nodes[local[j + 1]]});
    }
    std::map<int, int> starting_at, ending_at;
    for (std::size_t s = 0; s < state.segments.size(); ++s) {
      starting_at[state.segments[s][0]] = static_cast<int>(s);
      ending_at[state.segments[s][1]] = static_cast<int>(s);
    }
    for (const auto& seg : state.segments) {
      const auto before = ending_at.find(seg[0]), after = starting_at.find(seg[1]);
      state.previous.push_back(before == ending_at.end() ? -1 : before->second);
      state.next.push_back(after == starting_at.end() ? -1 : after->second);
    }
    // *GAP PROFILE of the slave surface: its offsets, and what the GAP PROFILE sensitivities move of them
    state.slave_offset.assign(state.slave_nodes.size(), 0.0);
    if (const int g = model_.gap_profile(pair.slave); g >= 0) {
      const GapProfile& profile = model_.gap_profiles[g];
      const Eigen::Vector2d center = model_.gap_center(profile);
      const std::vector<SensitivityParameter>& parameters = model_.sensitivity.parameters;
      for (std::size_t i = 0; i < state.slave_nodes.size(); ++i)
        state.slave_offset[i] = profile.offset(model_.coordinates[state.slave_nodes[i]], center);
      if (std::any_of(parameters.begin(), parameters.end(),
                      [&](const SensitivityParameter& p) { return p.gap_surface == pair.slave; })) {
        state.gap_factors.setZero(static_cast<Eigen::Index>(state.slave_nodes.size()),
                                  static_cast<Eigen::Index>(parameters.size()));
        for (std::size_t j = 0; j < parameters.size(); ++j) {
          const SensitivityParameter& p = parameters[j];
          if (p.gap_surface != pair.slave) continue;
          for (std::size_t i = 0; i < state.slave_nodes.size(); ++i)
            state.gap_factors(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) =
                GapProfile::basis(p.gap_harmonic, p.gap_sine, model_.coordinates[state.slave_nodes[i]], center);
        }
      }
    }
    // d(slave weight)/dtheta of the SHAPE parameters: a moved contour changes the tributary lengths (central
    // difference; exact for straight faces, whose weights are linear in the positions)
    const auto n_parameters = static_cast<Eigen::Index>(model_.sensitivity.parameters.size());
    for (Eigen::Index j = 0; j < n_parameters && !shape_of_node_.empty(); ++j) {
      std::map<int, Eigen::Vector2d> along;
      for (const auto& [node, direction] : model_.sensitivity.parameters[static_cast<std::size_t>(j)].shape)
        along.emplace(node, direction);
      if (along.empty()) continue;
      if (state.weight_derivatives.size() == 0)
        state.weight_derivatives.setZero(static_cast<Eigen::Index>(state.slave_nodes.size()), n_parameters);
      constexpr double h = 1e-3;  // mm
      const std::map<int, double> plus = surface_weights(pair.slave, along, h), minus = surface_weights(pair.slave, along, -h);
      for (std::size_t i = 0; i < state.slave_nodes.size(); ++i)
        state.weight_derivatives(static_cast<Eigen::Index>(i), j) =
            (plus.at(state.slave_nodes[i]) - minus.at(state.slave_nodes[i])) / (2.0 * h);
    }
    state.history.assign(state.slave_nodes.size(), ContactHistory{});
    state.trial = state.history;
    state.points.assign(state.slave_nodes.size(), ContactPoint{});
    state.iterate_slip.assign(state.slave_nodes.size(), 0);
    state.hold.assign(state.slave_nodes.size(), kFree);
    state.element_nodes.assign(state.slave_nodes.size(), {});
    state.element_segment.assign(state.slave_nodes.size(), -1);
    state.history_sensitivity.assign(state.slave_nodes.size(), Eigen::MatrixXd());
    contacts_.push_back(std::move(state));
  }
}

void StaticAnalysis::anchor_contacts() {
  if (std::none_of(contacts_.begin(), contacts_.end(), [](const ContactState& c) { return c.law.friction > 0.0; }))
    return;
  const Eigen::VectorXd saved = residual_;
  residual_.setZero(n_dofs_);
  std::vector<ContactElement> unused;
  contact_residual(u_, false, unused);
  for (ContactState& c : contacts_)
    if (c.law.friction > 0.0) c.history = c.trial;
  residual_ = saved;
}

void StaticAnalysis::forget_contact_iterates() {
  for (ContactState& c : contacts_) {
    std::fill(c.iterate_slip.begin(), c.iterate_slip.end(), 0);
    std::fill(c.hold.begin(), c.hold.end(), kFree);
  }
}

bool StaticAnalysis::hold_chattering_contacts() {
  bool held = false;
  for (ContactState& c : contacts_) {
    for (std::size_t i = 0; i < c.points.size(); ++i) {
      const int slip = c.points[i].slip;
      if (slip == 0 || c.hold[i] != kFree) continue;
      if (slip == -c.iterate_slip[i]) {
        c.hold[i] = kHeld;
        held = true;
      }
      c.iterate_slip[i] = slip;
    }
  }
  return held;
}

bool StaticAnalysis::release_slipping_contacts() {
  bool released = false;
  for (ContactState& c : contacts_) {
    for (std::size_t i = 0; i < c.points.size(); ++i) {
      if (c.hold[i] == kHeld && c.points[i].touching && c.points[i].slip != 0) {
        c.hold[i] = kReleased;
        released = true;
      }
    }
  }
  return released;
}

void StaticAnalysis::contact_residual(const Eigen::VectorXd& u, bool tangent, std::vector<ContactElement>& elements) {
  auto position = [&](int node) {
    return Eigen::Vector2d(model_.coordinates[node].x() + u[2 * node], model_.coordinates[node].y() + u[2 * node + 1]);
  };
  const LoadState& loads = model_.steps[current_step_].loads;
  for (ContactState& c : contacts_) {
    const bool active = loads.contact_active[c.pair] != 0;
    // With friction, an inactive pair still records where each slave node faces the master: the
    // first touch after *MODEL CHANGE, ADD is then located within its increment like any other.
    const bool friction = c.law.friction > 0.0;
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      c.trial[i] = ContactHistory{};
      c.trial[i].slip = c.history[i].slip;   // the slip so far outlives an open increment
      c.points[i] = ContactPoint{};
      c.element_nodes[i].clear();
      if (!active && !friction) continue;
      const int slave = c.slave_nodes[i];
      const Eigen::Vector2d xs = position(slave);
      // Closest master segment by straight distance; then, among it and its neighbours,
      // the one whose smoothed projection falls inside it.
      int nearest = -1;
      double best_distance = 0.0;
      for (std::size_t k = 0; k < c.segments.size(); ++k) {
        const Eigen::Vector2d a = position(c.segments[k][0]), b = position(c.segments[k][1]);
        const Eigen::Vector2d d = b - a;
        const double s = std::clamp((xs - a).dot(d) / d.squaredNorm(), 0.0, 1.0);
        const double distance = (xs - a - s * d).norm();
        if (nearest < 0 || distance < best_distance) {
          nearest = static_cast<int>(k);
          best_distance = distance;
        }
      }
      if (nearest < 0) continue;
      const ContactHistory& h = c.history[i];
      auto element_nodes = [&](int k) {
        const auto& seg = c.segments[k];
        std::vector<int> nodes = {slave, seg[0], seg[1], c.previous[k] >= 0 ? c.segments[c.previous[k]][0] : seg[0],
                                  c.next[k] >= 0 ? c.segments[c.next[k]][1] : seg[1]};
        if (friction && h.anchored()) {
          nodes.push_back(c.segments[h.segment][0]);
          nodes.push_back(c.segments[h.segment][1]);
        }
        return nodes;
      };
      auto positions = [&](const std::vector<int>& nodes) {
        Eigen::VectorXd x(2 * nodes.size());
        for (std::size_t k = 0; k < nodes.size(); ++k) x.segment<2>(2 * static_cast<Eigen::Index>(k)) = position(nodes[k]);
        return x;
      };
      int best = nearest;
      for (int k : {nearest, c.previous[nearest], c.next[nearest]}) {
        if (k < 0) continue;
        Eigen::VectorXd scratch;
        const ContactPoint probe = contact_element(positions(element_nodes(k)), c.law, h, k, c.slave_weight[i], scratch,
                                                   nullptr, false, c.slave_offset[i]);
        if (probe.xi >= 0.0 && probe.xi <= 1.0) {
          best = k;
          break;
        }
      }
      const std::vector<int> nodes = element_nodes(best);
      Eigen::VectorXd r;
      Eigen::MatrixXd K;
      // Coulomb's law is a bang-bang switch for Newton: a slipping node carries +-mu p_N whatever its slip, its
      // tangent has no tangential stiffness, and where the converged state sticks, Newton can throw the node from
      // slipping one way to slipping the other and back (the garment band's first touch: the friction forces of
      // a dozen skin nodes flipped sign at every iteration for 12 iterations). A node that reversed its slip
      // direction within the increment is held sticking (shear = trial, residual and tangent) while Newton
      // iterates, and released when the converged state would have it slip (release_slipping_contacts): an
      // accepted state obeys the same Coulomb law.
      const bool hold = friction && active && c.hold[i] == kHeld;
      const ContactPoint point = contact_element(positions(nodes), c.law, h, best, c.slave_weight[i], r,
                                                 tangent && active ? &K : nullptr, hold, c.slave_offset[i]);
      c.element_nodes[i] = nodes;
      c.element_segment[i] = best;
      if (!active || !point.touching) {
        // Open (or the pair inactive): keep the master point the node faces, for its first touch.
        if (friction && point.gap >= 0.0 && point.xi >= -0.5 && point.xi <= 1.5)
          c.trial[i] = ContactHistory{false, point.segment, point.xi, 0.0, point.gap, h.slip};
        if (!active) continue;
      }
      c.points[i] = point;
      if (!point.touching) continue;
      c.trial[i] = ContactHistory{true, point.segment, point.xi, point.shear, 0.0, h.slip + point.tangential_motion};
      ContactElement element;
      for (std::size_t k = 0; k < nodes.size(); ++k) {
        element.dofs.push_back(2 * nodes[k]);
        element.dofs.push_back(2 * nodes[k] + 1);
      }
      for (std::size_t k = 0; k < element.dofs.size(); ++k) residual_[element.dofs[k]] += r[static_cast<Eigen::Index>(k)];
      if (tangent) {
        element.K = std::move(K);
        std::vector<int> near = nodes;
        for (int k = best, j = 0; k >= 0 && j < kContactReach; k = c.previous[k], ++j) near.push_back(c.segments[k][0]);
        for (int k = best, j = 0; k >= 0 && j < kContactReach; k = c.next[k], ++j) near.push_back(c.segments[k][1]);
        std::sort(near.begin(), near.end());
        near.erase(std::unique(near.begin(), near.end()), near.end());
        for (int node : near) {
          element.reach.push_back(2 * node);
          element.reach.push_back(2 * node + 1);
        }
        elements.push_back(std::move(element));
      }
    }
  }
}

}  // namespace calfit
