"""What a new user meets first: every bad input below is refused by the `calfit` command with exit code 2 and one
sentence on stderr that names the file or the option and says how to mend it, no traceback, and nothing left
behind (no run folder, no lock file). `calfit --version` prints the package's version.

The cases are small hand-written case folders (48x64 pixels): every refusal comes before any segmentation, mesh or
engine run, so the whole file runs in seconds.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orchestrator.case.folder import write_case_folder
from orchestrator.cli import main, version
from orchestrator.core.run_lock import LOCK_NAME

SHAPE = (48, 64)
PIXEL = (0.5, 0.5)


def _labels() -> np.ndarray:
    labels = np.zeros(SHAPE, np.uint8)
    labels[8:40, 8:56] = 1
    labels[12:36, 12:52] = 2
    labels[20:26, 20:28] = 3
    return labels


@pytest.fixture
def case(tmp_path) -> Path:
    rng = np.random.default_rng(3)
    images = [rng.integers(100, 60000, SHAPE).astype(np.uint16) for _ in range(2)]
    return write_case_folder(tmp_path / "case", name="first-hour", unloaded=images[0], loaded=images[1],
                             pixel_size_mm=PIXEL, tension_N_per_mm=0.16, labels=_labels())


def _png(path: Path, pixels: np.ndarray) -> None:
    from orchestrator.case._formats import write_png16

    write_png16(path, pixels)


def _edit_toml(old: str, new: str):
    def edit(folder: Path) -> None:
        toml = folder / "case.toml"
        text = toml.read_text()
        assert old in text
        toml.write_text(text.replace(old, new))
    return edit


def _black(folder: Path) -> None:
    (folder / "labels.png").unlink()
    for name in ("unloaded.png", "loaded.png"):
        _png(folder / name, np.zeros(SHAPE, np.uint16))


def _corrupt_dicom(folder: Path) -> None:
    (folder / "loaded.png").unlink()
    (folder / "loaded.dcm").write_bytes(b"\0" * 128 + b"not a DICOM dataset at all" * 8)


def _labels_with(block: tuple[slice, slice], value: int = 255):
    def edit(folder: Path) -> None:
        labels = _labels()
        labels[block] = value
        _png(folder / "labels.png", labels)
    return edit


def _snapshot(root: Path) -> set[str]:
    return {str(path.relative_to(root)) for path in root.rglob("*")}


def _refused(capsys, argv: list[str]) -> str:
    """Run `calfit argv` in this process: exit code 2 (returned, or argparse's SystemExit), one line on stderr,
    nothing on stdout; returns that line."""
    try:
        code = main(argv)
    except SystemExit as stop:
        code = stop.code
    captured = capsys.readouterr()
    assert code == 2, captured.err
    assert "Traceback" not in captured.err and captured.out == ""
    line = captured.err.strip().splitlines()[-1]
    assert line.startswith("calfit"), captured.err
    return line


# (what the user did, how the case is spoiled, the extra arguments, what the sentence must say: the file or option,
# what is wrong, the fix)
BAD_INPUTS = [
    ("all-black images", _black, [], ["unloaded.png", "single grey level", "export the MRI slice itself again"]),
    ("0-byte PNG", lambda f: (f / "loaded.png").write_bytes(b""), [],
     ["loaded.png", "is empty (0 bytes)", "copy the slice again"]),
    ("corrupt DICOM", _corrupt_dicom, [], ["loaded.dcm", "not a DICOM file", "export the slice again as DICOM"]),
    ("labels.png of another size", lambda f: _png(f / "labels.png", _labels()[:40]), [],
     ["labels.png", "is 40x64 pixels but unloaded.png is 48x64", "remove labels.png (calfit then segments"]),
    ("labels.png with 255 at a corner", _labels_with((slice(0, 6), slice(0, 6))), [],
     ["labels.png", "label 255", "outside the leg", "0 background, 1 fat, 2 muscle, 3 bone", "relabel those pixels"]),
    ("label 255 inside the leg", _labels_with((slice(14, 18), slice(36, 40))), [],
     ["labels.png", "label 255", "inside the leg", "which means no tissue", "relabel those pixels"]),
    ("a compartment label of a few pixels", _labels_with((slice(14, 18), slice(36, 40)), value=5), [],
     ["labels.png", "label 5", "too small for a muscle compartment", "relabel those pixels"]),
    ("tension of 1e9 N/mm", _edit_toml("tension_N_per_mm = 0.16", "tension_N_per_mm = 1e9"), [],
     ["case.toml", "line 6", "[garment] tension_N_per_mm = 1000000000.0", "at most 2", "write tension_N_per_mm = 0.16"]),
    ("pixel size in cm", _edit_toml("[0.5, 0.5]", "[360.0, 360.0]"), [],
     ["case.toml", "[case] pixel_size_mm = [360.0, 360.0]", "between 0.01 and 5 mm", "write pixel_size_mm = [0.36"]),
    ("pixel size of 10 nm", _edit_toml("[0.5, 0.5]", "[1e-05, 1e-05]"), [],
     ["case.toml", "pixel_size_mm = [1e-05, 1e-05]", "between 0.01 and 5 mm"]),
    ("a typo in a key", _edit_toml("tension_N_per_mm", "tension_N_per_m"), [],
     ["case.toml", "[garment] has an unknown key 'tension_N_per_m'", "write tension_N_per_mm"]),
    ("--workers 0", None, ["--workers", "0"], ["--workers", "0 is not a whole number of at least 1", "give 1 or more"]),
    ("--workers -3", None, ["--workers", "-3"], ["--workers", "give 1 or more"]),
    ("--step 0", None, ["--step", "0"], ["--step", "give 1 or more"]),
    ("--step -2", None, ["--step", "-2"], ["--step", "give 1 or more"]),
]


@pytest.mark.parametrize("what, spoil, extra, says", BAD_INPUTS, ids=[entry[0] for entry in BAD_INPUTS])
def test_a_bad_input_to_measure_is_one_sentence_and_leaves_nothing(case, tmp_path, capsys, what, spoil, extra, says):
    if spoil is not None:
        spoil(case)
    before = _snapshot(tmp_path)
    run = tmp_path / "runs" / "run"
    line = _refused(capsys, ["measure", str(case), "--out", str(run), *extra])
    for text in says:
        assert text in line, f"{text!r} not in {line!r}"
    assert _snapshot(tmp_path) == before     # no run folder, no runs/ above it, nothing in the case


def test_the_wrong_advice_is_gone(case, tmp_path, capsys):
    _png(case / "labels.png", _labels()[:40])
    assert "calfit segment" not in _refused(capsys, ["measure", str(case), "--out", str(tmp_path / "run")])
    _labels_with((slice(0, 6), slice(0, 6)))(case)
    assert "touches the image border" not in _refused(capsys, ["measure", str(case), "--out", str(tmp_path / "run")])


def test_a_case_folder_that_does_not_exist_leaves_no_run_folder(tmp_path, capsys):
    line = _refused(capsys, ["measure", str(tmp_path / "nowhere"), "--out", str(tmp_path / "run")])
    assert "nowhere: is not a folder" in line and "give the path of a case folder" in line
    assert list(tmp_path.iterdir()) == []


def test_a_refused_command_in_an_existing_folder_leaves_it_as_it_was(tmp_path, capsys):
    """The user's own folder given as --out is never removed, and gets no lock file from a refused command."""
    mine = tmp_path / "my-runs"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    _refused(capsys, ["measure", str(tmp_path / "nowhere"), "--out", str(mine)])
    assert sorted(path.name for path in mine.iterdir()) == ["notes.txt"] and not (mine / LOCK_NAME).exists()


@pytest.mark.parametrize("command", [["measure", "CASE", "--out"], ["identify", "CASE", "--out"], ["solve", "DECK.inp", "-o"],
                                     ["study", "STUDY", "--out"]])
@pytest.mark.parametrize("under", [False, True], ids=["a file", "under a file"])
def test_an_output_folder_that_is_a_file_is_refused_by_its_option(tmp_path, capsys, command, under):
    existing = tmp_path / "results.txt"
    existing.write_text("a file the user keeps")
    target = existing / "run" if under else existing
    line = _refused(capsys, [*command, str(target)])
    option = command[-1]
    assert f"argument {option}" in line or f"/{option}" in line, line
    assert str(target) in line
    assert ("which is a file" if under else "is a file, not a folder") in line
    assert "give the path of a folder" in line
    assert sorted(path.name for path in tmp_path.iterdir()) == ["results.txt"]
    assert existing.read_text() == "a file the user keeps"


def test_the_command_itself_prints_no_traceback(case, tmp_path):
    """The installed entry point, as a user runs it: the sentence and exit code 2, and no traceback."""
    (case / "loaded.png").write_bytes(b"")
    finished = subprocess.run([sys.executable, "-m", "orchestrator.cli", "measure", str(case), "--out",
                               str(tmp_path / "run")], capture_output=True, text=True, timeout=120)
    assert finished.returncode == 2
    assert finished.stderr.startswith("calfit: ") and finished.stderr.count("\n") == 1, finished.stderr
    assert "loaded.png: is empty (0 bytes)" in finished.stderr and "Traceback" not in finished.stderr
    assert not (tmp_path / "run").exists()


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    printed = capsys.readouterr().out.strip()
    assert printed == f"calfit {version()}" and version()[0].isdigit()
    from importlib.metadata import version as installed

    assert version() == installed("calfit")
