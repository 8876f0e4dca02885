// Result files of calfit-fe (formats in solver_cpp/README.md): VTK XML unstructured
// grid per step, a NumPy .npy table of nodal displacements, and summary.json. Each
// is written to a temporary name and renamed, so no reader sees a partial file.
#pragma once

#include "model/model.hpp"
#include "solver/field_output.hpp"
#include "solver/newton.hpp"

#include <string>
#include <vector>

namespace calfit {

void write_vtu(const std::string& path, const Model& model, const FieldOutput& fields);
void write_displacement_table(const std::string& path, const Model& model, const Eigen::VectorXd& u);

struct StepSummary {
  StepResult result;
  std::string vtu, table;
};
// One requested sensitivity parameter, as summary.json lists it.
struct SensitivitySummary {
  int index = 0;  // 1-based, deck order
  std::string name, file;
  double value = 0, max_abs_du = 0;
};
struct RunSummary {
  std::string deck, status, message, linear_solver;
  int exit_code = 0;
  double wall_time_s = 0, parse_s = 0, output_s = 0, sensitivity_s = 0;
  std::vector<SensitivitySummary> sensitivities;
  Timings timings;
  int n_nodes = 0, n_elements = 0, n_dof = 0, n_free_dof = 0, threads = 0;
  std::vector<StepSummary> steps;
};
void write_summary(const std::string& path, const RunSummary& summary);

}  // namespace calfit
