"""Newton health of calfit-fe: quadratic convergence, and a clean exit 3 when it cannot converge.

With the consistent tangent (material, geometric, and the load stiffness of follower and
Laplace pressures) Newton-Raphson converges quadratically near the solution; an
inconsistent tangent shows first here (STYLE.md). From the relative residual norms of
summary.json we estimate the observed order q = log(r_{k+1}/r_k) / log(r_k/r_{k-1}) on the
last three iterates above the round-off floor, and require q >= 1.6 (1 for a wrong
tangent) in every increment that has such a triple.

An impossible load (a follower pressure far beyond the one that collapses the annulus)
must give exit 3, "status": "not_converged", and the last converged increment written:
its displacement must be the closed-form solution at the load it reached.
"""

from __future__ import annotations

import numpy as np
import pytest

from engine_closed_forms import Law, annulus
from engine_run import run_engine
from fe_cases import deck, ring, unit_square

FLOOR = 1e-13  # relative residuals below this are round-off


def observed_orders(history: list[float]) -> list[float]:
    r = [x for x in history if x > FLOOR]
    out = []
    for k in range(2, len(r)):
        a, b, c = r[k - 2], r[k - 1], r[k]
        if b < 0.1 and b < a:  # asymptotic range
            out.append(np.log(c / b) / np.log(b / a))
    return out


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
    orders = [q for h in histories for q in observed_orders(h)[-1:]]
    assert orders, f"no increment reached the asymptotic range: {histories}"
    assert min(orders) >= 1.6, f"observed Newton orders {orders}; histories {histories}"
    for h in histories:
        if h:
            assert h[-1] < 1e-8, h
    step = run.summary["steps"][0]
    assert step["status"] == "converged"
    assert step["time_reached"] == pytest.approx(1.0)
    assert step["newton_iterations"] == sum(len(inc["residual_norms"]) for inc in step["increments"]) or \
        step["newton_iterations"] == sum(max(len(inc["residual_norms"]) - 1, 0) for inc in step["increments"])


def test_impossible_load_exits_3_with_last_converged_state(tmp_path):
    law = Law("AVRIL", (1.0, 10.0))
    mesh = ring(3, 6, 2, quarter=True)
    p = 200.0
    text = deck(
        mesh, law, fixed=[("INNER", 1, 2), ("XSYM", 1, 1), ("YSYM", 2, 2)], pressure=[("OUTER", p)],
        static=(0.005, 1.0, 1e-5, 0.005), inc=1000,
    )
    run = run_engine(text, tmp_path, timeout=120)
    assert run.returncode == 3, (run.returncode, run.stderr)
    assert run.summary is not None and run.summary["status"] == "not_converged"
    assert run.summary["exit_code"] == 3
    step = run.summary["steps"][0]
    assert step["status"] == "not_converged"
    t = step["time_reached"]
    assert 0.0 < t < 1.0
    assert (run.outdir / "step-1.vtu").is_file()
    assert run.table is not None and np.all(np.isfinite(run.table))
    # The written state is the converged solution at the load reached, p * t.
    ref = annulus(law, p=p * t)
    outer = mesh.nsets["OUTER"]
    ur = np.sum(run.u()[outer] * mesh.nodes[outer], axis=1) / 2.0
    assert np.mean(ur) == pytest.approx(float(ref.u_r(2.0)), rel=2e-2)
    J = np.concatenate(run.vtu(1).cell_data["J"])
    assert np.all(J > 0)


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
