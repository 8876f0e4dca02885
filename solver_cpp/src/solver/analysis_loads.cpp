// StaticAnalysis: the loads and kinematics of a step ramped over its increments (prescribed displacements,
// rigid motions of node sets, forces, volume changes, follower and Laplace-law pressures, the latter's
// reference-contour share with its nodal pressures p0).
#include "solver/analysis_support.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

namespace calfit {

using namespace analysis_support;

std::map<std::pair<int, int>, StaticAnalysis::LaplaceFace> StaticAnalysis::laplace_faces(
    const LoadState& state, const std::vector<TensionProfile>& profiles) const {
  std::map<std::pair<int, int>, LaplaceFace> faces;
  for (const auto& [surface, load] : state.laplace) {
    const std::vector<Face>& surface_faces = model_.surfaces[surface];
    Eigen::Vector2d center = Eigen::Vector2d::Zero();
    const TensionProfile* profile = load.profile >= 0 ? &profiles[load.profile] : nullptr;
    if (profile && profile->has_center) {
      center = profile->center;
    } else if (profile) {
      std::set<int> nodes;
      for (const Face& f : surface_faces)
        for (int l : face_nodes(model_.elements[f.element].shape, f.face)) nodes.insert(model_.elements[f.element].nodes[l]);
      for (int n : nodes) center += model_.coordinates[n];
      center /= static_cast<double>(nodes.size());
    }
    std::vector<Eigen::VectorXd> tensions;  // per face of the surface, at its nodes
    for (const Face& f : surface_faces) {
      const std::vector<int> local = face_nodes(model_.elements[f.element].shape, f.face);
      Eigen::VectorXd tension(local.size());
      for (std::size_t k = 0; k < local.size(); ++k) {
        double factor = 1.0;
        if (profile) {
          const Eigen::Vector2d r = model_.coordinates[model_.elements[f.element].nodes[local[k]]] - center;
          factor = profile->factor(std::atan2(r.y(), r.x()) * 180.0 / kPi);
        }
        tension(static_cast<Eigen::Index>(k)) = load.tension * factor;
      }
      tensions.push_back(std::move(tension));
    }
    const double alpha = load.reference;
    // alpha = 0 (the default) computes no reference pressure: today's load, to the bit.
    const std::vector<Eigen::VectorXd> reference = alpha != 0.0 ? reference_pressures(surface_faces, tensions)
                                                                : std::vector<Eigen::VectorXd>();
    for (std::size_t i = 0; i < surface_faces.size(); ++i) {
      const Eigen::VectorXd tension = (1.0 - alpha) * tensions[i];
      const Eigen::VectorXd pressure = alpha != 0.0 ? Eigen::VectorXd(alpha * reference[i])
                                                    : Eigen::VectorXd::Zero(tensions[i].size());
      LaplaceFace& total = faces[{surface_faces[i].element, surface_faces[i].face}];
      // two surfaces may share a face
      total.tension = total.tension.size() ? Eigen::VectorXd(total.tension + tension) : tension;
      total.reference_pressure =
          total.reference_pressure.size() ? Eigen::VectorXd(total.reference_pressure + pressure) : pressure;
    }
  }
  return faces;
}

std::vector<Eigen::VectorXd> StaticAnalysis::reference_pressures(const std::vector<Face>& faces,
                                                                 const std::vector<Eigen::VectorXd>& tensions) const {
  // The membrane load F0 of the tensions on the REFERENCE contour (edge_loads.hpp) holds the contour's
  // curvature: distributed along curved faces, concentrated in the kink forces T (t+ - t-) at the corners
  // between faces, as the deformed-contour law sees it. Each corner node takes F0, the consistent length and
  // the normal sum of its faces, a T6 face's mid-side node's half of each (the kink force is the resultant
  // of the pressure over the corner's tributary length, half of each face), and p0 = -(F0 . n0) / L0 as the
  // output's laplace_pressure is computed (analysis_assembly.cpp). A mid-side node takes the mean of its
  // face's corners: the pressure is linear along each face. (Its own -(F0 . n0) / L0 would be 0 on a
  // straight T6 face and its corners' 3 T kappa: a pressure that puts its force where the kinks are, not
  // where a pressure T kappa puts it; on the leg slice 8.5 % of max |u| from *DLOAD T kappa per face with
  // 1,200 elements.) On a circle of radius R0 cut into equal chords, T3 or straight T6, p0 = T / R0 exactly.
  struct NodeSum {
    Eigen::Vector2d force = Eigen::Vector2d::Zero(), normal = Eigen::Vector2d::Zero();
    double length = 0.0;
  };
  std::map<int, NodeSum> corners;
  std::vector<std::array<int, 2>> face_corners;
  for (std::size_t i = 0; i < faces.size(); ++i) {
    const ElementDef& e = model_.elements[faces[i].element];
    const std::vector<int> local = face_nodes(e.shape, faces[i].face);
    const auto n = static_cast<Eigen::Index>(local.size());
    EdgeNodes X(n, 2);
    for (Eigen::Index k = 0; k < n; ++k) X.row(k) = model_.coordinates[e.nodes[local[static_cast<std::size_t>(k)]]].transpose();
    EdgeVector force;
    laplace_membrane_load(X, tensions[i], force, nullptr);
    Eigen::VectorXd length;
    EdgeNodes normal;
    face_weights(X, length, normal);
    const std::array<int, 2> ends = {e.nodes[local.front()], e.nodes[local.back()]};
    const std::array<Eigen::Index, 2> end_rows = {0, n - 1};
    for (int c = 0; c < 2; ++c) {
      NodeSum& sum = corners[ends[c]];
      const Eigen::Index row = end_rows[c];
      sum.force += force.segment<2>(2 * row);
      sum.normal += normal.row(row).transpose();
      sum.length += length[row];
      if (n == 3) {  // the mid-side node's share, half to each corner
        sum.force += 0.5 * force.segment<2>(2);
        sum.normal += 0.5 * normal.row(1).transpose();
        sum.length += 0.5 * length[1];
      }
    }
    face_corners.push_back(ends);
  }
  std::vector<Eigen::VectorXd> pressures;
  for (std::size_t i = 0; i < faces.size(); ++i) {
    std::array<double, 2> p{};
    for (int c = 0; c < 2; ++c) {
      const NodeSum& sum = corners.at(face_corners[i][c]);
      if (sum.length > 0.0 && sum.normal.norm() > 0.0) p[c] = -sum.force.dot(sum.normal.normalized()) / sum.length;
    }
    Eigen::VectorXd nodal(tensions[i].size());
    if (nodal.size() == 2) {
      nodal << p[0], p[1];
    } else {
      nodal << p[0], 0.5 * (p[0] + p[1]), p[1];
    }
    pressures.push_back(std::move(nodal));
  }
  return pressures;
}

void StaticAnalysis::prepare_step(int step) {
  static const LoadState nothing;
  const LoadState& before = step > 0 ? model_.steps[step - 1].loads : nothing;
  const LoadState& now = model_.steps[step].loads;

  std::vector<char> active(n_dofs_, 0);
  for (const std::vector<int>& dofs : element_dofs_)
    for (int d : dofs) active[d] = 1;
  current_step_ = step;
  forces_lambda_ = -1;  // the element forces held are of the last step's loads and kinematics
  free_ = active;
  prescribed_.clear();
  // The *BOUNDARY values ramp linearly; rigid motions ramp in angle (prepare_rigid_motions).
  for (const auto& [dof, value] : now.prescribed) {
    free_[dof] = 0;
    prescribed_.push_back({dof, u_[dof], value});
  }
  prepare_rigid_motions(before, now);
  system_contact_dofs_.clear();  // a step's pattern starts from the elements alone: the free dofs change
  rebuild_system({});
  free_dofs_ = system_->size();

  forces_.clear();
  for_each_ramp(before.forces, now.forces, [&](int dof, const double* start, const double* end) {
    forces_.push_back({dof, start ? *start : 0.0, end ? *end : 0.0});
  });

  const std::size_t n_elements = elements_.size();
  volume_change_start_.assign(n_elements, 0.0);
  volume_change_end_.assign(n_elements, 0.0);
  for_each_ramp(before.volume_change, now.volume_change, [&](int element, const double* start, const double* end) {
    volume_change_start_[element] = start ? *start : 0.0;
    volume_change_end_[element] = end ? *end : 0.0;
  });
  axial_stretch_start_ = before.axial_stretch;
  axial_stretch_end_ = now.axial_stretch;

  pressure_faces_.clear();
  for_each_ramp(before.pressures, now.pressures,
                [&](const std::pair<int, int>& key, const double* start, const double* end) {
                  FaceLoad f = unloaded_face(key);
                  f.start = start ? *start : 0.0;
                  f.end = end ? *end : 0.0;
                  pressure_faces_.push_back(f);
                });

  laplace_faces_.clear();
  for_each_ramp(laplace_faces(before, model_.profiles), laplace_faces(now, model_.profiles),
                [&](const std::pair<int, int>& key, const LaplaceFace* start, const LaplaceFace* end) {
                  FaceLoad f = unloaded_face(key);
                  const Eigen::Index n = static_cast<Eigen::Index>(f.local.size());
                  f.t_start = start ? start->tension : Eigen::VectorXd::Zero(n);
                  f.t_end = end ? end->tension : Eigen::VectorXd::Zero(n);
                  f.p_start = start ? start->reference_pressure : Eigen::VectorXd::Zero(n);
                  f.p_end = end ? end->reference_pressure : Eigen::VectorXd::Zero(n);
                  laplace_faces_.push_back(f);
                });
}

void StaticAnalysis::prepare_rigid_motions(const LoadState& before, const LoadState& now) {
  rigid_motions_.clear();
  for_each_ramp(before.rigid_motions, now.rigid_motions,
                [&](const std::string&, const RigidMotion* start, const RigidMotion* end) {
                  if (!end) return;  // removed (OP=NEW): its nodes are free again
                  RigidRamp r;
                  r.nodes = end->nodes;
                  r.center = end->center;
                  r.translation_end = {end->ux, end->uy};
                  r.angle_end = end->angle_degrees;
                  r.translation_start.setZero();
                  if (start) {
                    // The previous motion about this centre: same angle, translation
                    // t + (R - I)(c_now - c_before), so a moved centre does not jump.
                    r.translation_start = start->displacement(end->center);
                    r.angle_start = start->angle_degrees;
                  }
                  for (int node : r.nodes) {
                    free_[2 * node] = free_[2 * node + 1] = 0;
                    const Eigen::Vector2d at_start =
                        RigidMotion::displacement(r.translation_start, r.angle_start, r.center, model_.coordinates[node]);
                    r.mismatch.emplace_back(u_[2 * node] - at_start.x(), u_[2 * node + 1] - at_start.y());
                  }
                  rigid_motions_.push_back(std::move(r));
                });
}

ElementKinematics StaticAnalysis::kinematics(int element, double lambda) const {
  return ElementKinematics::from_volume_change(
      ramp(volume_change_start_[element], volume_change_end_[element], lambda),
      ramp(axial_stretch_start_, axial_stretch_end_, lambda));
}

StaticAnalysis::FaceLoad StaticAnalysis::unloaded_face(const std::pair<int, int>& key) const {
  FaceLoad f;
  f.element = key.first;
  f.local = face_nodes(model_.elements[key.first].shape, key.second);
  return f;
}

EdgeNodes StaticAnalysis::face_positions(const FaceLoad& f, const Eigen::VectorXd& u) const {
  const std::vector<int>& nodes = model_.elements[f.element].nodes;
  EdgeNodes x(static_cast<Eigen::Index>(f.local.size()), 2);
  for (std::size_t k = 0; k < f.local.size(); ++k) {
    const int node = nodes[f.local[k]];
    x.row(static_cast<Eigen::Index>(k)) << model_.coordinates[node].x() + u[2 * node],
        model_.coordinates[node].y() + u[2 * node + 1];
  }
  return x;
}

void StaticAnalysis::apply_prescribed(Eigen::VectorXd& u, double lambda) const {
  for (const Ramp& r : prescribed_) u[r.dof] = ramp(r.start, r.end, lambda);
  for (const RigidRamp& r : rigid_motions_) {
    const Eigen::Vector2d translation = r.translation_start + lambda * (r.translation_end - r.translation_start);
    const double angle = ramp(r.angle_start, r.angle_end, lambda);
    for (std::size_t k = 0; k < r.nodes.size(); ++k) {
      const int node = r.nodes[k];
      const Eigen::Vector2d d = RigidMotion::displacement(translation, angle, r.center, model_.coordinates[node]) +
                                (1.0 - lambda) * r.mismatch[k];
      u[2 * node] = d.x();
      u[2 * node + 1] = d.y();
    }
  }
}

}  // namespace calfit
