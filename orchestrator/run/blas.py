"""One BLAS thread in the orchestrator's processes.

The orchestrator's linear algebra is small (a few thousand values: the whitening's eigendecomposition, the DIC's
windows, Levenberg-Marquardt's steps), and it runs beside the engine's processes and the DIC's workers on the
same cores. OpenBLAS's own threads then wait for cores the others hold, and spin while they wait: on this 2-core
machine, busy, the eigendecomposition of a 632-value covariance took 0.1-1.0 s with two BLAS threads and 0.05 s
with one, and benchmarks/loop.py's images-first path spent 2.3-2.8 s whitening with two against 1.0 s with one
(its DIC 9.1-9.6 s against 7.3 s). The engine chooses its own (solver_cpp platform/thread_policy).

`single_blas_thread` limits the BLAS libraries this process has loaded (numpy's, scipy's) to one thread with
threadpoolctl, and sets OPENBLAS_NUM_THREADS=1 for the processes it starts, unless the user asked for a count
(OPENBLAS_NUM_THREADS, OMP_NUM_THREADS or MKL_NUM_THREADS set): that is theirs."""

from __future__ import annotations

import os

ASKED = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_blas_thread() -> int:
    """One BLAS thread (module text); returns how many libraries were limited (0 when the user set a count)."""
    if any(os.environ.get(name) for name in ASKED):
        return 0
    os.environ["OPENBLAS_NUM_THREADS"] = "1"   # the processes started from here (DIC workers, evaluators)
    import numpy  # noqa: F401  (their libraries loaded, to be limited)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import ThreadpoolController

    blas = ThreadpoolController().select(user_api="blas")
    blas.limit(limits=1)   # applied now, and kept: nothing restores it
    return len(blas.lib_controllers)
