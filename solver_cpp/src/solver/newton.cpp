// Incremental Newton-Raphson solution: see newton.hpp.
#include "solver/newton.hpp"

#include "element/mixed_element.hpp"
#include "load/edge_loads.hpp"

#include <algorithm>
#include <chrono>
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
namespace {

constexpr double kPi = 3.14159265358979323846;
// The directional difference of the residual along a prescribed increment moves the prescribed dofs by this
// fraction of the model's size: far above round-off, far below any strain the elements could notice.
constexpr double kDirectionalStep = 1e-7;

double ramp(double start, double end, double lambda) { return start + lambda * (end - start); }

// The next increment after one that converged in `iterations` Newton iterations (`previous`: the increment
// before it, 0 if none).
// - Driven by prescribed displacements: the iteration count measures how nonlinear the increment was, and the
//   next one is scaled by (N_d / N)^(1/2) when it took more than N_d = kEasyIterations (Crisfield, Non-linear
//   Finite Element Analysis of Solids and Structures, vol. 1, sec. 9.5.1), at least halved; easy twice in a row,
//   1.5 times longer (CalculiX's growth rule). A compressed block then keeps to 3-4 iterations per increment
//   instead of meeting a 9-iteration one near its barrelling.
// - Driven by loads alone, or with penalty contact, the count follows other things (a nearly incompressible
//   displacement element's volumetric overshoot, changes of contact status) and shrinking only crawls: there an
//   increment grows 1.5 times after one of at most kLoadEasyIterations and shrinks only when it fails.
constexpr int kEasyIterations = 3;
constexpr int kRateCheckIterations = 3;     // Newton iterations before the contraction is checked
constexpr double kSlowContraction = 0.1;    // a residual that falls by less than this per iteration is slow
constexpr int kLoadEasyIterations = 5;
double next_increment_factor(int iterations, int previous, bool displacement_driven) {
  if (!displacement_driven) return iterations <= kLoadEasyIterations ? 1.5 : 1.0;
  if (iterations > kEasyIterations)
    return std::max(std::sqrt(static_cast<double>(kEasyIterations) / iterations), 0.5);
  return previous > 0 && previous <= kEasyIterations ? 1.5 : 1.0;
}

// Adds the wall time of its scope to a counter.
class ScopedTimer {
public:
  explicit ScopedTimer(double& total) : total_(total), start_(std::chrono::steady_clock::now()) {}
  ~ScopedTimer() { total_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count(); }
  ScopedTimer(const ScopedTimer&) = delete;
  ScopedTimer& operator=(const ScopedTimer&) = delete;

private:
  double& total_;
  std::chrono::steady_clock::time_point start_;
};

// Calls fn(key, start, end) for every key loaded before or now, where start and end
// point to the values at the two ends of the step (nullptr: not loaded, i.e. zero).
template <typename Map, typename Fn>
void for_each_ramp(const Map& before, const Map& now, Fn fn) {
  std::set<typename Map::key_type> keys;
  for (const auto& kv : before) keys.insert(kv.first);
  for (const auto& kv : now) keys.insert(kv.first);
  for (const auto& key : keys) {
    const auto b = before.find(key), n = now.find(key);
    fn(key, b == before.end() ? nullptr : &b->second, n == now.end() ? nullptr : &n->second);
  }
}

// Face-local dof indices (2 per node) into the element's dof list.
std::vector<int> local_dofs(const std::vector<int>& local_nodes) {
  std::vector<int> dofs;
  for (int l : local_nodes) {
    dofs.push_back(2 * l);
    dofs.push_back(2 * l + 1);
  }
  return dofs;
}

// Element `index` of the model with the given materials (the model's own, or a
// sensitivity parameter's perturbed copy of them).
std::unique_ptr<Element> make_element(const Model& model, const std::vector<MaterialDef>& materials, int index) {
  const ElementDef& e = model.elements[index];
  const SectionDef& s = model.sections[e.section];
  const Material& law = *materials[s.material].law;
  const int degree = e.shape == ElementShape::T3 ? 1 : (s.full_integration ? 4 : 2);
  NodeMatrix X(node_count(e.shape), 2);
  for (int k = 0; k < X.rows(); ++k) X.row(k) = model.coordinates[e.nodes[k]].transpose();
  if (!e.hybrid) return std::make_unique<SolidElement>(e.shape, X, law, s.thickness, degree);
  return std::make_unique<MixedElement>(e.shape, X, dynamic_cast<const SplitHyperelastic&>(law), s.thickness, degree);
}

}  // namespace

StaticAnalysis::StaticAnalysis(const Model& model, SolverSettings settings) : model_(model), settings_(settings) {
#ifdef _OPENMP
  if (settings_.threads > 0) omp_set_num_threads(settings_.threads);
#endif
  // Unknowns: the nodal displacements 0 .. 2 n_nodes - 1, then the pressures of the
  // hybrid elements (one per corner node shared by CPE6H elements, one per CPE3H).
  n_dofs_ = model.dof_count();
  std::unordered_map<int, int> corner_pressure;
  for (std::size_t index = 0; index < model.elements.size(); ++index) {
    const ElementDef& e = model.elements[index];
    elements_.push_back(make_element(model, model.materials, static_cast<int>(index)));
    std::vector<int> dofs;
    for (int node : e.nodes) {
      dofs.push_back(2 * node);
      dofs.push_back(2 * node + 1);
    }
    if (e.hybrid) {
      if (e.shape == ElementShape::T6) {
        for (int k = 0; k < 3; ++k) {
          const auto inserted = corner_pressure.emplace(e.nodes[k], n_dofs_);
          if (inserted.second) ++n_dofs_;
          dofs.push_back(inserted.first->second);
        }
      } else {
        dofs.push_back(n_dofs_++);
      }
    }
    element_dofs_.push_back(std::move(dofs));
  }
  saddle_point_ = n_dofs_ > model.dof_count();
  Eigen::Vector2d low = model.coordinates.front(), high = low;
  for (const Eigen::Vector2d& x : model.coordinates) {
    low = low.cwiseMin(x);
    high = high.cwiseMax(x);
  }
  model_size_ = (high - low).norm();
  u_.setZero(n_dofs_);
  build_contacts();
  element_force_.resize(elements_.size());
  element_tangent_.resize(elements_.size());
}

std::map<std::pair<int, int>, Eigen::VectorXd> StaticAnalysis::laplace_tensions(
    const LoadState& state, const std::vector<TensionProfile>& profiles) const {
  std::map<std::pair<int, int>, Eigen::VectorXd> tensions;  // (element, face) -> nodal tension
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
      Eigen::VectorXd& total = tensions[{f.element, f.face}];
      total = total.size() ? Eigen::VectorXd(total + tension) : tension;  // two surfaces may share a face
    }
  }
  return tensions;
}

void StaticAnalysis::prepare_step(int step) {
  static const LoadState nothing;
  const LoadState& before = step > 0 ? model_.steps[step - 1].loads : nothing;
  const LoadState& now = model_.steps[step].loads;

  std::vector<char> active(n_dofs_, 0);
  for (const std::vector<int>& dofs : element_dofs_)
    for (int d : dofs) active[d] = 1;
  current_step_ = step;
  free_ = active;
  prescribed_.clear();
  // The *BOUNDARY values ramp linearly; rigid motions ramp in angle (prepare_rigid_motions).
  for (const auto& [dof, value] : now.prescribed) {
    free_[dof] = 0;
    prescribed_.push_back({dof, u_[dof], value});
  }
  prepare_rigid_motions(before, now);
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
  for_each_ramp(laplace_tensions(before, model_.profiles), laplace_tensions(now, model_.profiles),
                [&](const std::pair<int, int>& key, const Eigen::VectorXd* start, const Eigen::VectorXd* end) {
                  FaceLoad f = unloaded_face(key);
                  const Eigen::Index n = static_cast<Eigen::Index>(f.local.size());
                  f.t_start = start ? *start : Eigen::VectorXd::Zero(n);
                  f.t_end = end ? *end : Eigen::VectorXd::Zero(n);
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

void StaticAnalysis::rebuild_system(const std::vector<ContactElement>& contact) {
  std::vector<std::vector<int>> dofs = element_dofs_;
  system_contact_dofs_.clear();
  for (const ContactElement& c : contact) {
    dofs.push_back(c.dofs);
    system_contact_dofs_.push_back(c.dofs);
  }
  auto rebuilt = std::make_unique<SparseSystem>(dofs, free_, saddle_point_);
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
    // uniform pressure transferred between matching T6 faces reads uniform.
    auto surface_weights = [&](int surface) {
      std::map<int, double> weights;
      for (const Face& f : model_.surfaces[surface]) {
        const ElementDef& e = model_.elements[f.element];
        const std::vector<int> local = face_nodes(e.shape, f.face);
        EdgeNodes X(static_cast<Eigen::Index>(local.size()), 2);
        for (std::size_t j = 0; j < local.size(); ++j)
          X.row(static_cast<Eigen::Index>(j)) = model_.coordinates[e.nodes[local[j]]].transpose();
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
    state.history.assign(state.slave_nodes.size(), ContactHistory{});
    state.trial = state.history;
    state.points.assign(state.slave_nodes.size(), ContactPoint{});
    contacts_.push_back(std::move(state));
  }
}

void StaticAnalysis::contact_residual(const Eigen::VectorXd& u, bool tangent, std::vector<ContactElement>& elements) {
  auto position = [&](int node) {
    return Eigen::Vector2d(model_.coordinates[node].x() + u[2 * node], model_.coordinates[node].y() + u[2 * node + 1]);
  };
  const LoadState& loads = model_.steps[current_step_].loads;
  for (ContactState& c : contacts_) {
    const bool active = loads.contact_active[c.pair] != 0;
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      c.trial[i] = ContactHistory{};
      c.points[i] = ContactPoint{};
      if (!active) continue;
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
        if (c.law.friction > 0.0 && h.touching) {
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
        const ContactPoint probe = contact_element(positions(element_nodes(k)), c.law, h, k, c.slave_weight[i], scratch, nullptr);
        if (probe.xi >= 0.0 && probe.xi <= 1.0) {
          best = k;
          break;
        }
      }
      const std::vector<int> nodes = element_nodes(best);
      Eigen::VectorXd r;
      Eigen::MatrixXd K;
      const ContactPoint point = contact_element(positions(nodes), c.law, h, best, c.slave_weight[i], r, tangent ? &K : nullptr);
      c.points[i] = point;
      if (!point.touching) continue;
      c.trial[i] = ContactHistory{true, point.segment, point.xi, point.shear};
      ContactElement element;
      for (std::size_t k = 0; k < nodes.size(); ++k) {
        element.dofs.push_back(2 * nodes[k]);
        element.dofs.push_back(2 * nodes[k] + 1);
      }
      for (std::size_t k = 0; k < element.dofs.size(); ++k) residual_[element.dofs[k]] += r[static_cast<Eigen::Index>(k)];
      if (tangent) {
        element.K = std::move(K);
        elements.push_back(std::move(element));
      }
    }
  }
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

ElementVector StaticAnalysis::local_unknowns(const Eigen::VectorXd& u, int element) const {
  const std::vector<int>& dofs = element_dofs_[element];
  ElementVector ue(static_cast<Eigen::Index>(dofs.size()));
  for (std::size_t k = 0; k < dofs.size(); ++k) ue[static_cast<Eigen::Index>(k)] = u[dofs[k]];
  return ue;
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

StaticAnalysis::Evaluation StaticAnalysis::evaluate(const Eigen::VectorXd& u, double lambda, bool tangent) {
  const ScopedTimer timer(timings_.assembly_s);
  const int n_elements = static_cast<int>(elements_.size());
  int failures = 0;
#pragma omp parallel for schedule(static) reduction(+ : failures)
  for (int e = 0; e < n_elements; ++e) {
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
    if (tangent) {
      std::vector<std::vector<int>> couplings;
      for (const ContactElement& c : contact) couplings.push_back(c.dofs);
      if (couplings != system_contact_dofs_) rebuild_system(contact);
    }
  }
  // The reference force of the convergence test is the internal force of the bodies;
  // contact forces balance it and would otherwise vanish from it at equilibrium.
  const double contact_norm = residual_.norm();
  if (tangent) system_->set_zero();
  for (std::size_t c = 0; c < contact.size() && tangent; ++c)
    system_->add(n_elements + static_cast<int>(c), contact[c].K);
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
      laplace_membrane_load(x, f.tension(lambda), fe, tangent ? &dfe : nullptr);
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

StepResult StaticAnalysis::run_step(int step, const std::function<void(const std::string&)>& log) {
  prepare_step(step);
  const StepDef& s = model_.steps[step];
  StepResult result;
  double time = 0.0, dt = s.initial_dt;
  double last_lambda_in_step = 0.0;  // the load fraction of the committed state within this step
  int previous_iterations = 0;       // Newton iterations of the last converged increment
  bool factorization_committed = false;  // the last factorization is Newton's last at the committed state
  const bool contact_in_step = std::any_of(s.loads.contact_active.begin(), s.loads.contact_active.end(),
                                           [](char active) { return active != 0; });
  bool moves_prescribed = !rigid_motions_.empty();
  for (const Ramp& r : prescribed_) moves_prescribed = moves_prescribed || r.start != r.end;
  const bool displacement_driven = moves_prescribed && !contact_in_step;
  const int n = system_->size();
  Eigen::VectorXd rhs(n), du(n);

  // The linear solve of one Newton correction: du of the free dofs for R + coupling, or false with a note.
  auto correction = [&](const Eigen::VectorXd& coupling, bool first_of_step, int it, IncrementRecord& rec,
                        Eigen::VectorXd& full) {
    for (int d = 0; d < n_dofs_; ++d)
      if (system_->equation(d) >= 0) rhs[system_->equation(d)] = -(residual_[d] + coupling[d]);
    if (!system_->finite()) {
      rec.note = "the tangent stiffness is not finite (an element's stiffness overflowed)";
      return false;
    }
    bool solved;
    {
      const ScopedTimer timer(timings_.factorization_s);
      const int reused_before = system_->reused_factorizations();
      solved = system_->solve(rhs, du);
      ++(system_->reused_factorizations() > reused_before ? timings_.reused_factorizations : timings_.factorizations);
    }
    if (system_->became_indefinite())
      log("step " + std::to_string(step + 1) + ": the tangent is not positive definite; UMFPACK LU solves it "
          "for the rest of the step");
    if (!solved) {
      if (first_of_step && it == 0)
        throw std::runtime_error("the tangent stiffness is singular at the start of step " + std::to_string(step + 1) +
                                 ": part of the model can move freely; fix rigid-body motions with *BOUNDARY");
      rec.note = "singular tangent (a structural instability?)";
      return false;
    }
    linear_solver_ = system_->solver_name();
    full.setZero(n_dofs_);
    for (int d = 0; d < n_dofs_; ++d)
      if (system_->equation(d) >= 0) full[d] = du[system_->equation(d)];
    return true;
  };

  // One Newton solve of the increment ending at load fraction lambda; u is updated in place. u starts at the
  // committed state, its prescribed dofs where the previous increment left them; prescribed_step moves them to
  // this increment's values. The first correction solves for the free dofs' response to that move, K_ff du_f =
  // -(R_f + K_fp du_p), with K_fp du_p the directional derivative of R along du_p (Wriggers, Nonlinear Finite
  // Element Methods, sec. 5.1): the boundary and the interior move together, so no row of elements next to the
  // boundary is squashed, and Newton converges quadratically from its first iteration.
  // The predictor's K_ff is the tangent at the committed state. After a converged increment the factorization
  // of Newton's last iteration is that tangent to within the last correction, and is reused: one factorization
  // less per increment. After a cut-back, or at a step's start, the tangent is assembled and factorized there.
  auto newton = [&](Eigen::VectorXd& u, double lambda, const Eigen::VectorXd& prescribed_step, IncrementRecord& rec,
                    bool first_of_step, bool committed_factorization) {
    const double largest_step = prescribed_step.cwiseAbs().maxCoeff();
    const bool reuse = largest_step > 0.0 && committed_factorization && system_->factorized();
    Evaluation ev = evaluate(u, lambda, !reuse);
    if (!ev.ok) {
      rec.note = "the residual at the start of the increment is not finite";
      return false;
    }
    // The force scale is at least the one the increment started from: a volume change or
    // an axial stretch of a free body, or a rigid motion, ends in a state where every
    // nodal force vanishes with the residual, which would then never be small relative
    // to the current forces alone.
    const double increment_reference = ev.reference;
    if (largest_step > 0.0) {
      const Eigen::VectorXd start_residual = residual_;
      const double h = kDirectionalStep * model_size_ / largest_step;
      const Evaluation shifted = evaluate(u + h * prescribed_step, lambda, false);
      if (!shifted.ok) {
        rec.note = "the residual next to the start of the increment is not finite";
        return false;
      }
      const Eigen::VectorXd coupling = (residual_ - start_residual) / h;
      residual_ = start_residual;
      Eigen::VectorXd full;
      if (reuse) {
        for (int d = 0; d < n_dofs_; ++d)
          if (system_->equation(d) >= 0) rhs[system_->equation(d)] = -(residual_[d] + coupling[d]);
        const ScopedTimer timer(timings_.factorization_s);
        if (!system_->solve_factored(rhs, du)) {
          rec.note = "the committed state's factorization gave no finite predictor";
          return false;
        }
        full.setZero(n_dofs_);
        for (int d = 0; d < n_dofs_; ++d)
          if (system_->equation(d) >= 0) full[d] = du[system_->equation(d)];
      } else if (!correction(coupling, first_of_step, 0, rec, full)) {
        return false;
      }
      u += prescribed_step + full;
      ev = evaluate(u, lambda, true);
      if (!ev.ok) {
        rec.note = "an element turned inside out (det F <= 0) under the prescribed displacement increment";
        return false;
      }
    }
    int rises = 0;
    double last_correction = std::numeric_limits<double>::infinity();
    for (int it = 0;; ++it) {
      const double relative = ev.norm / std::max(ev.reference, increment_reference);
      rec.residual_norms.push_back(relative);
      if (relative <= settings_.residual_tolerance) return true;
      // Stiff penalties (contact) put a round-off floor under the residual; there the
      // correction has become negligible while the residual is still small.
      if (relative <= settings_.floor_tolerance &&
          last_correction <= settings_.correction_tolerance * std::max(u.cwiseAbs().maxCoeff(), 1e-300))
        return true;
      // A state where every force is round-off from the start (all nodes moved rigidly, only
      // hybrid pressures free) has no force scale at all: there, a correction at the
      // round-off of the model's size means that nothing is left to solve.
      if (last_correction <= 1e-13 * model_size_) return true;
      if (!std::isfinite(relative) || it >= settings_.max_iterations) {
        rec.note = it >= settings_.max_iterations ? "no convergence within the iteration limit" : "residual not finite";
        return false;
      }
      // The convergence-rate check of CalculiX and Abaqus (I_0 iterations): a displacement-driven increment
      // whose residual is still far from the quadratic regime after kRateCheckIterations is too large; cutting
      // it back costs less than iterating on
      if (displacement_driven && it >= kRateCheckIterations && relative > kSlowContraction * rec.residual_norms[it - 1]) {
        rec.note = "converging slowly: a smaller increment";
        return false;
      }
      Eigen::VectorXd full;
      if (!correction(Eigen::VectorXd::Zero(n_dofs_), first_of_step && largest_step == 0.0, it, rec, full)) return false;

      // Backtracking line search on |R|: full step first, halved while it fails to
      // reduce the residual (or inverts an element).
      Eigen::VectorXd trial = u + full;
      Evaluation next = evaluate(trial, lambda, true);
      if (!next.ok || next.norm > ev.norm) {
        bool found = false;
        for (double eta = 0.5; eta > 0.01; eta *= 0.5) {
          Eigen::VectorXd shorter = u + eta * full;
          const Evaluation e2 = evaluate(shorter, lambda, false);
          if (e2.ok && e2.norm < ev.norm) {
            trial = shorter;
            found = true;
            break;
          }
        }
        if (found) {
          next = evaluate(trial, lambda, true);
        } else if (!next.ok) {
          rec.note = "every line-search step turns an element inside out";
          return false;
        } else {
          next = evaluate(trial, lambda, true);  // accept the full step; Newton may rise before it falls
        }
      }
      last_correction = (trial - u).cwiseAbs().maxCoeff();
      rises = next.norm > ev.norm ? rises + 1 : 0;
      if (rises >= 6) {
        rec.note = "residual diverging";
        return false;
      }
      u = trial;
      ev = next;
    }
  };

  while (time < s.period * (1.0 - 1e-12)) {
    if (result.increments >= s.max_increments) {
      result.message = "reached the increment limit INC=" + std::to_string(s.max_increments) + " at step time " +
                       std::to_string(time) + "; raise INC on *STEP";
      return result;
    }
    if (s.period - (time + dt) < 1e-9 * s.period) dt = s.period - time;
    dt = std::min(dt, s.period - time);
    const double lambda = (time + dt) / s.period;
    IncrementRecord rec;
    rec.time = time + dt;
    rec.dt = dt;
    Eigen::VectorXd u = u_;
    apply_prescribed(u, last_lambda_in_step);
    Eigen::VectorXd target = u;
    apply_prescribed(target, lambda);
    rec.converged = newton(u, lambda, target - u, rec, time == 0.0 && result.cutbacks == 0, factorization_committed);
    factorization_committed = rec.converged;
    result.records.push_back(rec);
    // An increment whose prescribed displacements invert an element stops before its first residual.
    const int iterations = std::max(static_cast<int>(rec.residual_norms.size()) - 1, 0);
    result.newton_iterations += iterations;
    std::ostringstream line;
    line << "step " << step + 1 << " time " << rec.time << " dt " << dt << ": " << iterations << " iterations, residual ";
    if (rec.residual_norms.empty())
      line << "none";
    else
      line << rec.residual_norms.back();
    line << (rec.converged ? "" : " (cut back: " + rec.note + ")");
    log(line.str());
    if (rec.converged) {
      u_ = u;
      for (ContactState& c : contacts_) c.history = c.trial;
      last_lambda_ = lambda;
      last_lambda_in_step = lambda;
      time += dt;
      result.time_reached = time;
      ++result.increments;
      dt = std::min(dt * next_increment_factor(iterations, previous_iterations, displacement_driven), s.max_dt);
      previous_iterations = iterations;
      continue;
    }
    ++result.cutbacks;
    previous_iterations = 0;
    dt *= 0.25;
    if (dt < s.min_dt * (1.0 - 1e-12)) {
      result.message = "increment below the minimum " + std::to_string(s.min_dt) + " at step time " +
                       std::to_string(time) + " (" + rec.note + ")";
      return result;
    }
  }
  result.converged = true;
  return result;
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
  // Nodal garment pressure: the Laplace load's nodal force over the node's consistent
  // length, along the node's outward normal.
  const int n_nodes = static_cast<int>(model_.coordinates.size());
  out.laplace_pressure = Eigen::VectorXd::Zero(n_nodes);
  Eigen::MatrixXd force = Eigen::MatrixXd::Zero(n_nodes, 2), normal = Eigen::MatrixXd::Zero(n_nodes, 2);
  Eigen::VectorXd length = Eigen::VectorXd::Zero(n_nodes);
  for (const FaceLoad& f : laplace_faces_) {
    const ElementDef& e = model_.elements[f.element];
    const EdgeNodes x = face_positions(f, u_);
    EdgeVector fe;
    laplace_membrane_load(x, f.tension(last_lambda_), fe, nullptr);
    Eigen::VectorXd w;
    EdgeNodes nw;
    face_weights(x, w, nw);
    for (std::size_t k = 0; k < f.local.size(); ++k) {
      const int node = e.nodes[f.local[k]];
      const auto kk = static_cast<Eigen::Index>(k);
      force.row(node) += fe.segment<2>(2 * kk).transpose();
      normal.row(node) += nw.row(kk);
      length[node] += w[kk];
    }
  }
  for (int node = 0; node < n_nodes; ++node)
    if (length[node] > 0.0 && normal.row(node).norm() > 0.0)
      out.laplace_pressure[node] = -force.row(node).dot(normal.row(node).normalized()) / length[node];

  // Contact tractions: as computed on the slave nodes, and on the master nodes the
  // slave forces they receive over their tributary length.
  out.contact_pressure = Eigen::VectorXd::Zero(n_nodes);
  out.contact_shear = Eigen::VectorXd::Zero(n_nodes);
  for (const ContactState& c : contacts_) {
    Eigen::VectorXd master_normal = Eigen::VectorXd::Zero(n_nodes), master_shear = Eigen::VectorXd::Zero(n_nodes);
    for (std::size_t i = 0; i < c.slave_nodes.size(); ++i) {
      const ContactPoint& p = c.points[i];
      if (!p.touching) continue;
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
  const auto tensions = laplace_tensions(state.loads, state.profiles);
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
    if (const auto t = tensions.find(key); t != tensions.end()) {
      laplace_membrane_load(x, t->second, fe, nullptr);
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
