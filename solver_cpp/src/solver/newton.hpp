// Newton-Raphson in load increments, as StaticAnalysis::run_step solves a step (newton.cpp): the step ramps its
// loads and prescribed displacements over the step time; each increment is solved by Newton-Raphson with the
// consistent tangent (internal + load stiffness) and a backtracking line search on the residual norm; an increment
// that does not converge is retried with a quarter of the time increment, down to the step's minimum (the
// CalculiX *STATIC convention), after which the step is reported not converged. This header: the settings the
// iterations obey, and what each increment and step report (summary.json, output/writers.hpp).
#pragma once

#include <string>
#include <vector>

namespace calfit {

struct SolverSettings {
  double residual_tolerance = 1e-9;    // |R| / reference force
  double floor_tolerance = 1e-6;       // ... accepted above 1e-9 only if also
  double correction_tolerance = 1e-10;  // |du|_inf <= this x |u|_inf
  int max_iterations = 25;
  int threads = 0;  // 0: OpenMP default
};

struct IncrementRecord {
  double time = 0, dt = 0;
  bool converged = false;
  std::vector<double> residual_norms;  // |R| / reference force, per Newton iteration
  std::string note;                    // why it was cut back, if it was
};

// Wall time spent in the parts of the solution, for the summary and benchmarks.
struct Timings {
  double assembly_s = 0, factorization_s = 0;
  int factorizations = 0, reused_factorizations = 0;  // Newton solves that factorized, or reused an earlier factor
  int krylov_steps = 0;  // GMRES steps of the Newton solves (on an earlier factor or a symmetric part's)
};

struct StepResult {
  bool converged = false;
  double time_reached = 0.0;
  int increments = 0, cutbacks = 0, newton_iterations = 0;
  std::vector<IncrementRecord> records;
  std::string message;
};

}  // namespace calfit
