"""Malformed decks: calfit-fe exits 2 with `FILE:LINE: what is wrong`, never crashes or hangs.

A valid two-triangle deck (which must solve, exit 0) is mutated in one place per case;
each case knows the file and line of the fault, and the test asserts the exit code 2,
the `FILE:LINE:` prefix of the message with that line number (for faults that can be
reported on two lines, e.g. a material left without data, both are accepted), and that
the engine returns within a timeout. The rules come from solver_cpp/README.md
("Any unknown keyword or parameter, unknown set, bad number, missing data line,
inverted or degenerate element is an error (exit 2) naming the file and line").
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from orchestrator.engine.locate import find_engine

BASE = """\
*HEADING
malformed-deck table: the valid base deck
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
*MATERIAL, NAME=RUBBER
*HYPERELASTIC, NEO HOOKE
1.0, 0.1
*SOLID SECTION, ELSET=EALL, MATERIAL=RUBBER
*BOUNDARY
BOTTOM, 1, 2
*STEP, NLGEOM
*STATIC
0.5, 1.0, 1e-5, 1.0
*DLOAD
1, P2, 0.1
*END STEP
"""
BASE_LINES = BASE.splitlines()


def line_of(text: str, lines: list[str] = BASE_LINES) -> int:
    """1-based number of the line equal to text."""
    return lines.index(text) + 1


@dataclass
class Case:
    name: str
    main: str  # text of main.inp
    where: list[tuple[str, int]]  # acceptable (file name, line) of the message
    extra: dict[str, str] = field(default_factory=dict)  # other files in the deck folder


def replace(old: str, new: str) -> tuple[str, int]:
    """BASE with the line old replaced by new (may be several lines); returns text and line."""
    k = line_of(old)
    lines = BASE_LINES[: k - 1] + new.split("\n") + BASE_LINES[k:]
    return "\n".join(lines) + "\n", k


def insert_after(old: str, new: str) -> tuple[str, int]:
    k = line_of(old)
    lines = BASE_LINES[:k] + new.split("\n") + BASE_LINES[k:]
    return "\n".join(lines) + "\n", k + 1


def _cases() -> list[Case]:
    cases: list[Case] = []

    def add(name, text_line, where=None):
        text, k = text_line
        cases.append(Case(name, text, where or [("main.inp", k)]))

    add("unknown keyword", insert_after("malformed-deck table: the valid base deck", "*FROBNICATE"))
    add("unknown parameter", replace("*ELEMENT, TYPE=CPE3, ELSET=EALL", "*ELEMENT, TYPE=CPE3, ELSET=EALL, COLOR=RED"))
    add("missing required parameter (TYPE)", replace("*ELEMENT, TYPE=CPE3, ELSET=EALL", "*ELEMENT, ELSET=EALL"))
    add("missing required parameter (NAME)", replace("*MATERIAL, NAME=RUBBER", "*MATERIAL"))
    add("missing required parameter (INPUT)", insert_after("1, 2", "*INCLUDE"))
    add("bad number in node", replace("3, 1.0, 1.0", "3, 1.0, 1.0x"))
    add("bad number in material", replace("1.0, 0.1", "1.0, abc"))
    add("bad integer id", replace("2, 1, 3, 4", "2.5, 1, 3, 4"))
    add("too few values in node", replace("3, 1.0, 1.0", "3, 1.0"))
    add("too few nodes in element", replace("2, 1, 3, 4", "2, 1, 3"))
    add("unknown node in element", replace("2, 1, 3, 4", "2, 1, 3, 9"))
    add("unknown set in section", replace(*_sec("NOPE")))
    add("unknown set in boundary", replace("BOTTOM, 1, 2", "NOSUCHSET, 1, 2"))
    add("unknown element in dload", replace("1, P2, 0.1", "99, P2, 0.1"))
    add("unknown surface in laplace pressure", insert_after("1, P2, 0.1", "*LAPLACE PRESSURE, SURFACE=NOPE, TENSION=1.0"))
    add("duplicate node id", replace("4, 0.0, 1.0", "3, 0.0, 1.0"))
    add("duplicate element id", replace("2, 1, 3, 4", "1, 1, 3, 4"))
    add("inverted (clockwise) element", replace("2, 1, 3, 4", "2, 1, 4, 3"))
    add("degenerate (zero-area) element", replace("2, 1, 3, 4", "2, 1, 2, 1"))
    add("collinear element", replace("4, 0.0, 1.0", "4, 2.0, 2.0"), [("main.inp", line_of("2, 1, 3, 4"))])
    add("unknown element type", replace("*ELEMENT, TYPE=CPE3, ELSET=EALL", "*ELEMENT, TYPE=CPE9, ELSET=EALL"))
    add("unknown hyperelastic model", replace("*HYPERELASTIC, NEO HOOKE", "*HYPERELASTIC, OGDEN"))
    text = BASE.replace("*HYPERELASTIC, NEO HOOKE\n1.0, 0.1\n", "")
    mat, sec = line_of("*MATERIAL, NAME=RUBBER"), line_of("*SOLID SECTION, ELSET=EALL, MATERIAL=RUBBER") - 2
    add("material without hyperelastic data", (text, mat), [("main.inp", mat), ("main.inp", sec)])
    hyper = line_of("*HYPERELASTIC, NEO HOOKE")
    add("hyperelastic without data line", (BASE.replace("*HYPERELASTIC, NEO HOOKE\n1.0, 0.1\n", "*HYPERELASTIC, NEO HOOKE\n"), hyper), [("main.inp", hyper), ("main.inp", hyper + 1)])
    add("section naming unknown material", replace(*_sec("EALL", "STEEL")))
    add("negative C10", replace("1.0, 0.1", "-1.0, 0.1"))
    add("negative D1", replace("1.0, 0.1", "1.0, -0.1"))
    add("step without NLGEOM", replace("*STEP, NLGEOM", "*STEP"))
    add("unknown face label", replace("1, P2, 0.1", "1, P7, 0.1"))
    add("unknown surface face label", replace("1, S2", "1, S9"))
    add("DOF out of range", replace("BOTTOM, 1, 2", "BOTTOM, 1, 7"))
    add("DOF zero", replace("BOTTOM, 1, 2", "BOTTOM, 0, 2"))
    add("bad static data", replace("0.5, 1.0, 1e-5, 1.0", "0.5, one, 1e-5, 1.0"))
    add("END STEP without STEP", insert_after("BOTTOM, 1, 2", "*END STEP"))
    add("STEP inside a STEP", insert_after("*STEP, NLGEOM", "*STEP, NLGEOM"))
    cases.append(Case("data line before any keyword", "1, 2, 3\n" + BASE, [("main.inp", 1)]))
    _project_kinematics_cases(add)
    # Includes: the error names the including line (or the line that closes the cycle).
    inc_line = line_of("*NSET, NSET=BOTTOM")
    text, _ = replace("*NSET, NSET=BOTTOM", "*INCLUDE, INPUT=missing_sets.inp\n*NSET, NSET=BOTTOM")
    cases.append(Case("include of a missing file", text, [("main.inp", inc_line)]))
    text, _ = replace("*NSET, NSET=BOTTOM", "*INCLUDE, INPUT=a.inp\n*NSET, NSET=BOTTOM")
    cases.append(
        Case(
            "include cycle",
            text,
            [("b.inp", 2), ("main.inp", inc_line), ("a.inp", 2)],
            extra={"a.inp": "** a\n*INCLUDE, INPUT=b.inp\n", "b.inp": "** b\n*INCLUDE, INPUT=a.inp\n"},
        )
    )
    text, _ = replace("*NSET, NSET=BOTTOM", "*INCLUDE, INPUT=sub/bad.inp\n*NSET, NSET=BOTTOM")
    cases.append(Case("error inside an included file", text, [("bad.inp", 3)], extra={"sub/bad.inp": "** included\n*ELSET, ELSET=E1\n1, x\n"}))
    return cases


def _project_kinematics_cases(add) -> None:
    """*VOLUME CHANGE, *AXIAL STRETCH, *RIGID MOTION and AVRIL's C20 (solver_cpp/README.md,
    Project keywords): unknown set, out-of-range value, wrong number of values, keyword
    outside a step, unknown parameter. `add(name, (text, line))` with the line that the
    message must name; in_step(new) puts new after the step's *DLOAD data line."""
    step_line = "1, P2, 0.1"
    model_line = "BOTTOM, 1, 2"  # the model-level *BOUNDARY data line, before *STEP

    def in_step(new: str, offset: int = 0):
        text, k = insert_after(step_line, new)
        return text, k + offset

    def in_model(new: str):
        return insert_after(model_line, new)

    # *VOLUME CHANGE, ELSET=, OP=; data line dv > -1
    add("volume change: unknown element set", in_step("*VOLUME CHANGE, ELSET=MUSCLE\n-0.1"))
    add("volume change: dv = -1 (no volume left)", in_step("*VOLUME CHANGE, ELSET=EALL\n-1.0", 1))
    add("volume change: dv not a number", in_step("*VOLUME CHANGE, ELSET=EALL\nminus", 1))
    add("volume change: two values", in_step("*VOLUME CHANGE, ELSET=EALL\n-0.1, 0.2", 1))
    add("volume change: two data lines", in_step("*VOLUME CHANGE, ELSET=EALL\n-0.1\n-0.2", 2))
    add("volume change: no data line", in_step("*VOLUME CHANGE, ELSET=EALL"))
    add("volume change: no ELSET", in_step("*VOLUME CHANGE\n-0.1"))
    add("volume change: unknown parameter", in_step("*VOLUME CHANGE, ELSET=EALL, SCALE=2\n-0.1"))
    add("volume change: bad OP", in_step("*VOLUME CHANGE, ELSET=EALL, OP=ADD\n-0.1"))
    add("volume change: outside a step", in_model("*VOLUME CHANGE, ELSET=EALL\n-0.1"))
    # *AXIAL STRETCH; data line lambda_z > 0
    add("axial stretch: zero", in_step("*AXIAL STRETCH\n0.0", 1))
    add("axial stretch: negative", in_step("*AXIAL STRETCH\n-1.05", 1))
    add("axial stretch: two values", in_step("*AXIAL STRETCH\n1.0, 1.1", 1))
    add("axial stretch: not a number", in_step("*AXIAL STRETCH\nlong", 1))
    add("axial stretch: no data line", in_step("*AXIAL STRETCH"))
    add("axial stretch: unknown parameter", in_step("*AXIAL STRETCH, OP=NEW\n1.05"))
    add("axial stretch: outside a step", in_model("*AXIAL STRETCH\n1.05"))
    # *RIGID MOTION, NSET=, CX=, CY=, OP=; data line ux, uy, angle
    add("rigid motion: unknown node set", in_step("*RIGID MOTION, NSET=TIBIA\n0, 0, 5"))
    add("rigid motion: two values", in_step("*RIGID MOTION, NSET=BOTTOM\n0.1, 5", 1))
    add("rigid motion: four values", in_step("*RIGID MOTION, NSET=BOTTOM\n0.1, 0, 5, 1", 1))
    add("rigid motion: angle not a number", in_step("*RIGID MOTION, NSET=BOTTOM\n0.1, 0, five", 1))
    add("rigid motion: CX without CY", in_step("*RIGID MOTION, NSET=BOTTOM, CX=0.5\n0, 0, 5"))
    add("rigid motion: no NSET", in_step("*RIGID MOTION\n0, 0, 5"))
    add("rigid motion: unknown parameter", in_step("*RIGID MOTION, NSET=BOTTOM, CZ=1\n0, 0, 5"))
    add("rigid motion: outside a step", in_model("*RIGID MOTION, NSET=BOTTOM\n0, 0, 5"))
    add("rigid motion: node in two motions", in_step("*RIGID MOTION, NSET=BOTTOM\n0, 0, 5\n*RIGID MOTION, NSET=1\n0, 0, 3", 2))
    add("boundary on a rigidly moved node", in_step("*RIGID MOTION, NSET=BOTTOM\n0, 0, 5\n*BOUNDARY\n1, 1, 1, 0.1", 3))
    # *HYPERELASTIC, AVRIL: C10, Kv[, C20 >= 0]
    hyper = line_of("*HYPERELASTIC, NEO HOOKE")
    avril = BASE.replace("*HYPERELASTIC, NEO HOOKE\n1.0, 0.1\n", "*HYPERELASTIC, AVRIL\n1.0, 10.0, {}\n")
    add("Avril: negative C20", (avril.format("-0.5"), hyper + 1))
    add("Avril: four constants", (avril.format("0.5, 1.0"), hyper + 1))


def _sec(elset: str, material: str = "RUBBER") -> tuple[str, str]:
    return "*SOLID SECTION, ELSET=EALL, MATERIAL=RUBBER", f"*SOLID SECTION, ELSET={elset}, MATERIAL={material}"


CASES = _cases()
TIMEOUT_S = 30


def _run(deck: Path, tmp: Path):
    return subprocess.run(
        [str(find_engine()), str(deck), "-o", str(tmp / "out"), "--quiet"],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        cwd=tmp,
    )


def test_table_has_at_least_20_kinds():
    assert len({c.name for c in CASES}) >= 20


def test_base_deck_is_valid(tmp_path):
    deck = tmp_path / "main.inp"
    deck.write_text(BASE)
    proc = _run(deck, tmp_path)
    assert proc.returncode == 0, proc.stderr


def test_base_deck_with_the_project_kinematics_is_valid(tmp_path):
    """The mutations of _project_kinematics_cases start from a deck that solves."""
    text, _ = insert_after(
        "1, P2, 0.1",
        "*VOLUME CHANGE, ELSET=EALL, OP=NEW\n-0.05\n*AXIAL STRETCH\n1.02\n*RIGID MOTION, NSET=BOTTOM, CX=0.5, CY=0\n0.01, 0, 2",
    )
    text = text.replace("*HYPERELASTIC, NEO HOOKE\n1.0, 0.1\n", "*HYPERELASTIC, AVRIL\n1.0, 10.0, 0.5\n")
    deck = tmp_path / "main.inp"
    deck.write_text(text)
    proc = _run(deck, tmp_path)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_malformed_deck(tmp_path, case):
    deck = tmp_path / "main.inp"
    deck.write_text(case.main)
    for name, text in case.extra.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    try:
        proc = _run(deck, tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{case.name}: calfit-fe did not return within {TIMEOUT_S} s")
    assert proc.returncode == 2, f"{case.name}: exit {proc.returncode}, stderr: {proc.stderr!r}"
    found = re.findall(r"([^\s:]+\.inp):(\d+):", proc.stderr)
    assert found, f"{case.name}: no FILE:LINE: in {proc.stderr!r}"
    got = [(Path(f).name, int(n)) for f, n in found]
    assert got[0] in case.where, f"{case.name}: message at {got[0]}, expected one of {case.where}: {proc.stderr!r}"
    assert not (tmp_path / "out" / "step-1.vtu").exists()


@pytest.mark.parametrize("content", ["", "\n\n", "** only a comment\n"], ids=["empty", "blank lines", "comment only"])
def test_empty_deck(tmp_path, content):
    deck = tmp_path / "main.inp"
    deck.write_text(content)
    proc = _run(deck, tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert re.search(r"main\.inp:\d+:", proc.stderr), proc.stderr


def test_missing_deck_file(tmp_path):
    proc = _run(tmp_path / "nowhere.inp", tmp_path)
    assert proc.returncode in (2, 4), proc.stderr
    assert "nowhere.inp" in proc.stderr


@pytest.mark.parametrize("blob", [b"\x00\xff\xfe*NODE\n1,\x00,2\n", bytes(range(256)) * 4], ids=["nul bytes", "binary"])
def test_binary_garbage(tmp_path, blob):
    deck = tmp_path / "main.inp"
    deck.write_bytes(blob)
    proc = _run(deck, tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert re.search(r"main\.inp:\d+:", proc.stderr), proc.stderr
