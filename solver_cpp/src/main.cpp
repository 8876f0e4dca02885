// calfit-fe: command-line entry of the engine. Reads a deck, solves its steps, writes
// the results (see solver_cpp/README.md) and maps every outcome to an exit code:
// 0 converged, 2 bad deck or mesh, 3 not converged (last converged state written),
// 4 any other failure.
#include "deck/build_model.hpp"
#include "output/writers.hpp"
#include "solver/sensitivity.hpp"
#include "solver/static_analysis.hpp"

#include <dlfcn.h>
#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <climits>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <new>
#include <string>
#include <thread>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr int kConverged = 0, kUsage = 2, kBadDeck = 2, kNotConverged = 3, kFailure = 4;

struct Arguments {
  std::string deck, outdir;
  int threads = 0;
  bool quiet = false;
};

const char* kUsageText =
    "usage: calfit-fe DECK.inp [-o OUTDIR] [--threads N] [--quiet]\n"
    "  Solves a plane-strain finite-strain deck; writes step-N.vtu, step-N.u.npy and summary.json\n"
    "  (and step-N.du-K.npy for the parameters of *SENSITIVITY)\n"
    "  into OUTDIR (default: DECK without .inp, plus .out). Exit: 0 converged, 2 bad deck,\n"
    "  3 not converged, 4 other failure. --threads N: the element loops' threads (default: OMP_NUM_THREADS,\n"
    "  else the cores other programs leave idle now); the BLAS runs on one.\n";

bool parse_arguments(int argc, char** argv, Arguments& args) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if ((a == "-o" || a == "--output") && i + 1 < argc) {
      args.outdir = argv[++i];
    } else if (a == "--threads" && i + 1 < argc) {
      char* end = nullptr;
      const long n = std::strtol(argv[++i], &end, 10);
      if (*end != '\0' || n < 1 || n > 1024) return false;
      args.threads = static_cast<int>(n);
    } else if (a == "--quiet" || a == "-q") {
      args.quiet = true;
    } else if (a == "-h" || a == "--help") {
      std::cout << kUsageText;
      std::exit(0);
    } else if (!a.empty() && a[0] != '-' && args.deck.empty()) {
      args.deck = a;
    } else {
      return false;
    }
  }
  return !args.deck.empty();
}

// The BLAS under CHOLMOD runs on one thread whatever --threads says: a threaded dgemm splits its sums by thread
// and changed the leg deck's displacements by 5e-15 mm between 1 and 2 threads, where the element loops, each
// element on its own and gathered in a fixed order, give the same bytes on any count; on plane slices its
// supernodes are small and the second thread bought little (solver_cpp/README.md, Threads). OpenBLAS exposes its
// setter as a C symbol, looked up at run time so that another BLAS links too.
void set_blas_threads(int threads) {
  using Setter = void (*)(int);
  if (void* symbol = dlsym(RTLD_DEFAULT, "openblas_set_num_threads")) reinterpret_cast<Setter>(symbol)(threads);
}

int usable_cpus() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof set, &set) == 0) return std::max(1, CPU_COUNT(&set));
  return std::max(1u, std::thread::hardware_concurrency());
}

// Threads of the whole system runnable now (/proc/stat procs_running) less this process's own (state R in
// /proc/self/task/*/stat: the BLAS workers spinning at load would otherwise pass for another program); -1 when
// /proc cannot tell.
int others_runnable() {
  std::ifstream stat("/proc/stat");
  int running = -1;
  for (std::string line; std::getline(stat, line);)
    if (line.rfind("procs_running ", 0) == 0) running = std::atoi(line.c_str() + 14);
  if (running < 0) return -1;
  int own = 0;
  std::error_code error;
  for (const auto& task : std::filesystem::directory_iterator("/proc/self/task", error)) {
    std::ifstream task_stat(task.path() / "stat");
    std::string text;
    std::getline(task_stat, text);
    const std::size_t close = text.rfind(')');
    if (close != std::string::npos && close + 2 < text.size() && text[close + 2] == 'R') ++own;
  }
  return std::max(0, running - own);
}

// The default thread count: OMP_NUM_THREADS when the caller set it, else the CPUs of this process that other
// programs leave idle now (sampled three times 2 ms apart, the fewest busy counted: a passing burst is ignored, a
// busy program is seen every time), at least 1. Two threads on a 2-core machine beside one busy program ran 2.4x
// slower than one thread, beside two 14x (benchmarks/threads.py); the element loops give the same bytes on any
// count, so the choice changes the time of a run, not its digits.
int default_threads() {
  if (const char* given = std::getenv("OMP_NUM_THREADS")) {
    const int n = std::atoi(given);
    if (n > 0) return n;
  }
  const int cpus = usable_cpus();
  int busy = INT_MAX;
  for (int sample = 0; sample < 3; ++sample) {
    if (sample > 0) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    const int others = others_runnable();
    if (others >= 0) busy = std::min(busy, others);
  }
  if (busy == INT_MAX) return cpus;
  return std::clamp(cpus - busy, 1, cpus);
}

// OpenMP's worker threads spin after every parallel region and OpenBLAS's after every BLAS call: on a machine
// with few cores each steals the other's core (assembling 800 T6 took 5 times longer than with them asleep).
// libgomp reads OMP_WAIT_POLICY when it is loaded, before main, so a process started without it restarts
// itself once with PASSIVE. OpenBLAS starts its worker threads when it is loaded too, and they spin (sched_yield)
// for a while even when --threads keeps them idle (a sixth of a 22.5k-DOF run's samples on the second core with
// --threads 1): the restart also sets OPENBLAS_NUM_THREADS=1 (set_blas_threads), so that none is started, and
// OMP_NUM_THREADS to the count chosen (default_threads), so that the restarted process keeps it. If the restart
// fails it carries on as it is.
void restart_with_thread_environment(const Arguments& args, char** argv) {
  bool changed = false;
  if (std::getenv("OMP_WAIT_POLICY") == nullptr) changed = setenv("OMP_WAIT_POLICY", "PASSIVE", 1) == 0;
  const char* blas = std::getenv("OPENBLAS_NUM_THREADS");
  if ((blas == nullptr || std::string(blas) != "1") && setenv("OPENBLAS_NUM_THREADS", "1", 1) == 0) changed = true;
  const std::string threads = std::to_string(args.threads);
  const char* omp = std::getenv("OMP_NUM_THREADS");
  if ((omp == nullptr || threads != omp) && setenv("OMP_NUM_THREADS", threads.c_str(), 1) == 0) changed = true;
  if (changed) execv("/proc/self/exe", argv);
}

std::string default_outdir(const std::string& deck) {
  std::filesystem::path p(deck);
  if (p.extension() == ".inp") p.replace_extension();
  return p.string() + ".out";
}

}  // namespace

int main(int argc, char** argv) {
  using namespace calfit;
  Arguments args;
  if (!parse_arguments(argc, argv, args)) {
    std::cerr << kUsageText;
    return kUsage;
  }
  if (args.threads == 0) args.threads = default_threads();
  restart_with_thread_environment(args, argv);
  if (args.outdir.empty()) args.outdir = default_outdir(args.deck);
  set_blas_threads(1);
  const auto start = std::chrono::steady_clock::now();
  auto log = [&](const std::string& line) {
    if (!args.quiet) std::cout << line << '\n';
  };

  Model model;
  try {
    model = build_model(args.deck);
  } catch (const DeckError& e) {
    std::cerr << e.what() << '\n';
    return kBadDeck;
  } catch (const std::exception& e) {
    std::cerr << args.deck << ":0: " << e.what() << '\n';
    return kBadDeck;
  }

  RunSummary summary;
  summary.deck = args.deck;
  summary.parse_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  summary.n_nodes = static_cast<int>(model.coordinates.size());
  summary.n_elements = static_cast<int>(model.elements.size());
  summary.n_dof = model.dof_count();
#ifdef _OPENMP
  summary.threads = args.threads;
#else
  summary.threads = 1;
#endif
  const std::string summary_path = (std::filesystem::path(args.outdir) / "summary.json").string();
  auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); };

  try {
    std::filesystem::create_directories(args.outdir);
    SolverSettings settings;
    settings.threads = args.threads;
    StaticAnalysis analysis(model, settings);
    summary.status = "converged";
    for (std::size_t k = 0; k < model.steps.size(); ++k) {
      StepSummary step;
      step.result = analysis.run_step(static_cast<int>(k), log);
      summary.n_free_dof = analysis.free_dof_count();
      summary.linear_solver = analysis.linear_solver();
      const std::string stem = "step-" + std::to_string(k + 1);
      step.vtu = stem + ".vtu";
      step.table = stem + ".u.npy";
      summary.timings = analysis.timings();
      const bool ok = step.result.converged;

      // Sensitivities of the last step's converged state, written with that step.
      std::vector<ParameterSensitivity> sensitivities;
      if (ok && k + 1 == model.steps.size() && model.sensitivity.requested) {
        const auto sensitivity_start = std::chrono::steady_clock::now();
        sensitivities = SensitivityAnalysis(model, analysis).compute();
        summary.sensitivity_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - sensitivity_start).count();
      }

      const auto output_start = std::chrono::steady_clock::now();
      FieldOutput fields = analysis.output();
      for (const ParameterSensitivity& s : sensitivities) {
        fields.point_vectors.emplace_back("du/d" + s.name, s.du.head(model.dof_count()));
        if (s.dpressure.size()) fields.cell_scalars.emplace_back("dp/d" + s.name, s.dpressure);
      }
      write_vtu((std::filesystem::path(args.outdir) / step.vtu).string(), model, fields);
      write_displacement_table((std::filesystem::path(args.outdir) / step.table).string(), model, fields.displacement);
      for (std::size_t j = 0; j < sensitivities.size(); ++j) {
        SensitivitySummary entry;
        entry.index = static_cast<int>(j + 1);
        entry.name = sensitivities[j].name;
        entry.value = sensitivities[j].value;
        entry.max_abs_du = sensitivities[j].max_abs_du;
        entry.file = stem + ".du-" + std::to_string(j + 1) + ".npy";
        write_displacement_table((std::filesystem::path(args.outdir) / entry.file).string(), model, sensitivities[j].du);
        summary.sensitivities.push_back(entry);
      }
      summary.output_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - output_start).count();
      summary.steps.push_back(step);
      if (!ok) {
        summary.status = "not_converged";
        summary.exit_code = kNotConverged;
        summary.message = "step " + std::to_string(k + 1) + " did not converge: " + step.result.message +
                          "; the last converged state (step time " + std::to_string(step.result.time_reached) +
                          ") is written";
        summary.wall_time_s = elapsed();
        write_summary(summary_path, summary);
        std::cerr << args.deck << ": " << summary.message << '\n';
        return kNotConverged;
      }
      summary.wall_time_s = elapsed();
      write_summary(summary_path, summary);
    }
    log("converged in " + std::to_string(elapsed()) + " s; results in " + args.outdir);
    return kConverged;
  } catch (const DeckError& e) {
    std::cerr << e.what() << '\n';
    return kBadDeck;
  } catch (const std::bad_alloc&) {
    std::cerr << args.deck << ": out of memory\n";
    return kFailure;
  } catch (const std::exception& e) {
    std::cerr << args.deck << ": " << e.what() << '\n';
    try {
      summary.status = "failed";
      summary.exit_code = kFailure;
      summary.message = e.what();
      summary.wall_time_s = elapsed();
      write_summary(summary_path, summary);
    } catch (...) {
    }
    return kFailure;
  }
}
