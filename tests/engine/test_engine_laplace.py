"""Laplace-law garment pressure (*LAPLACE PRESSURE) in calfit-fe.

Avril et al. (first paper, eq. (1)): a garment of tension T (force per unit length)
presses on the skin with p = T / r, r the radius of curvature of the DEFORMED contour.
1. Circle: a full ring (inner radius 1 clamped, outer radius 2, Avril law C10 = 1,
   Kv = 10) with the tension on its outer circle. The applied nodal pressure written to
   the VTU (point data laplace_pressure) must be T / r with r = |X + u| of that node, and
   the displacement must be the axisymmetric solution with the boundary condition
   P_R(2) = -(T / r(2)) lambda_theta (engine_closed_forms.annulus with tension=T).
2. Ellipse: a ring whose outer boundary is the ellipse of semi-axes 2.4 x 1.6. The
   applied pressure must follow the curvature of the deformed boundary, computed here
   from the engine's output positions with a periodic cubic spline through the deformed
   outer nodes (kappa = (x'y'' - y'x'') / |x'|^3).
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_closed_forms import Law, annulus
from engine_run import run_engine
from fe_cases import deck, l2_error, ring
from scipy.interpolate import CubicSpline

LAW = Law("AVRIL", (1.0, 10.0))
T = 1.0


def _run_ring(tmp_path, order, outer, nr=4, nt=48, tension=T):
    mesh = ring(nr, nt, order, outer=outer)
    text = deck(mesh, LAW, fixed=[("INNER", 1, 2)], laplace=[("OUTER", tension)], static=(0.25, 1.0, 1e-4, 0.25))
    run = run_engine(text, tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.summary["status"] == "converged"
    return mesh, run


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
def test_circle_pressure_is_tension_over_deformed_radius(tmp_path, order):
    mesh, run = _run_ring(tmp_path, order, (2.0, 2.0), nr=6 if order == 2 else 12, nt=48 if order == 2 else 128)
    ref = annulus(LAW, p=0.0, tension=T)
    u = run.u()
    vtu = run.vtu(1)
    lp = np.asarray(vtu.point_data["laplace_pressure"]).ravel()
    outer = mesh.nsets["OUTER"]
    others = np.setdiff1d(np.arange(len(mesh.nodes)), outer)
    assert np.all(lp[others] == 0.0)
    r_def = np.hypot(*(mesh.nodes[outer] + u[outer]).T)
    assert np.abs(lp[outer] - T / r_def).max() < 2e-3 * T / 2.0
    assert np.abs(lp[outer] - T / ref.r(2.0)).max() < 2e-3 * T / 2.0
    # The displacement is the closed-form one with p = T / r(2).
    e, nrm = l2_error(mesh, u, ref.u_xy)
    tol = 5e-3 if order == 1 else 5e-4  # a few times the discretisation error
    assert e / nrm < tol
    ur = np.sum(u[outer] * mesh.nodes[outer], axis=1) / 2.0
    assert np.mean(ur) == pytest.approx(float(ref.u_r(2.0)), rel=tol)


def deformed_curvature(points: np.ndarray) -> np.ndarray:
    """Signed curvature at each of the closed, counter-clockwise ordered points (periodic spline)."""
    closed = np.vstack([points, points[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))])
    spl = CubicSpline(s, closed, bc_type="periodic")
    d1, d2 = spl(s[:-1], 1), spl(s[:-1], 2)
    return (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.hypot(d1[:, 0], d1[:, 1]) ** 3


def circle_curvature(points: np.ndarray) -> np.ndarray:
    """Signed curvature of the circle through each point and its two neighbours (closed, ccw)."""
    prev, nxt = np.roll(points, 1, axis=0), np.roll(points, -1, axis=0)
    a, b = points - prev, nxt - points
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return 2.0 * cross / (np.hypot(*a.T) * np.hypot(*b.T) * np.hypot(*(nxt - prev).T))


def test_curvature_helper_on_exact_ellipse():
    th = np.linspace(0, 2 * np.pi, 129)[:-1]  # as many points as the CPE6 ellipse's outer nodes
    a, b = 2.4, 1.6
    pts = np.column_stack([a * np.cos(th), b * np.sin(th)])
    exact = a * b / (a**2 * np.sin(th) ** 2 + b**2 * np.cos(th) ** 2) ** 1.5
    assert np.abs(deformed_curvature(pts) - exact).max() < 2e-3 * exact.max()
    circle = np.column_stack([2.0 * np.cos(th), 2.0 * np.sin(th)])
    assert np.allclose(circle_curvature(circle), 0.5, rtol=1e-12)
    assert np.abs(circle_curvature(pts) - exact).max() < 2e-3 * exact.max()


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
def test_ellipse_pressure_follows_deformed_curvature(tmp_path, order):
    a, b = 2.4, 1.6
    tension = 3.0  # large enough that the deformed and reference curvatures differ clearly
    mesh, run = _run_ring(
        tmp_path, order, (a, b), nr=4 if order == 2 else 6, nt=64 if order == 2 else 128, tension=tension
    )
    u = run.u()
    lp = np.asarray(run.vtu(1).point_data["laplace_pressure"]).ravel()
    outer = mesh.nsets["OUTER"]
    X = mesh.nodes[outer]
    order_ccw = np.argsort(np.mod(np.arctan2(X[:, 1] / b, X[:, 0] / a), 2 * np.pi))
    nodes = outer[order_ccw]
    x = mesh.nodes[nodes] + u[nodes]
    if order == 1:
        # Straight faces: the curvature at a node is that of the circle through it and its
        # two deformed neighbours (the discrete curvature; a smooth spline is not the
        # reference here, the T3 boundary carries an O(h_r^2 / h_t^2) odd-even ripple).
        kappa = circle_curvature(x)
        tol_max, tol_median = 1e-8, 1e-8
    else:
        kappa = deformed_curvature(x)
        tol_max, tol_median = 2e-2, 5e-3
    assert np.all(kappa > 0)
    expected = tension * kappa
    err = np.abs(lp[nodes] - expected) / expected
    assert err.max() < tol_max, f"max relative deviation {err.max():.3e}"
    assert np.median(err) < tol_median
    # It is the DEFORMED curvature: the reference ellipse's curvature differs measurably.
    kappa_ref = deformed_curvature(mesh.nodes[nodes])
    assert np.abs(lp[nodes] - tension * kappa_ref).max() > 3 * np.abs(lp[nodes] - expected).max()
    # Pressure at the ends of the major axis (sharp) well above the minor-axis ends (flat).
    i_major = np.argmin(np.abs(mesh.nodes[nodes, 1]))
    i_minor = np.argmin(np.abs(mesh.nodes[nodes, 0]))
    assert lp[nodes][i_major] / lp[nodes][i_minor] == pytest.approx(kappa[i_major] / kappa[i_minor], rel=2e-2)
    assert lp[nodes][i_major] / lp[nodes][i_minor] > 2.0
