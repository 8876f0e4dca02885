"""Homogeneous finite-strain states of every material law of calfit-fe against closed forms.

Two homogeneous problems on the unit square, for NEO HOOKE, MOONEY-RIVLIN, REDUCED
POLYNOMIAL (N = 2, 3), ARRUDA-BOYCE, AVRIL and ELASTIC (St Venant-Kirchhoff):

1. rollers on the bottom and left edges, a follower pressure p on the top face: the
   state is F = diag(l1, l2) with sigma_xx = 0, sigma_yy = -p; (l1, l2) solve those two
   nonlinear equations (scipy, engine_closed_forms). Issue 2 quotes, for CPE6, NEO HOOKE
   C10 = 1, D1 = 0.1, p = 0.5: u_x(1, 1) = 5.7195986e-2, which the closed form reproduces.
2. every boundary node given the displacement of a general F (shear + stretch, not
   symmetric): every element must carry sigma(F) (full Cauchy tensor, closed form).

Energies and the stress formula are those written at the top of engine_closed_forms.py
(CalculiX / Abaqus definitions, plane strain).
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_closed_forms import Law, stretches_for_stress
from engine_run import run_engine
from fe_cases import deck, unit_square

LAWS = {
    "NEO HOOKE": Law("NEO HOOKE", (1.0, 0.1)),
    "MOONEY-RIVLIN": Law("MOONEY-RIVLIN", (0.8, 0.3, 0.1)),
    "REDUCED POLYNOMIAL N=2": Law("REDUCED POLYNOMIAL", (1.0, 0.4, 0.1, 0.5), n=2),
    "REDUCED POLYNOMIAL N=3": Law("REDUCED POLYNOMIAL", (1.0, 0.4, 0.2, 0.1, 0.5, 1.0), n=3),
    "ARRUDA-BOYCE": Law("ARRUDA-BOYCE", (2.0, 1.5, 0.1)),
    "AVRIL": Law("AVRIL", (1.0, 10.0)),
    "ELASTIC": Law("ELASTIC", (10.0, 0.3)),
}
P_TOP = 0.5
F_GENERAL = np.array([[1.25, 0.2], [-0.1, 0.85]])


def test_issue_value_reproduced_by_closed_form():
    """Issue 2: CPE6, NEO HOOKE C10=1, D1=0.1, p=0.5 gives u_x(1,1) = 5.7195986e-2."""
    l1, _ = stretches_for_stress(LAWS["NEO HOOKE"], 0.0, -P_TOP, (1.05, 0.9))
    assert l1 - 1.0 == pytest.approx(5.7195986e-2, abs=5e-10)


@pytest.mark.parametrize("law_name", list(LAWS))
def test_principal_and_tensor_stress_agree(law_name):
    """Self-check of the Python closed forms: principal formula == tensor formula."""
    law = LAWS[law_name]
    s = law.cauchy(np.diag([1.2, 0.85]))
    c1, c2 = law.principal_cauchy(1.2, 0.85)
    assert s[0, 0] == pytest.approx(c1, rel=1e-12, abs=1e-13)
    assert s[1, 1] == pytest.approx(c2, rel=1e-12, abs=1e-13)
    # Stress-free reference state.
    assert np.abs(law.cauchy(np.eye(2))).max() < 1e-13


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
@pytest.mark.parametrize("law_name", list(LAWS))
def test_pressure_on_top_with_rollers(tmp_path, law_name, order):
    law = LAWS[law_name]
    l1, l2 = stretches_for_stress(law, 0.0, -P_TOP, (1.05, 0.9))
    mesh = unit_square(2, order)
    text = deck(mesh, law, fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)], pressure=[("TOP", P_TOP)])
    run = run_engine(text, tmp_path)
    assert run.returncode == 0, run.stderr
    u = run.u()
    X = mesh.nodes
    exact = np.column_stack([(l1 - 1) * X[:, 0], (l2 - 1) * X[:, 1]])
    corner = mesh.nsets["CORNER"][0]
    assert u[corner, 0] == pytest.approx(l1 - 1, rel=1e-9)
    assert u[corner, 1] == pytest.approx(l2 - 1, rel=1e-9)
    assert np.abs(u - exact).max() < 1e-9 * np.abs(exact).max()
    if law_name == "NEO HOOKE" and order == 2:
        assert u[corner, 0] == pytest.approx(5.7195986e-2, abs=5e-10)  # issue 2's quoted value
    cell = np.concatenate(run.vtu(1).cell_data["cauchy_stress"])
    sig = law.cauchy(np.diag([l1, l2]))
    expected = np.array([0.0, -P_TOP, sig[2, 2], 0.0, 0.0, 0.0])
    assert np.abs(cell - expected).max() < 1e-8 * P_TOP
    J = np.concatenate(run.vtu(1).cell_data["J"])
    assert np.allclose(J, l1 * l2, rtol=1e-9)


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
@pytest.mark.parametrize("law_name", list(LAWS))
def test_prescribed_general_deformation(tmp_path, law_name, order):
    law = LAWS[law_name]
    mesh = unit_square(3, order)
    G = F_GENERAL - np.eye(2)
    ub = mesh.nodes @ G.T
    prescribed = []
    for n in mesh.nsets["ALLB"]:
        prescribed += [(int(n), 1, ub[n, 0]), (int(n), 2, ub[n, 1])]
    run = run_engine(deck(mesh, law, prescribed=prescribed), tmp_path)
    assert run.returncode == 0, run.stderr
    u = run.u()
    assert np.abs(u - ub).max() < 1e-10 * np.abs(ub).max()
    sig = law.cauchy(F_GENERAL)
    expected = np.array([sig[0, 0], sig[1, 1], sig[2, 2], sig[0, 1], 0.0, 0.0])
    cell = np.concatenate(run.vtu(1).cell_data["cauchy_stress"])
    assert np.abs(cell - expected).max() < 1e-8 * np.abs(expected).max()
