"""Newton health of calfit-fe: quadratic convergence, and a clean exit 3 when it cannot converge.

With the consistent tangent (material, geometric, and the load stiffness of follower and
Laplace pressures) Newton-Raphson converges quadratically near the solution; an
inconsistent tangent shows first here (STYLE.md). On the relative residual norms r_k of
summary.json, every pair in the asymptotic range (r_k < 1e-2, and C r_k^2 above the
round-off floor 1e-13) must satisfy r_{k+1} <= C r_k^2 with C = 10 (a tangent error of
even 10 % gives r_{k+1} ~ 0.1 r_k, i.e. r_{k+1} / r_k^2 >= 100 there).

An impossible load must give exit 3, "status": "not_converged", and the last converged
increment written. St Venant-Kirchhoff softens in compression: a unit square on rollers
under a follower pressure on its top face has no equilibrium beyond the limit pressure
max over l2 of -sigma_yy(l1(l2), l2) with sigma_xx = 0 (about 0.187 E for nu = 0.3,
computed here). A pressure of 0.5 E must stop there: the written state must be in
equilibrium with the load reached (closed-form stresses of its stretches), and that load
must be the limit pressure.
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_closed_forms import Law, stretch_for_stress_given_other
from engine_run import run_engine
from fe_cases import deck, ring, unit_square
from scipy import optimize

FLOOR = 1e-13  # relative residuals below this are round-off
C_QUAD = 10.0


def asymptotic_pairs(history: list[float]) -> list[tuple[float, float]]:
    return [(a, b) for a, b in zip(history, history[1:]) if a < 1e-2 and C_QUAD * a * a > FLOOR]


def _cases():
    quarter = ring(4, 8, 2, quarter=True)
    full_ellipse = ring(3, 32, 2, outer=(2.4, 1.6))
    square = unit_square(2, 2)
    sym = [("INNER", 1, 2), ("XSYM", 1, 1), ("YSYM", 2, 2)]
    one_inc = (1.0, 1.0, 1e-4, 1.0)
    return {
        "avril follower pressure": deck(quarter, Law("AVRIL", (1.0, 10.0)), fixed=sym, pressure=[("OUTER", 2.0)], static=one_inc),
        "mooney-rivlin follower pressure": deck(
            quarter, Law("MOONEY-RIVLIN", (0.7, 0.3, 0.1)), fixed=sym, pressure=[("OUTER", 1.0)], static=one_inc
        ),
        "arruda-boyce follower pressure": deck(
            quarter, Law("ARRUDA-BOYCE", (2.0, 1.5, 0.1)), fixed=sym, pressure=[("OUTER", 1.0)], static=one_inc
        ),
        "reduced polynomial N=3": deck(
            quarter, Law("REDUCED POLYNOMIAL", (1.0, 0.4, 0.2, 0.1, 0.5, 1.0), n=3), fixed=sym,
            pressure=[("OUTER", 1.0)], static=one_inc,
        ),
        "laplace pressure on an ellipse": deck(
            full_ellipse, Law("AVRIL", (1.0, 10.0)), fixed=[("INNER", 1, 2)], laplace=[("OUTER", 3.0)], static=one_inc
        ),
        "st venant-kirchhoff square": deck(
            square, Law("ELASTIC", (10.0, 0.3)), fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)], pressure=[("TOP", 1.0)],
            static=one_inc,
        ),
    }


CASES = _cases()


@pytest.mark.parametrize("name", list(CASES))
def test_quadratic_convergence(tmp_path, name):
    run = run_engine(CASES[name], tmp_path)
    assert run.returncode == 0, run.stderr
    histories = run.residual_histories()
    assert histories, "summary.json has no residual_norms"
    pairs = [pr for h in histories for pr in asymptotic_pairs(h)]
    assert pairs, f"no increment reached the asymptotic range: {histories}"
    worst = max(b / (a * a) for a, b in pairs)
    assert worst <= C_QUAD, f"r_(k+1) / r_k^2 up to {worst:.3g}; histories {histories}"
    for h in histories:
        if h:
            assert h[-1] < 1e-8, h
    step = run.summary["steps"][0]
    assert step["status"] == "converged"
    assert step["time_reached"] == pytest.approx(1.0)
    assert step["newton_iterations"] == sum(len(inc["residual_norms"]) for inc in step["increments"]) or \
        step["newton_iterations"] == sum(max(len(inc["residual_norms"]) - 1, 0) for inc in step["increments"])


def svk_limit_pressure(law: Law) -> float:
    """Largest follower pressure a St Venant-Kirchhoff square on rollers can carry."""

    def sigma_yy(l2):
        l1 = stretch_for_stress_given_other(law, l2, 0.0)
        return law.principal_cauchy(l1, l2)[1]

    res = optimize.minimize_scalar(sigma_yy, bounds=(0.35, 0.95), method="bounded", options={"xatol": 1e-12})
    return -float(res.fun)


def test_impossible_load_exits_3_with_last_converged_state(tmp_path):
    E = 10.0
    law = Law("ELASTIC", (E, 0.3))
    p_limit = svk_limit_pressure(law)
    assert 0.18 * E < p_limit < 0.19 * E
    mesh = unit_square(2, 1)
    p = 0.5 * E
    text = deck(
        mesh, law, fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)], pressure=[("TOP", p)], static=(0.05, 1.0, 1e-4, 0.05)
    )
    run = run_engine(text, tmp_path, timeout=120)
    assert run.returncode == 3, (run.returncode, run.stderr)
    assert "job.inp" in run.stderr
    assert run.summary is not None and run.summary["status"] == "not_converged"
    assert run.summary["exit_code"] == 3
    step = run.summary["steps"][0]
    assert step["status"] == "not_converged"
    t = step["time_reached"]
    assert 0.0 < t < 1.0
    assert (run.outdir / "step-1.vtu").is_file()
    assert run.table is not None and np.all(np.isfinite(run.table))
    # The written state is an equilibrium state for the load reached, p t ...
    corner = mesh.nsets["CORNER"][0]
    l1, l2 = 1.0 + run.u()[corner]
    s1, s2 = law.principal_cauchy(l1, l2)
    assert abs(s1) < 1e-8 * p and s2 == pytest.approx(-p * t, rel=1e-8)
    cell = np.concatenate(run.vtu(1).cell_data["cauchy_stress"])
    assert np.allclose(cell[:, 1], -p * t, rtol=1e-8)
    # ... and that load is the limit load (to the minimum increment, 1e-4 of the step).
    assert p * t == pytest.approx(p_limit, rel=2e-3)
    assert p * t <= p_limit * (1 + 1e-9)


def test_increment_limit_exits_3(tmp_path):
    """INC= caps the number of increments: 0.1-wide increments cannot reach t = 1 in 3."""
    mesh = unit_square(1, 1)
    text = deck(
        mesh, Law("NEO HOOKE", (1.0, 0.1)), fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)], pressure=[("TOP", 0.1)],
        static=(0.1, 1.0, 1e-5, 0.1), inc=3,
    )
    run = run_engine(text, tmp_path)
    assert run.returncode == 3, run.stderr
    assert run.summary["status"] == "not_converged"
    assert run.summary["steps"][0]["time_reached"] == pytest.approx(0.3)


def test_results_do_not_depend_on_the_machines_load(tmp_path):
    """The linear solver's choices (reuse an earlier factor, or factorize; LDL^T or LU) are made on counts, not
    timings: the same deck run alone and beside two busy processes gives the same solves and the same bytes. The
    leg under a pressure varying around it (an unsymmetric tangent, GMRES on Cholesky factors, factor reuse)."""
    import subprocess
    import sys
    from pathlib import Path

    deck_text = (Path(__file__).resolve().parents[1] / "support" / "ccx_reference" / "leg_follower_cpe6.inp").read_text()
    quiet = run_engine(deck_text, tmp_path / "quiet")
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        busy = run_engine(deck_text, tmp_path / "busy")
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()
    assert quiet.returncode == busy.returncode == 0, quiet.stderr + busy.stderr
    assert quiet.summary["linear_solves"] == busy.summary["linear_solves"]
    assert quiet.summary["linear_solves"]["reused"] > 0  # the choice this guards was made
    assert np.array_equal(quiet.table, busy.table)


def _leg_follower_deck() -> str:
    from pathlib import Path

    return (Path(__file__).resolve().parents[1] / "support" / "ccx_reference" / "leg_follower_cpe6.inp").read_text()


def test_the_thread_count_changes_no_digit(tmp_path):
    """The element loops compute each element on its own and gather them in a fixed order, and the BLAS under
    CHOLMOD runs on one thread (a threaded dgemm changed the displacements by 5e-15 mm between 1 and 2 threads):
    the default thread count can follow the machine's load without moving a digit."""
    one = run_engine(_leg_follower_deck(), tmp_path / "one", extra_args=("--threads", "1"))
    three = run_engine(_leg_follower_deck(), tmp_path / "three", extra_args=("--threads", "3"))
    assert one.returncode == three.returncode == 0, one.stderr + three.stderr
    assert (one.summary["threads"], three.summary["threads"]) == (1, 3)
    assert np.array_equal(one.table, three.table)


def test_the_default_leaves_the_cores_that_other_programs_use(tmp_path, monkeypatch):
    """Without --threads, calfit-fe takes the cores other programs leave idle when it starts (two threads beside
    another engine on a 2-core machine ran 2.4x slower than one, 14x beside two: benchmarks/threads.py); the
    caller's OMP_NUM_THREADS and --threads win."""
    import os
    import subprocess
    import sys
    import time

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    cores = len(os.sched_getaffinity(0))
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)]
    try:
        time.sleep(0.5)     # the burners running before the engine looks
        crowded = run_engine(_leg_follower_deck(), tmp_path / "crowded")
        asked = run_engine(_leg_follower_deck(), tmp_path / "asked", extra_args=("--threads", "2"))
        monkeypatch.setenv("OMP_NUM_THREADS", "3")
        told = run_engine(_leg_follower_deck(), tmp_path / "told")
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()
    assert crowded.returncode == asked.returncode == told.returncode == 0
    assert crowded.summary["threads"] == 1
    assert asked.summary["threads"] == 2 and told.summary["threads"] == 3
