"""Engine parameter sensitivities (*SENSITIVITY) against finite differences of the engine.

calfit-fe differentiates its converged solution directly (solver_cpp/src/solver/
sensitivity.hpp: K du/dtheta = -dR/dtheta on the converged tangent). The reference here
is the engine itself: two runs with theta (1 - h) and theta (1 + h) (absolute steps +-h
for a parameter at 0), du_FD = (u+ - u-) / (theta+ - theta-), the thetas as written in
the decks. On the leg slice (orchestrator.meshing.leg_slice_deck, a few hundred T6
elements, clamped bones, Laplace-law garment with a TYPE=FOURIER tension profile) with
CPE6 and with CPE6H elements, for every parameter kind: each constant of AVRIL,
MOONEY-RIVLIN (C10, C01, D1) and NEO HOOKE (C10, D1), the garment TENSION and the
profile coefficients A1 (listed in the profile, or at 0 under a uniform garment) and B2
(not listed: at 0), the relative
error max|du - du_FD| / max|du_FD| must stay below 1e-4.

The same for the effect parameters, once where their keywords are absent (dv = 0,
lambda_z = 1, BONE2 clamped with BONES, AVRIL's C20 = 0 from a two-value data line) and
once where they are given (*VOLUME CHANGE on MUSCLE, *AXIAL STRETCH, *RIGID MOTION of
BONE2, C20 > 0): VOLUME CHANGE:MUSCLE, AXIAL STRETCH, RIGID MOTION:BONE2:UX|UY|ANGLE,
MATERIAL:FAT:C20. C20 cannot go below 0 in a deck, so at 0 its reference is the
one-sided difference of second order, (-3 u(0) + 4 u(h) - u(2h)) / 2h.

Accuracy of the reference: the central difference with h = 1e-3 has a truncation error
of order h^2 = 1e-6 (relative); the runs' own error is their Newton residual over h.
The engine has no deck keyword for its Newton tolerance (relative residual 1e-9,
SolverSettings); quadratic convergence puts the last residual far lower, and the test
checks that every reference run ended below 1e-10, so that this part stays below
about 1e-6 too.

The same through frictionless penalty contact: the leg under the explicit garment band, the
tissues' constants and the band's C10; and through Coulomb friction, carried along the loading
path, with the last step's volume change and axial stretch. With *FRICTION, *SENSITIVITY of a
load on faces or of a prescribed motion exits 2.

A `*SENSITIVITY, NAME=` block (weighted lines as one parameter) against the weighted sum of
its members' own columns of the same run, through frictionless contact and along a frictional
put-on.

Also: the pressure sensitivities (PRESSURE=YES) against the same differences of the
element pressures; the reader EngineResults.sensitivities on a synthetic output folder;
malformed *SENSITIVITY lines and FOURIER profiles exit 2 with FILE:LINE.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from engine_run import run_engine

from orchestrator.core.errors import ResultsError
from orchestrator.engine.locate import find_engine
from orchestrator.engine.results import EngineResults
from orchestrator.meshing import leg_slice_deck, leg_slice_mesh

TENSION = 0.16  # N/mm
PROFILE = {1: (0.1, 0.05)}  # k -> (a_k, b_k): B2 is not listed
RELATIVE_STEP = 1e-3
TOLERANCE = 1e-4
REFERENCE_RESIDUAL = 1e-10

# elset -> (law, constants by name, in data-line order); MPa and 1/MPa
LAWS = {
    "avril-mooney": {
        "FAT": ("AVRIL", {"C10": 0.0045, "KV": 0.106}),
        "MUSCLE": ("MOONEY-RIVLIN", {"C10": 0.009, "C01": 0.0022, "D1": 1.0 / 0.0695}),
    },
    "neo-hooke": {
        "FAT": ("NEO HOOKE", {"C10": 0.0045, "D1": 1.0 / 0.106}),
        "MUSCLE": ("NEO HOOKE", {"C10": 0.0112, "D1": 1.0 / 0.0695}),
    },
}


def _written(value: float) -> float:
    """The value as leg_slice_deck writes it (10 significant digits)."""
    return float(f"{value:.10g}")


def parameters(laws) -> list[str]:
    names = [f"MATERIAL:{elset}:{c}" for elset, (_, constants) in laws.items() for c in constants]
    return names + ["TENSION:SKIN", "PROFILE:GARMENT:A1", "PROFILE:GARMENT:B2"]


# The effect keywords of a deck: dv of MUSCLE, lambda_z, BONE2's motion (ux mm, uy mm, angle
# degrees); None leaves the keyword out (BONE2 then stays clamped with BONES).
NO_EFFECTS = {"dv": None, "lambda_z": None, "motion": None}


def effect_keywords(effects: dict) -> str:
    text = ""
    if effects["dv"] is not None:
        text += f"*VOLUME CHANGE, ELSET=MUSCLE\n{effects['dv']!r}\n"
    if effects["lambda_z"] is not None:
        text += f"*AXIAL STRETCH\n{effects['lambda_z']!r}\n"
    if effects["motion"] is not None:
        text += "*RIGID MOTION, NSET=BONE2\n" + ", ".join(repr(v) for v in effects["motion"]) + "\n"
    return text


def write_deck(folder: Path, mesh, laws, element_type: str, tension: float, profile: dict, sensitivity: list[str],
               effects: dict = NO_EFFECTS) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    deck = folder / "leg.inp"
    materials = {elset: (law, tuple(constants.values())) for elset, (law, constants) in laws.items()}
    leg_slice_deck(deck, mesh=mesh, materials=materials, laplace_tension=tension, include_mesh=False)
    text = deck.read_text()
    if element_type == "CPE6H":
        text = text.replace("TYPE=CPE6,", "TYPE=CPE6H,")
    harmonics = "".join(f"{k}, {a!r}, {b!r}\n" for k, (a, b) in sorted(profile.items()))
    text = text.replace("*STEP,", f"*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n{harmonics}*STEP,", 1)
    text = re.sub(r"(\*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=[^\n]*)", r"\1, PROFILE=GARMENT", text)
    text = text.replace(", PROFILE=GARMENT\n", ", PROFILE=GARMENT\n" + effect_keywords(effects), 1)
    if sensitivity:
        lines = [", ".join(name.split(":")) for name in sensitivity]
        text += "*SENSITIVITY, PRESSURE=YES\n" + "\n".join(lines) + "\n"
    deck.write_text(text)
    return deck


def with_value(laws, tension, profile, name: str, value: float, effects: dict = NO_EFFECTS):
    """(laws, tension, profile, effects) with parameter `name` set to value."""
    laws = {elset: (law, dict(constants)) for elset, (law, constants) in laws.items()}
    profile = dict(profile)
    effects = dict(effects)
    kind, *rest = name.split(":")
    if kind == "MATERIAL":
        laws[rest[0]][1][rest[1]] = value  # a C20 the line did not give is appended: AVRIL's third value
    elif kind == "TENSION":
        tension = value
    elif kind == "VOLUME CHANGE":
        effects["dv"] = value
    elif kind == "AXIAL STRETCH":
        effects["lambda_z"] = value
    elif kind == "RIGID MOTION":
        motion = list(effects["motion"] or (0.0, 0.0, 0.0))
        motion[("UX", "UY", "ANGLE").index(rest[1])] = value
        effects["motion"] = tuple(motion)
    else:
        k = int(rest[1][1:])
        a, b = profile.get(k, (0.0, 0.0))
        profile[k] = (value, b) if rest[1][0] == "A" else (a, value)
    return laws, tension, profile, effects


def _check_report(title: str, report: list[tuple[str, float, float, float]]) -> None:
    """Print (parameter, max|du/dtheta|, relative error of du, of dp) rows; the worst errors must be below
    TOLERANCE."""
    print(f"\n{title}: parameter, max|du/dtheta|, relative error of du, of dp")
    for row in report:
        print("  %-26s %.4e  %.2e  %.2e" % row)
    worst = max(report, key=lambda row: row[2])
    assert worst[2] < TOLERANCE, f"du/d{worst[0]} differs from the finite difference by {worst[2]:.2e}: {report}"
    worst_dp = max(report, key=lambda row: row[3])
    assert worst_dp[3] < TOLERANCE, f"dp/d{worst_dp[0]} differs from the finite difference by {worst_dp[3]:.2e}: {report}"


@pytest.fixture(scope="module")
def mesh():
    return leg_slice_mesh(300, order=2)


# (law set, element type, garment profile): the profiled garment has an unsymmetric
# tangent (UMFPACK); the uniform one (a FOURIER profile with no terms, A1 and B2 at 0) a
# symmetric one (CHOLMOD, or for CPE6H the saddle-point LDL^T when it is the faster).
CASES = [
    ("avril-mooney", "CPE6", PROFILE),
    ("avril-mooney", "CPE6H", PROFILE),
    ("neo-hooke", "CPE6", {}),
    ("neo-hooke", "CPE6H", {}),
]


@pytest.mark.parametrize("law_set, element_type, profile", CASES,
                         ids=[f"{c[0]}-{c[1]}-{'profiled' if c[2] else 'uniform'}" for c in CASES])
def test_sensitivities_match_finite_differences(tmp_path, mesh, law_set, element_type, profile):
    laws = LAWS[law_set]
    names = parameters(laws)
    deck = write_deck(tmp_path / "sensitivity", mesh, laws, element_type, TENSION, profile, names)
    run = run_engine(None, tmp_path, "sensitivity", deck_path=deck)
    assert run.returncode == 0, run.stderr
    results = EngineResults(run.outdir)
    du = results.sensitivities()
    dp = results.pressure_sensitivities()
    entries = results.sensitivity_parameters
    assert [e["name"] for e in entries] == names
    assert [e["index"] for e in entries] == list(range(1, len(names) + 1))
    assert results.summary["time_s"]["sensitivity"] > 0.0

    report = []
    for entry in entries:
        name, theta = entry["name"], entry["value"]
        step = RELATIVE_STEP * abs(theta) if theta else RELATIVE_STEP
        sides = {}
        for label, value in (("minus", theta - step), ("plus", theta + step)):
            value = _written(value) if name.startswith(("MATERIAL", "TENSION")) else value
            folder = tmp_path / f"{name.replace(':', '_')}-{label}"
            fd_laws, fd_tension, fd_profile, _ = with_value(laws, TENSION, profile, name, value)
            fd_deck = write_deck(folder, mesh, fd_laws, element_type, fd_tension, fd_profile, [])
            fd_run = run_engine(None, folder, "run", deck_path=fd_deck)
            assert fd_run.returncode == 0, fd_run.stderr
            last_residual = fd_run.residual_histories()[-1][-1]
            assert last_residual <= REFERENCE_RESIDUAL, f"{name} {label}: reference run stopped at {last_residual:.1e}"
            sides[label] = (value, fd_run.u(), EngineResults(fd_run.outdir).cell_field("pressure"))
        (v_minus, u_minus, p_minus), (v_plus, u_plus, p_plus) = sides["minus"], sides["plus"]
        du_fd = (u_plus - u_minus) / (v_plus - v_minus)
        dp_fd = (p_plus - p_minus) / (v_plus - v_minus)
        error = np.abs(du[name] - du_fd).max() / np.abs(du_fd).max()
        dp_error = np.abs(dp[name] - dp_fd).max() / np.abs(dp_fd).max()
        assert entry["max_abs_du"] == pytest.approx(np.abs(du[name]).max(), rel=1e-12)
        report.append((name, float(np.abs(du_fd).max()), float(error), float(dp_error)))
    _check_report(f"{law_set} {element_type} {'profiled' if profile else 'uniform'} garment, "
                  f"{run.summary['linear_solver']}", report)


# ----------------------------------------------------------------------------------------
# Effect parameters: VOLUME CHANGE, AXIAL STRETCH, RIGID MOTION, AVRIL's C20
# ----------------------------------------------------------------------------------------

EFFECT_PARAMETERS = ["VOLUME CHANGE:MUSCLE", "AXIAL STRETCH", "RIGID MOTION:BONE2:UX", "RIGID MOTION:BONE2:UY",
                     "RIGID MOTION:BONE2:ANGLE", "MATERIAL:FAT:C20"]
# absent: the neutral values (the deck has none of the keywords, AVRIL's line two values);
# given: a drained muscle, an axially shortened slice, a moved second bone, C20 > 0.
EFFECT_CASES = {
    "absent": (NO_EFFECTS, None),
    "given": ({"dv": -0.04, "lambda_z": 0.98, "motion": (0.3, -0.2, 2.0)}, 0.002),
}


def _zero_step(name: str, laws) -> float:
    """The difference step of a parameter at 0: for a law constant RELATIVE_STEP times the largest
    constant of the same kind (C20 beside C10), otherwise RELATIVE_STEP (dv, mm, degrees)."""
    kind, *rest = name.split(":")
    if kind == "MATERIAL":
        constants = laws[rest[0]][1]
        return RELATIVE_STEP * max(abs(v) for c, v in constants.items() if c[0] == rest[1][0])
    return RELATIVE_STEP


@pytest.mark.parametrize("element_type", ["CPE6", "CPE6H"])
@pytest.mark.parametrize("case", sorted(EFFECT_CASES))
def test_effect_sensitivities_match_finite_differences(tmp_path, mesh, case, element_type):
    effects, c20 = EFFECT_CASES[case]
    laws = {elset: (law, dict(constants)) for elset, (law, constants) in LAWS["avril-mooney"].items()}
    if c20 is not None:
        laws["FAT"][1]["C20"] = c20
    deck = write_deck(tmp_path / "sensitivity", mesh, laws, element_type, TENSION, PROFILE, EFFECT_PARAMETERS, effects)
    run = run_engine(None, tmp_path, "sensitivity", deck_path=deck)
    assert run.returncode == 0, run.stderr
    results = EngineResults(run.outdir)
    du, dp = results.sensitivities(), results.pressure_sensitivities()
    entries = results.sensitivity_parameters
    assert [e["name"] for e in entries] == EFFECT_PARAMETERS
    expected = {"VOLUME CHANGE:MUSCLE": effects["dv"] or 0.0, "AXIAL STRETCH": effects["lambda_z"] or 1.0,
                "MATERIAL:FAT:C20": c20 or 0.0}
    for k, component in enumerate(("UX", "UY", "ANGLE")):
        expected[f"RIGID MOTION:BONE2:{component}"] = effects["motion"][k] if effects["motion"] else 0.0
    assert {e["name"]: e["value"] for e in entries} == pytest.approx(expected, rel=1e-12, abs=0.0)

    def reference(name: str, value: float):
        folder = tmp_path / f"{name.replace(':', '_').replace(' ', '_')}-{value!r}"
        value = _written(value) if name.startswith("MATERIAL") else value
        fd_laws, fd_tension, fd_profile, fd_effects = with_value(laws, TENSION, PROFILE, name, value, effects)
        fd_run = run_engine(None, folder, "run", deck_path=write_deck(folder, mesh, fd_laws, element_type, fd_tension,
                                                                      fd_profile, [], fd_effects))
        assert fd_run.returncode == 0, fd_run.stderr
        last_residual = fd_run.residual_histories()[-1][-1]
        assert last_residual <= REFERENCE_RESIDUAL, f"{name} = {value}: reference run stopped at {last_residual:.1e}"
        return value, fd_run.u(), EngineResults(fd_run.outdir).cell_field("pressure")

    report = []
    for entry in entries:
        name, theta = entry["name"], entry["value"]
        if name == "MATERIAL:FAT:C20" and theta == 0.0:  # C20 < 0 is no deck: one-sided, second order
            h = _zero_step(name, laws)
            (v0, u0, p0), (v1, u1, p1), (v2, u2, p2) = (reference(name, v) for v in (0.0, h, 2.0 * h))
            h = (v2 - v0) / 2.0  # as written
            du_fd, dp_fd = (-3.0 * u0 + 4.0 * u1 - u2) / (2.0 * h), (-3.0 * p0 + 4.0 * p1 - p2) / (2.0 * h)
        else:
            h = RELATIVE_STEP * abs(theta) if theta else _zero_step(name, laws)
            (v_minus, u_minus, p_minus), (v_plus, u_plus, p_plus) = reference(name, theta - h), reference(name, theta + h)
            du_fd, dp_fd = (u_plus - u_minus) / (v_plus - v_minus), (p_plus - p_minus) / (v_plus - v_minus)
        error = np.abs(du[name] - du_fd).max() / np.abs(du_fd).max()
        dp_error = np.abs(dp[name] - dp_fd).max() / np.abs(dp_fd).max()
        report.append((name, float(np.abs(du_fd).max()), float(error), float(dp_error)))
    _check_report(f"effects {case}, {element_type}, {run.summary['linear_solver']}", report)
    # The bone's own nodes follow the motion: du/dux = (1, 0) there, exactly.
    bone2 = np.asarray(mesh.node_sets["BONE2"])
    np.testing.assert_allclose(du["RIGID MOTION:BONE2:UX"][bone2], np.tile([1.0, 0.0], (len(bone2), 1)), atol=1e-9)


def test_sensitivity_reader(tmp_path):
    """EngineResults.sensitivities on a hand-written output folder (the engine's formats)."""
    table = np.column_stack([[1, 2, 3], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.1, 0.2, 0.3], [-0.1, -0.2, -0.3]])
    np.save(tmp_path / "step-1.du-1.npy", table)
    np.save(tmp_path / "step-1.du-2.npy", 2 * table)
    entries = [
        {"index": 1, "name": "MATERIAL:FAT:C10", "value": 0.0045, "file": "step-1.du-1.npy", "max_abs_du": 0.3},
        {"index": 2, "name": "TENSION:SKIN", "value": 0.16, "file": "step-1.du-2.npy", "max_abs_du": 0.6},
    ]
    (tmp_path / "summary.json").write_text(json.dumps({"steps": [{}], "sensitivities": entries}))
    results = EngineResults(tmp_path)
    du = results.sensitivities()
    assert list(du) == ["MATERIAL:FAT:C10", "TENSION:SKIN"]
    np.testing.assert_array_equal(du["TENSION:SKIN"], 2 * table[:, 3:5])
    assert results.sensitivity_parameters[1]["value"] == 0.16
    (tmp_path / "step-1.du-2.npy").unlink()
    with pytest.raises(ResultsError, match="TENSION:SKIN"):
        results.sensitivities()
    (tmp_path / "summary.json").write_text(json.dumps({"steps": [{}]}))
    assert EngineResults(tmp_path).sensitivities() == {}


def test_no_sensitivity_request_lists_none(tmp_path, mesh):
    deck = write_deck(tmp_path / "plain", mesh, LAWS["neo-hooke"], "CPE6", TENSION, PROFILE, [])
    run = run_engine(None, tmp_path, "plain", deck_path=deck)
    assert run.returncode == 0, run.stderr
    assert run.summary["sensitivities"] == []
    assert not list(run.outdir.glob("*.du-*.npy"))


# ----------------------------------------------------------------------------------------
# Malformed *SENSITIVITY and *TENSION PROFILE, TYPE=FOURIER: exit 2, FILE:LINE
# ----------------------------------------------------------------------------------------

BASE = """\
*NODE
1, 0.0, 0.0
2, 1.0, 0.0
3, 1.0, 1.0
4, 0.0, 1.0
*ELEMENT, TYPE=CPE3, ELSET=EALL
1, 1, 2, 3
2, 1, 3, 4
*NSET, NSET=BOTTOM
1, 2
*SURFACE, NAME=SKIN, TYPE=ELEMENT
1, S2
2, S2
*MATERIAL, NAME=RUBBER
*HYPERELASTIC, NEO HOOKE
1.0, 0.1
*SOLID SECTION, ELSET=EALL, MATERIAL=RUBBER
*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER
1, 0.1, 0.0
*TENSION PROFILE, NAME=TABLE
0, 1.0
*BOUNDARY
BOTTOM, 1, 2
*STEP, NLGEOM
*STATIC
0.5, 1.0, 1e-5, 1.0
*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=0.01, PROFILE=GARMENT
*END STEP
"""

MALFORMED = {
    # name: (text appended or substituted, substring expected in the message)
    "unknown kind": ("*SENSITIVITY\nSTIFFNESS, RUBBER\n", "unknown sensitivity parameter kind"),
    "unknown material": ("*SENSITIVITY\nMATERIAL, STEEL, C10\n", "material STEEL is not defined"),
    "constant the law lacks": ("*SENSITIVITY\nMATERIAL, RUBBER, C01\n", "has no constant C01"),
    "material line too short": ("*SENSITIVITY\nMATERIAL, RUBBER\n", "expected MATERIAL"),
    "unknown surface": ("*SENSITIVITY\nTENSION, BACK\n", "surface BACK is not defined"),
    "no Laplace load there": ("*SENSITIVITY\nTENSION, ALSO\n", "no *LAPLACE PRESSURE on surface ALSO"),
    "unknown profile": ("*SENSITIVITY\nPROFILE, SOCK, A1\n", "tension profile SOCK is not defined"),
    "table profile": ("*SENSITIVITY\nPROFILE, TABLE, A1\n", "TYPE=TABLE"),
    "bad coefficient": ("*SENSITIVITY\nPROFILE, GARMENT, C2\n", "use A<k> or B<k>"),
    "coefficient zero": ("*SENSITIVITY\nPROFILE, GARMENT, A0\n", "use A<k> or B<k>"),
    "listed twice": ("*SENSITIVITY\nTENSION, SKIN\nTENSION, SKIN\n", "listed twice"),
    "no data line": ("*SENSITIVITY\n", "needs at least one data line"),
    "bad PRESSURE": ("*SENSITIVITY, PRESSURE=MAYBE\nTENSION, SKIN\n", "PRESSURE must be YES or NO"),
    "unknown parameter": ("*SENSITIVITY, ORDER=2\nTENSION, SKIN\n", "ORDER"),
    "unknown element set": ("*SENSITIVITY\nVOLUME CHANGE, LEGS\n", "element set LEGS is not defined"),
    "volume change without set": ("*SENSITIVITY\nVOLUME CHANGE\n", "expected VOLUME CHANGE"),
    "axial stretch with a set": ("*SENSITIVITY\nAXIAL STRETCH, EALL\n", "expected AXIAL STRETCH"),
    "unknown node set": ("*SENSITIVITY\nRIGID MOTION, BONE, UX\n", "node set BONE is not defined"),
    "rigid motion UZ": ("*SENSITIVITY\nRIGID MOTION, BOTTOM, UZ\n", "use UX, UY"),
    "rigid motion without component": ("*SENSITIVITY\nRIGID MOTION, BOTTOM\n", "expected RIGID MOTION"),
    "rigid motion of a free set": ("*SENSITIVITY\nRIGID MOTION, TOP, ANGLE\n", "is not clamped"),
    "C20 of a law without it": ("*SENSITIVITY\nMATERIAL, RUBBER, C20\n", "has no constant C20"),
    "gap profile without *GAP PROFILE": ("*SENSITIVITY\nGAP PROFILE, SKIN, A2\n", "add *GAP PROFILE, SLAVE=SKIN"),
    "shape of a loaded surface": ("*SENSITIVITY\nSHAPE, SKIN, A2\n", "carry face loads"),
    "shape B0": ("*SENSITIVITY\nSHAPE, ALSO, B0\n", "shape coefficient B0 is not valid"),
    "named block without weights": ("*SENSITIVITY, NAME=BOTH\nTENSION\n", "followed by its weight"),
    "named block, bad weight": ("*SENSITIVITY, NAME=BOTH\nTENSION, SKIN, heavy\n", "the parameter's weight"),
    "named block, zero weight": ("*SENSITIVITY, NAME=BOTH\nTENSION, SKIN, 0\n", "must be a nonzero number"),
    "named block, bad name": ("*SENSITIVITY, NAME=A/B\nTENSION, SKIN, 1\n", "a name of letters"),
    "named block, a name twice": ("*SENSITIVITY, NAME=TENSION:SKIN\nMATERIAL, RUBBER, C10, 1\n*SENSITIVITY\n"
                                  "TENSION, SKIN\n", "listed twice"),
}


def _run(deck: Path, tmp: Path):
    return subprocess.run([str(find_engine()), str(deck), "-o", str(tmp / "out"), "--quiet"],
                          capture_output=True, text=True, timeout=30, cwd=tmp)


def _expect_error(tmp_path: Path, text: str, line: int, fragment: str) -> None:
    deck = tmp_path / "main.inp"
    deck.write_text(text)
    proc = _run(deck, tmp_path)
    assert proc.returncode == 2, proc.stderr
    found = re.findall(r"([^\s:]+\.inp):(\d+):", proc.stderr)
    assert found and (Path(found[0][0]).name, int(found[0][1])) == ("main.inp", line), proc.stderr
    assert fragment in proc.stderr, proc.stderr


def test_base_deck_with_sensitivities_runs(tmp_path):
    deck = tmp_path / "main.inp"
    deck.write_text(BASE + "*SENSITIVITY\nMATERIAL, RUBBER, C10\nTENSION, SKIN\nPROFILE, GARMENT, B3\n")
    proc = _run(deck, tmp_path)
    assert proc.returncode == 0, proc.stderr
    names = [e["name"] for e in EngineResults(tmp_path / "out").sensitivity_parameters]
    assert names == ["MATERIAL:RUBBER:C10", "TENSION:SKIN", "PROFILE:GARMENT:B3"]


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_sensitivity(tmp_path, case):
    addition, fragment = MALFORMED[case]
    base = BASE.replace("*TENSION PROFILE, NAME=GARMENT",
                        "*SURFACE, NAME=ALSO, TYPE=ELEMENT\n1, S1\n*NSET, NSET=TOP\n3, 4\n*TENSION PROFILE, NAME=GARMENT")
    text = base + addition
    # the error names the offending data line (the last), or the keyword line for keyword-level faults
    keyword_level = case in ("no data line", "bad PRESSURE", "unknown parameter", "named block, bad name")
    line = len(base.splitlines()) + 1 if keyword_level else len(text.splitlines())
    _expect_error(tmp_path, text, line, fragment)


def _with_contact(friction: str = "", after: str = "") -> str:
    """BASE with a penalty contact pair (OTHER, element 2's third face, against SKIN), `friction` lines and
    `after` keywords before *BOUNDARY."""
    return BASE.replace("*BOUNDARY", "*SURFACE INTERACTION, NAME=TOUCH\n*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR\n"
                        f"1000.0\n{friction}*SURFACE, NAME=OTHER, TYPE=ELEMENT\n2, S3\n"
                        f"*CONTACT PAIR, INTERACTION=TOUCH\nOTHER, SKIN\n{after}*BOUNDARY")


def test_sensitivity_of_a_load_refused_with_friction(tmp_path):
    text = _with_contact(friction="*FRICTION\n0.3, 100.0\n") + "*SENSITIVITY\nTENSION, SKIN\n"
    _expect_error(tmp_path, text, len(text.splitlines()), "not TENSION:SKIN: difference runs of the deck for it")


def test_a_contact_parameter_is_refused_in_a_named_block(tmp_path):
    text = (_with_contact(after="*GAP PROFILE, SLAVE=OTHER\n")
            + "*SENSITIVITY, NAME=BOTH\nMATERIAL, RUBBER, C10, 1\nGAP PROFILE, OTHER, A1, 1\n")
    _expect_error(tmp_path, text, len(text.splitlines()), "cannot be combined with other parameters")


GARMENT_PARAMETERS = ["MATERIAL:FAT:C10", "MATERIAL:MUSCLE:C10", "MATERIAL:MUSCLE:D1", "MATERIAL:GARMENT:C10"]


# the effects that act once the band is on (its last step), as the effect catalog writes them: dv of the muscle and
# lambda_z, at values given in the deck, and their values where the deck leaves them out
BAND_EFFECTS = {"VOLUME CHANGE:MUSCLE": -0.03, "AXIAL STRETCH": 1.02}
BAND_EFFECTS_ABSENT = {"VOLUME CHANGE:MUSCLE": 0.0, "AXIAL STRETCH": 1.0}
# the skin's offset as the band feels it (*GAP PROFILE, mm): a uniform one, a cosine and a sine term
GAP_PROFILE = {"GAP PROFILE:SKIN:A0": 0.0, "GAP PROFILE:SKIN:A3": 0.0, "GAP PROFILE:SKIN:B2": 0.0}
# the skin's shape itself (mm): its nodes moved radially about their centroid, the tissue's elements with them
SHAPE = {"SHAPE:SKIN:A0": 0.0, "SHAPE:SKIN:A2": 0.0, "SHAPE:SKIN:B3": 0.0}
SHAPE_STEP = 1e-4   # mm, with the moved nodes written to 17 digits (`_full_precision_nodes`)


def _full_precision_nodes(text: str, mesh) -> str:
    """The include text with the mesh's node lines (ids 1..N of its first *NODE block) written to 17 digits: its 10
    round a node at 100 mm by up to 5e-8 mm, 2.5e-4 of a difference of +-1e-4 mm."""
    head, nodes_and_rest = text.split("*NODE, NSET=NALL\n", 1)
    rest = nodes_and_rest.split("\n", len(mesh.nodes))[-1]
    lines = "".join("%d, %.17g, %.17g\n" % (i + 1, x, y) for i, (x, y) in enumerate(mesh.nodes.tolist()))
    return head + "*NODE, NSET=NALL\n" + lines + rest


def _skin_moved(leg, values: dict):
    """The leg mesh with its skin nodes moved by the SHAPE coefficients of `values`, radially about their centroid
    (the engine's SHAPE lines)."""
    from dataclasses import replace

    skin = np.unique(leg.skin_loop)
    radial = leg.nodes[skin] - leg.nodes[skin].mean(axis=0)
    phi = np.arctan2(radial[:, 1], radial[:, 0])
    nodes = leg.nodes.copy()
    for name, value in values.items():
        if name.startswith("SHAPE"):
            label = name.rsplit(":", 1)[1]
            shape = (np.sin if label[0] == "B" else np.cos)(int(label[1:]) * phi)
            nodes[skin] += value * shape[:, None] * radial / np.linalg.norm(radial, axis=1)[:, None]
    return replace(leg, nodes=nodes)


def _band_sensitivities_against_differences(tmp_path: Path, step: float, friction_mu: float = 0.0,
                                            hybrid: bool = False, effects: dict | None = None,
                                            parameters=GARMENT_PARAMETERS, gap_step: float = 1e-4
                                            ) -> list[tuple[str, float, float, float]]:
    """The leg under the explicit garment band (templates/leg_garment.inp.j2: inflated, let go onto the skin,
    settled), with `effects` (BAND_EFFECTS' names -> values) in its last step: du/dtheta and dp/dtheta of
    `parameters` against central differences of the engine's own runs, which each redo the whole put-on; the report
    rows of _check_report. `effects` may also give GAP_PROFILE's coefficients (then written as the skin's *GAP
    PROFILE) and SHAPE's (the skin's nodes moved), differenced by +-gap_step mm."""
    from dataclasses import replace

    from orchestrator.engine.decks import (
        MESH_INCLUDE_NAME,
        StepEffects,
        leg_garment_deck,
    )
    from orchestrator.meshing import DEFAULT_MATERIALS, garment_band

    leg = leg_slice_mesh(400, order=2)
    band = garment_band(leg)
    materials = {elset: (law, dict(zip(("C10", "D1"), constants))) for elset, (law, constants) in DEFAULT_MATERIALS.items()}
    materials["GARMENT"] = ("NEO HOOKE", {"C10": band.C10, "D1": band.D1})

    def mesh_text(values):
        moved = _skin_moved(leg, values)
        text = _full_precision_nodes(band.include_text(moved), moved)   # the band as built on the unmoved skin
        if hybrid:   # the leg's u/p elements (the band stays a displacement element, as forward.LegModel writes it)
            text = text.replace("*ELEMENT, TYPE=CPE6, ELSET=EALL", "*ELEMENT, TYPE=CPE6H, ELSET=EALL", 1)
        return text

    effects = dict(effects or {})

    def run(folder: Path, laws, values, sensitivity=()):
        folder.mkdir(parents=True)
        (folder / MESH_INCLUDE_NAME).write_text(mesh_text(values))
        tissues = {elset: (law, tuple(c.values())) for elset, (law, c) in laws.items() if elset != "GARMENT"}
        keywords = StepEffects(volume_changes=tuple((name.split(":")[1], dv) for name, dv in values.items()
                                                    if name.startswith("VOLUME CHANGE")),
                               axial_stretch=values.get("AXIAL STRETCH"))
        gap = {}
        for name, value in values.items():
            if name.startswith("GAP PROFILE"):
                label = name.rsplit(":", 1)[1]
                a, b = gap.get(int(label[1:]), (0.0, 0.0))
                gap[int(label[1:])] = (value, b) if label[0] == "A" else (a, value)
        text = leg_garment_deck(tissues, replace(band, **laws["GARMENT"][1]), leg, friction_mu=friction_mu,
                                effects=keywords, gap_profile=[(k, a, b) for k, (a, b) in sorted(gap.items())]
                                if any(p.startswith("GAP") for p in parameters) else None)
        if sensitivity:
            text += "*SENSITIVITY, PRESSURE=YES\n" + "\n".join(", ".join(name.split(":")) for name in sensitivity) + "\n"
        (folder / "leg.inp").write_text(text)
        result = run_engine(None, folder, "leg", deck_path=folder / "leg.inp")
        assert result.returncode == 0, result.stderr
        return result

    base = run(tmp_path / "base", materials, effects, parameters)
    results = EngineResults(base.outdir)
    du, dp = results.sensitivities(), results.pressure_sensitivities()
    report = []
    for k, name in enumerate(parameters):
        if name.startswith("MATERIAL"):
            _, elset, constant = name.split(":")
            value = materials[elset][1][constant]
        else:
            value = effects.get(name, {**BAND_EFFECTS_ABSENT, **GAP_PROFILE, **SHAPE}[name])
        u, pressure = [], []
        for sign in (1.0, -1.0):
            laws = {e: (law, dict(c)) for e, (law, c) in materials.items()}
            values = dict(effects)
            if name.startswith("MATERIAL"):
                laws[elset][1][constant] = _written(value * (1.0 + sign * step))
            elif name.startswith(("GAP PROFILE", "SHAPE")):
                values[name] = _written(value + sign * gap_step)
            else:
                values[name] = _written(value * (1.0 + sign * step) if value else sign * step)
            side = run(tmp_path / f"{k}{'+' if sign > 0 else '-'}", laws, values)
            u.append(side.u())
            pressure.append(EngineResults(side.outdir).cell_field("pressure"))
        width = (2.0 * gap_step if name.startswith(("GAP PROFILE", "SHAPE")) else
                 _written(value * (1 + step)) - _written(value * (1 - step)) if value else 2.0 * step)
        du_fd, dp_fd = (u[0] - u[1]) / width, (pressure[0] - pressure[1]) / width
        report.append((name, np.abs(du_fd).max(), np.abs(du[name] - du_fd).max() / np.abs(du_fd).max(),
                       np.abs(dp[name] - dp_fd).max() / np.abs(dp_fd).max()))
    return report


def test_sensitivities_through_frictionless_contact(tmp_path):
    """The tissues' constants and the band's C10 (its tension) through frictionless penalty contact. The tangent at
    the converged state, contact elements included, gives the derivative of the state as long as no slave node
    changes its contact status or segment, which a relative step of 1e-4 leaves as it is (measured on this leg,
    du/dC10 of muscle: 2.4e-2, 3.0e-3 and 1.5e-6 from the central differences of steps 1e-2, 1e-3 and 1e-4: a node
    within 1e-3 of such a change)."""
    _check_report("leg under the explicit garment band, frictionless contact",
                  _band_sensitivities_against_differences(tmp_path, 1e-4))


# mu = 0.3 (most of the skin sticking) with the effects of the last step given runs with the fast suite; the effects
# left out, the slipping skin and the u/p elements (20, 15 and 28 s of a 2-core machine's 10 minutes) with the slow one
@pytest.mark.parametrize("friction_mu, hybrid, effects", [pytest.param(0.3, False, {}, marks=pytest.mark.slow),
                                                           pytest.param(0.02, False, {}, marks=pytest.mark.slow),
                                                           pytest.param(0.3, True, {}, marks=pytest.mark.slow),
                                                           (0.3, False, BAND_EFFECTS)],
                         ids=["mu0.3", "mu0.02", "mu0.3-CPE6H", "mu0.3-effects"])
def test_sensitivities_through_friction_along_the_loading_path(tmp_path, friction_mu, hybrid, effects):
    """With Coulomb friction the put-on's end state depends on its path (where each skin node first touched the
    band and how far it slid since): the engine carries du/dtheta and the contact history's sensitivity from
    increment to increment (solver_cpp/src/solver/sensitivity.hpp, (4)-(5)). At mu = 0.3 (most of the skin
    sticking), at mu = 0.02 (much of it slipping) and on the second paper's u/p elements, the tissues' constants and
    the band's C10, and the muscle's volume change and the axial stretch of the last step (where the deck leaves
    them out, and where it gives them), against central differences of the whole put-on (the release in twentieths,
    as orchestrator.engine.decks writes it with friction). Measured at mu = 0.3: relative errors 3e-9 to 7e-7; without the
    history's part of (4), which the last tangent alone gives, 5e-2 to 0.68. The relative step of the differences
    is 3e-5: at 1e-5 the runs' Newton residual (1e-9 of the forces) over the step reached 5e-4, and at 1e-4 or 3e-4
    a step moved a skin node across a change of contact state (the band's C10 read 1-4 % off at mu = 0.02 and 5 % on
    CPE6H; 1e-7 at 3e-5)."""
    report = _band_sensitivities_against_differences(tmp_path, 3e-5, friction_mu, hybrid, effects,
                                                     GARMENT_PARAMETERS + list(BAND_EFFECTS_ABSENT))
    _check_report(f"leg under the explicit garment band, friction {friction_mu}{', CPE6H' if hybrid else ''}", report)


# one parameter moving several: MATERIAL, VOLUME CHANGE and AXIAL STRETCH lines with their weights (D1 and dv differenced)
COMBINED = {"MATERIAL:FAT:C10": 1.7, "MATERIAL:MUSCLE:C10": -0.4, "MATERIAL:MUSCLE:D1": 30.0,
            "VOLUME CHANGE:MUSCLE": 0.05, "AXIAL STRETCH": -0.02}


@pytest.mark.parametrize("friction_mu", [0.0, 0.3], ids=["frictionless", "mu0.3"])
def test_a_named_block_is_one_parameter_the_weighted_sum_of_its_lines(tmp_path, friction_mu):
    """`*SENSITIVITY, NAME=` makes its lines, each with a weight w_i, one parameter t moving every member by w_i t:
    du/dt = sum_i w_i du/dtheta_i in one column (a fitted constant shared by many material groups is one right-hand
    side carried along the frictional path, not one per group). Against the members' own columns of the same run, on
    the leg under the band (u/p elements; frictionless, and at mu = 0.3 carried along the put-on), displacements and
    pressures."""
    from dataclasses import replace

    from orchestrator.engine.decks import (
        MESH_INCLUDE_NAME,
        StepEffects,
        leg_garment_deck,
    )
    from orchestrator.meshing import DEFAULT_MATERIALS, garment_band

    leg = leg_slice_mesh(400, order=2)
    band = garment_band(leg)
    tissues = {elset: (law, constants) for elset, (law, constants) in DEFAULT_MATERIALS.items()}
    text = leg_garment_deck(tissues, replace(band), leg, friction_mu=friction_mu,
                            effects=StepEffects(volume_changes=(("MUSCLE", -0.03),), axial_stretch=1.02))
    lines = {name: ", ".join(name.split(":")) for name in COMBINED}
    text += ("*SENSITIVITY, PRESSURE=YES\n" + "\n".join(lines.values()) + "\n*SENSITIVITY, NAME=TISSUES\n"
             + "\n".join(f"{lines[name]}, {weight}" for name, weight in COMBINED.items()) + "\n")
    (tmp_path / MESH_INCLUDE_NAME).write_text(band.include_text(leg).replace("*ELEMENT, TYPE=CPE6, ELSET=EALL",
                                                                              "*ELEMENT, TYPE=CPE6H, ELSET=EALL", 1))
    (tmp_path / "leg.inp").write_text(text)
    result = run_engine(None, tmp_path, "leg", deck_path=tmp_path / "leg.inp")
    assert result.returncode == 0, result.stderr
    results = EngineResults(result.outdir)
    assert [e["name"] for e in results.sensitivity_parameters] == list(COMBINED) + ["TISSUES"]
    du, dp = results.sensitivities(), results.pressure_sensitivities()
    du_sum = sum(weight * du[name] for name, weight in COMBINED.items())
    dp_sum = sum(weight * dp[name] for name, weight in COMBINED.items())
    assert np.abs(du_sum).max() > 1e-3
    assert np.abs(du["TISSUES"] - du_sum).max() <= 1e-6 * np.abs(du_sum).max()
    assert np.abs(dp["TISSUES"] - dp_sum).max() <= 1e-5 * np.abs(dp_sum).max()


@pytest.mark.parametrize("friction_mu", [0.0, 0.3], ids=["frictionless", "mu0.3"])
def test_sensitivities_to_the_skin_offset_that_the_band_feels(tmp_path, friction_mu):
    """`GAP PROFILE` lines: du/d(a_k, b_k) of the skin's offset as the band's contact sees it (*GAP PROFILE, the
    skin's shape error under the band: orchestrator.fit.geometry_uncertainty), frictionless and carried through friction
    along the put-on (the offset acts at every increment, on the residual and on the contact history it leaves),
    where the deck leaves the profile at zero and where it gives a term, against central differences of the whole
    put-on with the offset moved by +-1e-4 mm."""
    report = _band_sensitivities_against_differences(tmp_path, 3e-5, friction_mu, effects={"GAP PROFILE:SKIN:A3": 0.02},
                                                     parameters=["MATERIAL:FAT:C10", *GAP_PROFILE])
    _check_report(f"the skin's offset under the explicit garment band, friction {friction_mu}", report)


@pytest.mark.parametrize("friction_mu", [0.0, 0.3], ids=["frictionless", "mu0.3"])
def test_sensitivities_to_the_skins_shape_under_the_band(tmp_path, friction_mu):
    """`SHAPE` lines: du/d(a_k, b_k) of the skin's nodes moved radially (the segmented skin's shape error: the
    tissue's elements, the band's contact and the contact's tributary weights all see it), frictionless and through
    friction, against central differences of whole put-ons on meshes with the skin moved by +-1e-4 mm. Measured:
    1e-8 to 8e-7 frictionless; without the weights' change 6e-4. (With a *GAP PROFILE given as well, 5e-5: a moved
    skin moves the centroid about which the profile's angles are taken, which the engine leaves out.)"""
    report = _band_sensitivities_against_differences(tmp_path, 3e-5, friction_mu,
                                                     parameters=["MATERIAL:MUSCLE:C10", *SHAPE, "GAP PROFILE:SKIN:A3"],
                                                     gap_step=SHAPE_STEP)
    _check_report(f"the skin's shape under the explicit garment band, friction {friction_mu}", report)


@pytest.mark.parametrize(
    "profile, fragment",
    [
        ("*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n1, 0.8, 0.8\n", "must stay > 0"),
        ("*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n0, 0.1, 0.0\n", "k must be >= 1"),
        ("*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n1, 0.1, 0.0\n1, 0.0, 0.1\n", "listed twice"),
        ("*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n1, 0.1\n", "expected 3"),
        ("*TENSION PROFILE, NAME=GARMENT, TYPE=SPLINE\n1, 0.1, 0.0\n", "TABLE or FOURIER"),
    ],
    ids=["factor not positive", "k zero", "k twice", "short line", "unknown type"],
)
def test_malformed_fourier_profile(tmp_path, profile, fragment):
    text = BASE.replace("*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n1, 0.1, 0.0\n", profile)
    start = text.splitlines().index(profile.splitlines()[0]) + 1
    keyword_level = fragment in ("must stay > 0", "TABLE or FOURIER")
    line = start if keyword_level else start + len(profile.splitlines()) - 1
    _expect_error(tmp_path, text, line, fragment)
