// calfit-fe: command-line entry of the engine. Reads a deck, solves its steps, writes
// the results (see solver_cpp/README.md) and maps every outcome to an exit code:
// 0 converged, 2 bad deck or mesh, 3 not converged (last converged state written),
// 4 any other failure.
#include "deck/build_model.hpp"
#include "output/writers.hpp"
#include "platform/thread_policy.hpp"
#include "solver/sensitivity.hpp"
#include "solver/static_analysis.hpp"

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <future>
#include <iostream>
#include <new>
#include <string>
#include <vector>

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
  platform::restart_with_thread_environment(argv);
  platform::keep_freed_memory();
  if (args.outdir.empty()) args.outdir = default_outdir(args.deck);
  platform::set_blas_threads(1);
  const auto start = std::chrono::steady_clock::now();
  // The idle cores are sampled (default_threads sleeps 2 ms between its samples) while the deck is read.
  std::future<int> sampled_threads;
  if (args.threads == 0) sampled_threads = std::async(std::launch::async, platform::default_threads);
  auto log = [&](const std::string& line) {
    if (!args.quiet) std::cout << line << '\n';
  };

  Model model;
  try {
    model = build_model(args.deck);
    if (sampled_threads.valid()) args.threads = sampled_threads.get();
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
