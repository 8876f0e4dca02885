"""Patch tests of calfit-fe: T3 and T6 reproduce a homogeneous state exactly.

The MacNeal-Harder patch (MacNeal & Harder, Finite Elem. Anal. Des. 1 (1985) 3-20):
a 0.24 x 0.12 rectangle with interior nodes (0.04,0.02), (0.18,0.03), (0.16,0.08),
(0.08,0.08), E = 1e6, nu = 0.25, boundary nodes given u = 1e-3 (x + y/2),
v = 1e-3 (y + x/2). In the linear limit the plane-strain stresses are sigma_x = sigma_y
= 1600, sigma_z = 800, tau_xy = 400 (published values of the benchmark). At finite strain
the same boundary data give the homogeneous deformation F = I + 1e-3 [[1, 1/2], [1/2, 1]]
exactly (a constant stress is divergence free), so the interior nodes must sit on the
linear field and every element must carry the Cauchy stress of that F, computed here in
Python for St Venant-Kirchhoff (*ELASTIC) and for NEO HOOKE with C10 = mu/2, D1 = 2/K
(the same linear limit).
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_closed_forms import Law, patch_linear_stress
from engine_run import run_engine
from fe_cases import deck, macneal_harder_patch

E, NU = 1.0e6, 0.25
MU, K = E / (2 * (1 + NU)), E / (3 * (1 - 2 * NU))
GRAD = 1e-3 * np.array([[1.0, 0.5], [0.5, 1.0]])  # du/dX
LAWS = {
    "ELASTIC": Law("ELASTIC", (E, NU)),
    "NEO HOOKE": Law("NEO HOOKE", (MU / 2, 2 / K)),
}
LINEAR_LIMIT = (1600.0, 1600.0, 800.0, 400.0)  # sigma_x, sigma_y, sigma_z, tau_xy


def linear_field(X: np.ndarray) -> np.ndarray:
    return X @ GRAD.T


def test_published_linear_limit_matches_hooke():
    """The quoted benchmark stresses are those of plane-strain Hooke's law for this strain."""
    assert patch_linear_stress(E, NU, GRAD[0, 0], GRAD[1, 1], 2 * GRAD[0, 1]) == pytest.approx(LINEAR_LIMIT, rel=1e-14)


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
@pytest.mark.parametrize("law_name", list(LAWS))
def test_macneal_harder_patch(tmp_path, order, law_name):
    law = LAWS[law_name]
    mesh = macneal_harder_patch(order)
    ub = linear_field(mesh.nodes)
    prescribed = []
    for n in mesh.nsets["BOUNDARY"]:
        prescribed += [(int(n), 1, ub[n, 0]), (int(n), 2, ub[n, 1])]
    text = deck(mesh, law, prescribed=prescribed, static=(1.0, 1.0, 1e-5, 1.0))
    run = run_engine(text, tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.summary["status"] == "converged"

    # Interior nodes on the linear field to 1e-10 of the displacement scale.
    u = run.u()
    assert np.array_equal(run.table[:, 0], np.arange(1, len(mesh.nodes) + 1))
    assert np.allclose(run.table[:, 1:3], mesh.nodes, rtol=0, atol=1e-15)
    scale = np.abs(ub).max()
    inner = mesh.nsets["INTERIOR"]
    err_u = np.abs(u[inner] - ub[inner]).max() / scale
    assert err_u < 1e-10, f"interior displacement error {err_u:.2e} (relative)"
    assert np.abs(u - ub).max() / scale < 1e-10

    # Every element carries the closed-form finite-strain Cauchy stress of F.
    sig = law.cauchy(np.eye(2) + GRAD)
    expected = np.array([sig[0, 0], sig[1, 1], sig[2, 2], sig[0, 1], 0.0, 0.0])
    vtu = run.vtu(1)
    cell = np.concatenate(vtu.cell_data["cauchy_stress"])
    assert cell.shape == (len(mesh.elems), 6)
    err_s = np.abs(cell - expected).max() / np.abs(expected).max()
    assert err_s < 1e-8, f"element stress error {err_s:.2e} (relative)"
    # Nodal averages of a constant field are that constant.
    nodal = vtu.point_data["cauchy_stress"]
    assert np.abs(nodal - expected).max() / np.abs(expected).max() < 1e-8
    J = np.concatenate(vtu.cell_data["J"])
    assert np.allclose(J, np.linalg.det(np.eye(2) + GRAD), rtol=1e-12)
    pressure = np.concatenate(vtu.cell_data["pressure"])
    assert np.allclose(pressure, -np.trace(sig) / 3, rtol=1e-8)

    # And within 0.5 % of the published linear-limit values.
    lin = np.array(LINEAR_LIMIT)
    got = cell[:, [0, 1, 2, 3]]
    assert np.all(np.abs(got - lin) <= 5e-3 * lin)
