// calfit-fe's thread policy on Linux: see thread_policy.hpp.
#include "platform/thread_policy.hpp"

#include <dlfcn.h>
#ifdef __GLIBC__
#include <malloc.h>
#endif
#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <climits>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>
#include <thread>

namespace calfit::platform {

namespace {

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

}  // namespace

// The idle CPUs are sampled three times 2 ms apart and the fewest busy counted: a passing burst is ignored, a busy
// program is seen every time. Two threads on a 2-core machine beside one busy program ran 2.4x slower than one
// thread, beside two 14x (benchmarks/threads.py).
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
// --threads 1): the restart also sets OPENBLAS_NUM_THREADS=1 (set_blas_threads), so that none is started. The
// thread count is chosen after the restart (the analysis sets it with omp_set_num_threads), so that the first
// process does no more than exec: sampling the idle cores there, and OMP_NUM_THREADS for the second, cost it
// 9 ms of a 20 ms start on the loaded 2-core machine.
void restart_with_thread_environment(char** argv) {
  bool changed = false;
  if (std::getenv("OMP_WAIT_POLICY") == nullptr) changed = setenv("OMP_WAIT_POLICY", "PASSIVE", 1) == 0;
  const char* blas = std::getenv("OPENBLAS_NUM_THREADS");
  if ((blas == nullptr || std::string(blas) != "1") && setenv("OPENBLAS_NUM_THREADS", "1", 1) == 0) changed = true;
  if (changed) execv("/proc/self/exe", argv);
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

void keep_freed_memory() {
#ifdef __GLIBC__
  constexpr int kOwnMapping = 256 << 20, kKeptTop = 512 << 20;
  mallopt(M_MMAP_THRESHOLD, kOwnMapping);
  mallopt(M_TRIM_THRESHOLD, kKeptTop);
#endif
}

}  // namespace calfit::platform
