// How calfit-fe takes its threads on Linux, the policy that made its runs fast on a machine with few cores
// shared with other programs (solver_cpp/README.md, Threads; benchmarks/threads.py). The element loops give the
// same bytes on any thread count, so none of this changes a digit of a run, only its time:
// - the element loops take the CPUs of this process that other programs leave idle now (default_threads);
// - OpenMP's and OpenBLAS's worker threads sleep instead of spinning, and OpenBLAS starts none: both read their
//   environment when they are loaded, before main, so the process restarts itself once with it set
//   (restart_with_thread_environment);
// - the BLAS under CHOLMOD runs on one thread (set_blas_threads);
// - freed memory stays with the process for the next allocation (keep_freed_memory).
// Each call reads the environment and /proc as they are now; none keeps state.
#pragma once

namespace calfit::platform {

// The default thread count: OMP_NUM_THREADS when the caller set it, else the CPUs of this process that other
// programs leave idle now, at least 1.
int default_threads();

// Restarts the process (execv of /proc/self/exe with `argv`) once with OMP_WAIT_POLICY=PASSIVE (unless set) and
// OPENBLAS_NUM_THREADS=1, when its environment differs; returns when it already has them, or when the restart
// fails (the run then carries on as it is).
void restart_with_thread_environment(char** argv);

// The BLAS's own thread count, through OpenBLAS's openblas_set_num_threads when that is linked (any other BLAS
// is left as it is).
void set_blas_threads(int threads);

// glibc's malloc hands blocks above a threshold (128 KiB, rising to at most 32 MiB as such blocks are freed) to
// mmap and returns them at free, and gives the top of the heap back past another: every solve's vectors of
// 22.5k doubles, GMRES's basis and each UMFPACK factorization's workspace came as fresh pages, zeroed by the kernel
// at first touch (a sixth of the garment deck's run in page faults and clearing, 100k faults where 11k remain).
// Both thresholds are raised so that the process keeps what it frees for its next allocation; a block larger than
// 256 MiB still gets its own mapping. The peak resident memory is that of the largest allocations held at once, as
// before. A no-op without glibc.
void keep_freed_memory();

}  // namespace calfit::platform
