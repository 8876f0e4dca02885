// The fields of a converged state, as the writers put them in each step's VTU (output/writers.hpp,
// solver_cpp/README.md, Outputs): StaticAnalysis::output fills them, the sensitivities add their own.
#pragma once

#include "element/element.hpp"

#include <Eigen/Dense>
#include <string>
#include <utility>
#include <vector>

namespace calfit {

struct FieldOutput {
  Eigen::VectorXd displacement;                // 2 n_nodes
  Eigen::VectorXd reaction;                    // 2 n_nodes: f_int - f_ext
  std::vector<ElementState> element_states;
  Eigen::VectorXd laplace_pressure;            // n_nodes: the garment pressure applied, (1 - alpha) T / r + alpha p0 (0 off the surface)
  Eigen::VectorXd contact_pressure, contact_shear;  // n_nodes: on slave and master nodes of contact pairs
  // n_nodes, on slave nodes: Abaqus's CSTATUS (0 open, 1 sticking, 2 slipping; frictionless contact slips), and the
  // slave's tangential slip over the master since its first touch (mm; tracked with friction only, 0 without)
  Eigen::VectorXd contact_status, contact_slip;
  // Further named fields (sensitivities): nodal vectors (2 n_nodes, x y per node) and
  // element scalars (n_elements).
  std::vector<std::pair<std::string, Eigen::VectorXd>> point_vectors, cell_scalars;
};

}  // namespace calfit
