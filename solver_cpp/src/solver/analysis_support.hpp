// Helpers shared by the files of StaticAnalysis (static_analysis.cpp: the unknowns; newton.cpp: increments and
// Newton iterations; analysis_loads.cpp: the loads and kinematics of a step; analysis_contact.cpp: garment contact;
// analysis_assembly.cpp: residual, tangent and field output; analysis_parameters.cpp: what the parameter
// sensitivities need). Internal to them.
#pragma once

#include "element/mixed_element.hpp"
#include "load/edge_loads.hpp"
#include "solver/static_analysis.hpp"

#include <chrono>
#include <map>
#include <memory>
#include <set>
#include <vector>

namespace calfit::analysis_support {

constexpr double kPi = 3.14159265358979323846;

inline double ramp(double start, double end, double lambda) { return start + lambda * (end - start); }

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
inline std::vector<int> local_dofs(const std::vector<int>& local_nodes) {
  std::vector<int> dofs;
  for (int l : local_nodes) {
    dofs.push_back(2 * l);
    dofs.push_back(2 * l + 1);
  }
  return dofs;
}

// Element `index` of the model with the given materials (the model's own, or a
// sensitivity parameter's perturbed copy of them), on reference positions moved by `shifts` (a SHAPE parameter's).
inline std::unique_ptr<Element> make_element(const Model& model, const std::vector<MaterialDef>& materials, int index,
                                             const std::map<int, Eigen::Vector2d>* shifts = nullptr) {
  const ElementDef& e = model.elements[index];
  const SectionDef& s = model.sections[e.section];
  const Material& law = *materials[s.material].law;
  const int degree = e.shape == ElementShape::T3 ? 1 : (s.full_integration ? 4 : 2);
  NodeMatrix X(node_count(e.shape), 2);
  for (int k = 0; k < X.rows(); ++k) {
    X.row(k) = model.coordinates[e.nodes[k]].transpose();
    if (shifts)
      if (const auto moved = shifts->find(e.nodes[k]); moved != shifts->end()) X.row(k) += moved->second.transpose();
  }
  if (!e.hybrid) return std::make_unique<SolidElement>(e.shape, X, law, s.thickness, degree);
  return std::make_unique<MixedElement>(e.shape, X, dynamic_cast<const SplitHyperelastic&>(law), s.thickness, degree);
}

}  // namespace calfit::analysis_support
