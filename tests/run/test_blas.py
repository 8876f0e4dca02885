"""One BLAS thread in the orchestrator's processes (`run.blas`), unless the user chose a count."""

from __future__ import annotations

import os

import numpy as np
from threadpoolctl import threadpool_info

from orchestrator.run.blas import ASKED, single_blas_thread


def test_a_count_the_user_chose_is_theirs(monkeypatch):
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    assert single_blas_thread() == 0
    assert os.environ["OPENBLAS_NUM_THREADS"] == "2"


def test_numpy_and_scipy_are_set_to_one_thread_and_compute_as_before(monkeypatch):
    for name in ASKED:   # set first, so that monkeypatch puts back what the worker had
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 200))
    covariance = a @ a.T + 200 * np.eye(200)
    before = np.linalg.eigvalsh(covariance)
    assert single_blas_thread() >= 1
    assert all(pool["num_threads"] == 1 for pool in threadpool_info() if pool["user_api"] == "blas")
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"   # for the processes started from here
    np.testing.assert_allclose(np.linalg.eigvalsh(covariance), before, rtol=1e-12)
