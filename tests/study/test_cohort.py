"""`calfit study` on a cohort (orchestrator.study.cohort): every case a task on a Dask LocalCluster, one row each in
study.csv, a failed case said and not in the way of the others, and a study started again repeats nothing.

The cases are phantom legs at different truths with points.csv (the displacement points the fit reads), on a
400-element mesh, through identify and montecarlo: the study's mechanics, in seconds. The images-only cohort
through every stage runs in test_cohort_images (slow).
"""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from orchestrator.core.errors import RunFolderError
from orchestrator.engine.runner import LOG_NAME
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import random_truth
from orchestrator.study.cohort import FAILED, ROW_FILE, CaseOptions, run_study

OPTIONS = CaseOptions(n_elements=400, draws=20, stages=("identify", "montecarlo"))


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    root = tmp_path_factory.mktemp("cohort")
    truths = {}
    for seed in (5, 6):
        truths[f"leg-{seed}"] = random_truth(seed)
        make_phantom_case(root / "study" / f"leg-{seed}", theta_kPa=truths[f"leg-{seed}"], n_elements=2000,
                          noise_seeds=(seed, seed + 1))
    broken = root / "study" / "leg-broken"
    shutil.copytree(root / "study" / "leg-5", broken)
    (broken / "loaded.png").unlink()
    lines = []
    summary = run_study(root / "study", root / "out", OPTIONS, workers=2, report=lines.append)
    return root, truths, summary, lines


def _table(root):
    with open(root / "out" / "study.csv", newline="") as handle:
        return {row["case"]: row for row in csv.DictReader(handle)}


def test_every_case_is_a_row_and_the_fits_find_their_truths(cohort):
    root, truths, summary, lines = cohort
    table = _table(root)
    assert sorted(table) == ["leg-5", "leg-6", "leg-broken"] and summary["done"] == 2
    for name, truth in truths.items():
        row = json.loads((root / "out" / "cases" / name / ROW_FILE).read_text())
        theta = np.array([row[p] for p in ("C10_fat", "C10_muscle", "Kv_fat", "Kv_muscle")])
        assert np.all(np.abs(theta - truth) / truth < 0.15), (name, theta, truth)
        assert table[name]["status"] == "done" and float(table[name]["C10_muscle"]) == pytest.approx(theta[1], rel=0.01)
    assert any(line.startswith("[") and "leg-6: done" in line for line in lines)


def test_a_failed_case_says_why_and_does_not_stop_the_others(cohort):
    root, _, summary, _ = cohort
    row = _table(root)["leg-broken"]
    assert row["status"] == FAILED and "loaded" in row["error"]
    assert summary["failed"] == ["leg-broken"]
    assert not (root / "out" / "cases" / "leg-broken" / ROW_FILE).exists()   # tried again next time


def test_the_csv_shows_the_digits_the_intervals_allow(cohort):
    root, _, _, _ = cohort
    row = _table(root)["leg-6"]
    width = float(row["Kv_muscle_high"]) - float(row["Kv_muscle_low"])
    decimals = len(row["Kv_muscle"].partition(".")[2])
    assert 10.0 ** -decimals <= width / 4.0 < 10.0 ** (2 - decimals)   # two significant digits of the std


def test_a_study_started_again_repeats_no_case(cohort):
    root, _, _, _ = cohort
    logs = {name: (root / "out" / "cases" / name / LOG_NAME).read_text() for name in ("leg-5", "leg-6")}
    rows = {name: (root / "out" / "cases" / name / ROW_FILE).stat().st_mtime_ns for name in ("leg-5", "leg-6")}
    again = run_study(root / "study", root / "out", OPTIONS, workers=1)
    assert again["ran_now"] == 1 and again["done"] == 2      # the failed case only
    for name in ("leg-5", "leg-6"):
        assert (root / "out" / "cases" / name / LOG_NAME).read_text() == logs[name]
        assert (root / "out" / "cases" / name / ROW_FILE).stat().st_mtime_ns == rows[name]


def test_a_study_is_a_folder_of_case_folders(cohort, tmp_path):
    root, _, _, _ = cohort
    with pytest.raises(RunFolderError, match="is one case"):
        run_study(root / "study" / "leg-5", tmp_path / "out", OPTIONS)
    with pytest.raises(RunFolderError, match="no case folder"):
        run_study(tmp_path, tmp_path / "out", OPTIONS)
    with pytest.raises(ValueError, match="stages"):
        CaseOptions(stages=("montecarlo",))


def test_the_table_is_also_parquet_at_full_precision(cohort):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    root, _, _, _ = cohort
    table = pd.read_parquet(root / "out" / "study.parquet").set_index("case")
    row = json.loads((root / "out" / "cases" / "leg-5" / ROW_FILE).read_text())
    assert table.loc["leg-5", "C10_fat"] == row["C10_fat"] and table.loc["leg-broken", "status"] == FAILED
