"""The report of a whole run (identify, Monte-Carlo, pressures, diagnose) on a phantom with a hidden fluid loss
of the muscle: the page is what the template makes of report.json (every table of the JSON on the page, cell
by cell as the page prints it, every figure present and a PNG), the user's questions are answered at the top
(pressure at each landmark in kPa and mmHg with its spread, the diagnosis' verdict), and every figure drawn
on the image has its axes in mm and colour bars that say their unit."""

from __future__ import annotations

import json
from html.parser import HTMLParser

import numpy as np
import pytest
from conftest import copy_run

from orchestrator.core.digits import decimals
from orchestrator.core.units import MMHG_PER_KPA
from orchestrator.report import figures
from orchestrator.report.run_report import format_cell, write_report
from orchestrator.run.setup import PARAMETERS_FILE, read_json
from orchestrator.run.stages import run_diagnose, run_montecarlo, run_pressures

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class PageReader(HTMLParser):
    """Tables (by id: caption, header cells, body rows), image sources and section ids of a page."""

    def __init__(self):
        super().__init__()
        self.tables, self.images, self.sections = {}, [], []
        self._table = self._row = self._cell = None
        self._in_caption = False

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "table":
            self._table = self.tables.setdefault(attrs["id"], {"caption": "", "header": [], "rows": []})
        elif tag == "caption":
            self._in_caption = True
        elif tag == "tr" and self._table is not None:
            self._row = []
        elif tag in ("td", "th") and self._row is not None:
            self._cell = ""
        elif tag == "img":
            self.images.append(attrs["src"])
        elif tag == "section":
            self.sections.append(attrs["id"])

    def handle_endtag(self, tag):
        if tag == "table":
            self._table = None
        elif tag == "caption":
            self._in_caption = False
        elif tag in ("td", "th") and self._cell is not None:
            self._row.append(self._cell.strip())
            self._cell = None
        elif tag == "tr" and self._row is not None:
            if self._table["header"] or not self._row:
                self._table["rows"].append(self._row)
            else:
                self._table["header"] = self._row
            self._row = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data
        elif self._in_caption and self._table is not None:
            self._table["caption"] += data


@pytest.fixture(scope="module")
def reported(drainage_case, drainage_identified, tmp_path_factory):
    """A run through every stage, then its report; the figures matplotlib drew, with their axes' labels."""
    _, truth_folder = drainage_case
    run = copy_run(drainage_identified, tmp_path_factory.mktemp("report") / "run")
    run_montecarlo(run, draws=30, workers=2, progress=False)
    run_pressures(run, draws=8, workers=2, progress=False)
    run_diagnose(run, refit_effects=["drainage"], workers=2, progress=False)
    drawn = {}
    save = figures.save

    def recording_save(figure, path):
        axes = [a for ax in figure.axes for a in (ax, *ax.child_axes)]     # secondary axes (mmHg) are children
        drawn[path.name] = {"x": [ax.get_xlabel() for ax in axes], "y": [ax.get_ylabel() for ax in axes]}
        return save(figure, path)

    truth = read_json(truth_folder / PARAMETERS_FILE, "calfit phantom")["parameters_kPa"]
    figures.save = recording_save
    try:
        page = write_report(run, truth)
    finally:
        figures.save = save
    reader = PageReader()
    reader.feed(page.read_text(encoding="utf-8"))
    return page, json.loads((page.parent / "report.json").read_text()), reader, drawn


def _json_tables(report: dict) -> list[dict]:
    return report["answers"]["tables"] + [t for section in report["sections"] for t in section["tables"]]


def test_every_table_of_the_json_is_on_the_page_cell_by_cell(reported):
    _, report, page, _ = reported
    tables = _json_tables(report)
    assert {t["id"] for t in tables} == set(page.tables)
    assert {"answers_pressures", "answers_parameters", "table1", "table2", "table3", "table4", "ranking",
            "comparison", "sectors"} <= set(page.tables)
    for table in tables:
        shown = page.tables[table["id"]]
        assert shown["caption"].strip() == table["title"]
        assert shown["header"] == table["header"]
        uncertainties = table["uncertainties"] or [[None] * len(row) for row in table["rows"]]
        assert shown["rows"] == [[format_cell(v, u) for v, u in zip(row, us)]
                                 for row, us in zip(table["rows"], uncertainties)], table["id"]
        for row, values, us in zip(shown["rows"], table["rows"], uncertainties):
            for text, value, u in zip(row, values, us):
                if isinstance(value, float):   # the JSON's number, to 4 digits or to its uncertainty's place
                    place = decimals(u)
                    tolerance = dict(rel=5e-4, abs=1e-300) if place is None else dict(abs=0.5 * 10.0 ** -place + 1e-12)
                    assert float(text) == pytest.approx(value, **tolerance)


def test_every_figure_is_on_the_page_and_a_png(reported):
    page_path, report, page, _ = reported
    listed = [f["file"] for section in report["sections"] for f in section["figures"]]
    assert sorted(listed) == sorted(page.images)
    assert {"images.png", "segmentation_mesh.png", "warped_dk.png", "intervals.png", "pressure.png", "ranking.png",
            "misfit.png", "residuals_before_after.png", "dk_before_after.png", "diagnosis.png"} <= set(listed)
    for name in listed:
        assert (page_path.parent / name).read_bytes()[:8] == PNG_SIGNATURE
    assert page.sections == ["answers"] + [s["id"] for s in report["sections"]]
    assert page.sections[-1] == "diagnosis"


def test_the_top_of_the_page_answers_pressure_in_mmhg_and_the_verdict(reported):
    page_path, report, page, _ = reported
    pressures = read_json(page_path.parent.parent / "pressures.json", "")
    rows = {row[0]: row for row in report["answers"]["tables"][0]["rows"]}
    for k, name in enumerate(pressures["landmarks"]):
        _, mean, std, mean_mmhg, std_mmhg, of_parameters, of_tension = rows[name]
        assert mean == pressures["mean_kPa"][k] and of_parameters == pressures["std_kPa"][k]
        # the headline spread holds the tension's uncertainty (Table 4), not the parameters' alone
        assert of_tension == pytest.approx(abs(pressures["plus_kPa"][k] - pressures["minus_kPa"][k]) / 2)
        assert std == pytest.approx(np.hypot(of_parameters, of_tension)) and std > 5 * of_parameters
        assert mean_mmhg == pytest.approx(mean * MMHG_PER_KPA) and std_mmhg == pytest.approx(std * MMHG_PER_KPA)
        shown = page.tables["answers_pressures"]["rows"][list(rows).index(name)]
        assert len(shown[2].split(".")[-1]) <= 3    # e.g. 0.25 kPa, not 0.0009352
    diagnosis = read_json(page_path.parent.parent / "diagnosis.json", "")
    assert report["answers"]["verdict"] == f"Diagnosis: {diagnosis['verdict']}."
    text = page_path.read_text(encoding="utf-8")
    assert text.index('id="answers"') < text.index('id="images"')
    assert "drainage" in diagnosis["verdict"]       # the hidden effect, said on the page's first screen
    montecarlo = read_json(page_path.parent.parent / "montecarlo.json", "")
    assert montecarlo["poorly_identified"]          # the fat's constants, as in the first paper: said loudly
    assert ('<p class="alert"><strong>Not identifiable: ' + ", ".join(montecarlo["poorly_identified"])) in text


def test_figures_on_the_image_have_axes_in_mm_and_colour_bars_with_units(reported):
    _, _, _, drawn = reported
    for name in ("images.png", "segmentation_mesh.png", "warped_dk.png", "pressure.png", "residuals_before_after.png",
                 "dk_before_after.png"):
        labels = drawn[name]
        image_axes = [k for k, x in enumerate(labels["x"]) if x == "x (mm)"]
        assert image_axes, name
        assert all(labels["y"][k] == "y (mm)" for k in image_axes), name
    assert "hydrostatic pressure (kPa)" in drawn["pressure.png"]["y"] and "(mmHg)" in drawn["pressure.png"]["y"]
    assert "|u_model - u_measured| (mm)" in drawn["residuals_before_after.png"]["y"]
    assert any("radial residual (mm" in label for label in drawn["residuals_before_after.png"]["y"])
    assert "contour distance d_k (mm)" in drawn["dk_before_after.png"]["y"]
    assert drawn["ranking.png"]["x"][0].startswith("-log10 p-value")
    assert drawn["misfit.png"]["y"][0] == "misfit / noise floor"
    assert "kPa" in drawn["intervals.png"]["y"]


def test_report_json_is_strict_json(reported):
    """No NaN or Infinity (which json.dumps writes by default and other readers refuse): what has no value is
    null, shown as "-"."""
    page_path, report, _, _ = reported
    json.loads((page_path.parent / "report.json").read_text(), parse_constant=lambda name: pytest.fail(name))
    numbers = [v for t in _json_tables(report) for row in t["rows"] for v in row if isinstance(v, float)]
    assert numbers and all(np.isfinite(numbers))
