"""Annulus under a follower pressure: calfit-fe against the axisymmetric finite-strain solution.

Inner radius 1 clamped, outer radius 2 loaded by a follower pressure p, Avril law
W = C10 (I1bar-3) + Kv [(J^2-1)/2 - ln J] with C10 = 1, plane strain. Issue 2 quotes
u_r(2) = -1.770086e-3 (Kv=10, p=0.05), -1.755893e-2 (Kv=10, p=0.5), -6.830609e-2
(Kv=10, p=2), -6.865956e-2 (Kv=2, p=0.5). The reference here is our own solution of the
axisymmetric boundary-value problem (engine_closed_forms.annulus, scipy solve_bvp at
tol 1e-10), which must first reproduce those 7-digit values. The engine runs a quarter
annulus with symmetry rollers on polar-structured T3 / T6 meshes (T6 isoparametric, the
mid-side nodes on the arcs); the L2 norm of the displacement error must fall at the
optimal rates, about h^2 for T3 and h^3 for T6 (rate fitted with
np.polyfit(np.log(h), np.log(err), 1)).
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_closed_forms import Law, annulus
from engine_run import run_engine
from fe_cases import deck, l2_error, ring

ISSUE_VALUES = [  # (Kv, p, u_r(2)) from issue 2
    (10.0, 0.05, -1.770086e-3),
    (10.0, 0.5, -1.755893e-2),
    (10.0, 2.0, -6.830609e-2),
    (2.0, 0.5, -6.865956e-2),
]


def annulus_deck(nr: int, order: int, law: Law, p: float) -> tuple[object, str]:
    mesh = ring(nr, 2 * nr, order, quarter=True)
    text = deck(
        mesh,
        law,
        fixed=[("INNER", 1, 2), ("XSYM", 1, 1), ("YSYM", 2, 2)],
        pressure=[("OUTER", p)],
        static=(0.25, 1.0, 1e-4, 0.25),
    )
    return mesh, text


def run_annulus(tmp_path, nr, order, law, p, name="job"):
    mesh, text = annulus_deck(nr, order, law, p)
    run = run_engine(text, tmp_path, name)
    assert run.returncode == 0, run.stderr
    assert run.summary["status"] == "converged"
    return mesh, run


@pytest.mark.parametrize("kv,p,value", ISSUE_VALUES)
def test_reference_reproduces_issue_values(kv, p, value):
    ref = annulus(Law("AVRIL", (1.0, kv)), p=p)
    half_unit = 0.5 * 10.0 ** (np.floor(np.log10(abs(value))) - 6)  # of the 7th significant digit
    assert abs(ref.u_r(2.0) - value) <= half_unit


@pytest.mark.parametrize("kv,p,value", ISSUE_VALUES)
def test_engine_outer_displacement(tmp_path, kv, p, value):
    """T6, 16 x 32 quarter mesh: u_r at every outer node within 1e-5 of |u_r(2)| (discretisation ~1e-6)."""
    law = Law("AVRIL", (1.0, kv))
    ref = annulus(law, p=p)
    mesh, run = run_annulus(tmp_path, 16, 2, law, p)
    u = run.u()
    outer = mesh.nsets["OUTER"]
    X = mesh.nodes[outer]
    ur = np.sum(u[outer] * X, axis=1) / np.hypot(X[:, 0], X[:, 1])
    ut = (u[outer, 1] * X[:, 0] - u[outer, 0] * X[:, 1]) / np.hypot(X[:, 0], X[:, 1])
    assert np.abs(ur - ref.u_r(2.0)).max() < 1e-5 * abs(value)
    assert np.abs(ut).max() < 1e-5 * abs(value)  # axisymmetric: no tangential motion
    assert np.mean(ur) == pytest.approx(value, rel=1e-5)


def _rate(tmp_path, order, levels, kv=10.0, p=0.5):
    law = Law("AVRIL", (1.0, kv))
    ref = annulus(law, p=p)
    h, err = [], []
    for nr in levels:
        mesh, run = run_annulus(tmp_path / f"n{nr}", nr, order, law, p)
        e, nrm = l2_error(mesh, run.u(), ref.u_xy)
        h.append(1.0 / nr)
        err.append(e / nrm)
    rate = np.polyfit(np.log(h), np.log(err), 1)[0]
    return rate, err


@pytest.mark.parametrize(
    "order,levels,min_rate",
    [(1, (4, 8, 16), 1.8), (2, (2, 4, 8), 2.7)],
    ids=["CPE3", "CPE6"],
)
def test_convergence_rate(tmp_path, order, levels, min_rate):
    rate, err = _rate(tmp_path, order, levels)
    assert rate > min_rate, f"observed rate {rate:.3f}, relative L2 errors {err}"
    assert rate < min_rate + 1.7, f"rate {rate:.3f} suspiciously high, errors {err}"
    assert all(a > b for a, b in zip(err, err[1:])), err


@pytest.mark.slow
@pytest.mark.parametrize(
    "order,levels,min_rate",
    [(1, (8, 16, 32, 64), 1.9), (2, (4, 8, 16, 32), 2.8)],
    ids=["CPE3", "CPE6"],
)
def test_convergence_rate_fine(tmp_path, order, levels, min_rate):
    rate, err = _rate(tmp_path, order, levels)
    assert rate > min_rate, f"observed rate {rate:.3f}, relative L2 errors {err}"
    assert all(a > b for a, b in zip(err, err[1:])), err


@pytest.mark.parametrize("integration", ["FULL", "REDUCED"])
def test_t6_integration_rules_agree(tmp_path, integration):
    """Both T6 rules converge to the same solution (within the discretisation error)."""
    law = Law("AVRIL", (1.0, 10.0))
    ref = annulus(law, p=0.5)
    mesh = ring(4, 8, 2, quarter=True)
    text = deck(
        mesh, law, fixed=[("INNER", 1, 2), ("XSYM", 1, 1), ("YSYM", 2, 2)], pressure=[("OUTER", 0.5)],
        integration=integration,
    )
    run = run_engine(text, tmp_path)
    assert run.returncode == 0, run.stderr
    e, nrm = l2_error(mesh, run.u(), ref.u_xy)
    assert e / nrm < 1e-3
