// StaticAnalysis: the model's unknowns (the nodal displacements, then the hybrid elements' pressures), its
// elements and contact pairs, set up once for every step: see static_analysis.hpp.
#include "solver/analysis_support.hpp"

#include <algorithm>
#include <unordered_map>
#include <utility>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace calfit {

using namespace analysis_support;

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
  for (std::size_t j = 0; j < model.sensitivity.parameters.size(); ++j)
    for (const auto& [node, direction] : model.sensitivity.parameters[j].shape)
      shape_of_node_[node].emplace_back(static_cast<int>(j), direction);
  build_contacts();
  carries_path_sensitivities_ =
      model.sensitivity.requested &&
      std::any_of(contacts_.begin(), contacts_.end(), [](const ContactState& c) { return c.law.friction > 0.0; });
  if (carries_path_sensitivities_)
    path_du_.setZero(n_dofs_, static_cast<Eigen::Index>(model.sensitivity.parameters.size()));
  element_force_.resize(elements_.size());
  element_tangent_.resize(elements_.size());
}

}  // namespace calfit
