"""The study report (orchestrator/report/study_report.py) from study rows: the pressure at the standard's named heights,
the profiles, the distributions and the failing cases."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orchestrator.core.units import MMHG_PER_KPA
from orchestrator.report.study_report import (
    at_height,
    parameter_names,
    pressure_names,
    write_study_report,
)

HEIGHTS = [204.0, 212.0, 220.0, 228.0]


def _row(k: int, height: float) -> dict:
    """A slice whose interface pressure falls linearly with height (2.8 kPa at 204 mm, -0.01 kPa/mm)."""
    pressure = 2.8 - 0.01 * (height - 204.0)
    return {"case": f"leg-z{height:.1f}mm", "status": "done", "error": "", "height_mm": height,
            "tension_N_per_mm": 0.2 - 0.0005 * (height - 204.0), "misfit_over_floor": 1.0 + 0.05 * k,
            "C10_fat": 3.0 + 0.1 * k, "C10_fat_low": 2.8 + 0.1 * k, "C10_fat_high": 3.2 + 0.1 * k,
            "C10_fat_identifiable": True,
            "Kv_fat": 90.0 + k, "Kv_fat_low": 80.0 + k, "Kv_fat_high": 100.0 + k, "Kv_fat_identifiable": k != 2,
            "interface_pressure_kPa": pressure, "interface_pressure_std_kPa": 0.1 * pressure,
            "pressure_deep_veins_kPa": 0.8 * pressure, "pressure_deep_veins_std_kPa": 0.05,
            "verdict": "the model fits to the noise floor", "explained": False, "lack_of_fit": k == 3,
            "wall_s": 30.0}


@pytest.fixture()
def rows():
    table = [_row(k, h) for k, h in enumerate(HEIGHTS)]
    table.append({"case": "leg-z236.0mm", "status": "failed", "error": "ImagingError: no bone found",
                  "height_mm": 236.0, "wall_s": 2.0})
    return table


def test_columns_are_found_from_the_rows(rows):
    assert parameter_names(rows) == ["C10_fat", "Kv_fat"]
    assert pressure_names(rows) == ["interface_pressure_kPa", "pressure_deep_veins_kPa"]


def test_pressure_between_slices_is_linear_and_none_outside(rows):
    done = rows[:4]
    value, spread = at_height(done, "interface_pressure_kPa", 216.0)
    assert value == pytest.approx(2.8 - 0.12)
    assert spread == pytest.approx(0.1 * (2.8 - 0.12))
    assert at_height(done, "interface_pressure_kPa", 250.0) is None
    assert at_height(done, "interface_pressure_kPa", 200.0) is None


def test_report_of_a_volume(tmp_path, rows):
    volume = {"name": "phantom-leg", "slice_spacing_mm": 8.0,
              "motion": {"rotation_vector_deg": [0.5, -0.5, 3.0], "translation_mm": [2.0, -1.0, 4.0],
                         "centre_mm": [0, 0, 0]},
              "compression_heights_mm": {"B": 204.0, "B1": 216.0, "C": 250.0}}
    page = write_study_report(tmp_path, rows, volume)
    report = json.loads((page.parent / "report.json").read_text())
    heights = next(t for t in report["answers"]["tables"] if t["id"] == "answers_heights")
    by_name = {row[0]: row for row in heights["rows"]}
    assert by_name["B1"][2] == pytest.approx(2.68)                    # interface pressure, kPa
    assert by_name["B1"][4] == pytest.approx(2.68 * MMHG_PER_KPA)     # and in mmHg
    assert by_name["B1"][5] == pytest.approx(0.8 * 2.68)              # deep veins
    assert by_name["C"][2] is None                                    # 250 mm: beyond the studied slices
    assert "leg-z228.0mm" in report["answers"]["verdict"] and "leg-z236.0mm" in report["answers"]["verdict"]
    failing = next(s for s in report["sections"] if s["id"] == "failing")["tables"][0]
    assert [row[0] for row in failing["rows"]] == ["leg-z228.0mm", "leg-z236.0mm"]
    for name in ("profile_parameters.png", "profile_pressures.png", "profile_misfit.png", "distributions.png"):
        assert (page.parent / name).stat().st_size > 10_000
    distribution = next(s for s in report["sections"] if s["id"] == "distributions")["tables"][0]
    kv = next(row for row in distribution["rows"] if row[0] == "Kv_fat")
    assert kv[1] == pytest.approx(91.5) and kv[5] == "3 of 4"
    html = page.read_text()
    assert "Pressure at the compression standard" in html and "2.68" in html


def test_report_of_a_cohort_has_no_profiles(tmp_path, rows):
    for row in rows:
        row.pop("height_mm")
    page = write_study_report(tmp_path, rows[:4])
    report = json.loads((page.parent / "report.json").read_text())
    assert [s["id"] for s in report["sections"]] == ["distributions", "failing", "table"]
    assert not report["answers"]["tables"]
    assert np.isfinite(report["sections"][-1]["tables"][0]["rows"][0][1])
