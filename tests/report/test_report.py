"""The report of a whole run (identify, Monte-Carlo, pressures, diagnose) on a phantom with a hidden fluid loss
of the muscle: the page is what the template makes of report.json (every table of the JSON on the page, cell
by cell as the page prints it, every figure present and a PNG), the user's questions are answered at the top
(pressure at each landmark in kPa and mmHg with its spread, the diagnosis' verdict), every figure drawn
on the image has its axes in mm and colour bars that say their unit, every number of a table has the digits its
uncertainty allows (or the significance its table states) under a header with its unit, the page and the figures
write "±", the misfit figure says what it compares and its legend hides none of its lines, and the DIC figure's
scale arrow lies clear of its title."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from types import SimpleNamespace

import matplotlib.text
import numpy as np
import pytest
from conftest import copy_run
from matplotlib.quiver import QuiverKey
from matplotlib.transforms import Bbox

from orchestrator.core.digits import decimals
from orchestrator.core.units import MMHG_PER_KPA
from orchestrator.fit.identify import pressure_spreads
from orchestrator.measure.figure import dic_vectors_plot
from orchestrator.report import figures
from orchestrator.report.run_report import SIGNIFICANT, format_cell, write_report
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
        drawn[path.name] = {"x": [ax.get_xlabel() for ax in axes], "y": [ax.get_ylabel() for ax in axes],
                            "titles": [ax.get_title() for ax in figure.axes],
                            "texts": [t.get_text() for t in figure.findobj(matplotlib.text.Text)]}
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
        assert shown["rows"] == [[format_cell(v, u, table["significant"]) for v, u in zip(row, us)]
                                 for row, us in zip(table["rows"], uncertainties)], table["id"]
        for row, values, us in zip(shown["rows"], table["rows"], uncertainties):
            for text, value, u in zip(row, values, us):
                if isinstance(value, float):   # the JSON's number, to its significance or to its uncertainty's place
                    place = decimals(u)
                    tolerance = (dict(rel=0.5 * 10.0 ** (1 - table["significant"]), abs=1e-300) if place is None
                                 else dict(abs=0.5 * 10.0 ** -place + 1e-12))
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


def _decimals_shown(text: str) -> int:
    return len(text.split(".")[1]) if "." in text else 0


def _significant_shown(text: str) -> int:
    """Significant digits of a number as printed (trailing zeros count: 3.60 has three)."""
    mantissa = text.lstrip("-").split("e")[0]
    digits = mantissa.replace(".", "").lstrip("0")
    return len(digits) if digits else len(mantissa.replace(".", ""))


def test_every_number_of_a_table_carries_the_digits_its_uncertainty_allows(reported):
    """GUM 7.2.6: a number with an uncertainty to the place of the uncertainty's second significant digit; one
    without, to the significance its table states (3); no table left to the 4-digit default."""
    _, report, page, _ = reported
    checked = 0
    for table in _json_tables(report):
        assert table["significant"] == SIGNIFICANT, table["id"]
        uncertainties = table["uncertainties"] or [[None] * len(row) for row in table["rows"]]
        for row, values, us in zip(page.tables[table["id"]]["rows"], table["rows"], uncertainties):
            for text, value, u in zip(row, values, us):
                if not isinstance(value, float):
                    continue
                place = decimals(u)
                if place is None:
                    assert _significant_shown(text) == SIGNIFICANT, (table["id"], text, value)
                else:
                    assert _decimals_shown(text) == max(place, 0), (table["id"], text, value, u)
                checked += 1
    assert checked > 100


def test_a_landmark_s_pressure_reads_the_same_in_every_table_to_its_whole_spread(reported):
    """Table 3's 2.5397 and Table 4's mix of 4 to 6 significant digits: each pressure now to the digits of its
    whole standard deviation (the parameters' and the tension's, 0.2 kPa on this phantom: 2 decimals), the
    standard deviations with two significant digits, Table 4's deviations with three."""
    page_path, report, page, _ = reported
    pressures = read_json(page_path.parent.parent / "pressures.json", "")
    _, _, total = pressure_spreads(pressures)
    answers = {row[0]: row for row in page.tables["answers_pressures"]["rows"]}
    table3 = {row[0]: row for row in page.tables["table3"]["rows"]}
    table4 = {row[0]: row for row in page.tables["table4"]["rows"]}
    for k, name in enumerate(pressures["landmarks"]):
        place = decimals(total[k])
        assert place == 2
        assert table3[name][1] == answers[name][1]           # mean (kPa): the top of the page's number
        assert table3[name][2] == answers[name][3]           # mean (mmHg)
        for text in (table3[name][1], table4[name][1], table4[name][2], table4[name][4]):
            assert _decimals_shown(text) == place, (name, text)
        assert all(_significant_shown(text) == 2 for text in table3[name][3:6])          # std, std, CV
        assert all(_significant_shown(table4[name][c]) == SIGNIFICANT for c in (3, 5))    # the deviations (%)
    assert all(re.search(r"\((kPa|mmHg|%)\)$", header) for header in page.tables["table3"]["header"][1:])


def test_the_sector_table_shows_each_residual_to_its_standard_error(reported):
    """-0.0003414 mm was printed for a mean over 25 residuals of 0.01 mm: each mean radial residual now to the
    digits of RMS / sqrt(n), each RMS to those of RMS / sqrt(2 n)."""
    _, report, page, _ = reported
    table = next(t for t in _json_tables(report) if t["id"] == "sectors")
    for (name, rms, radial, count), shown in zip(table["rows"], page.tables["sectors"]["rows"]):
        if not count:
            continue
        assert _decimals_shown(shown[1]) == decimals(rms / np.sqrt(2 * count))
        assert _decimals_shown(shown[2]) == decimals(rms / np.sqrt(count))


def test_table1_says_the_units_and_the_digits_of_its_parameters(reported):
    _, report, page, _ = reported
    header = page.tables["table1"]["header"]
    assert [h for h in header if not re.search(r"\([^()]+\)$", h)] == ["iterations", "engine runs"]   # units
    assert "misfit (mm^2)" in header and all(h.endswith("(kPa)") for h in header if h.startswith(("start C", "found C")))
    montecarlo = read_json(reported[0].parent.parent / "montecarlo.json", "")
    spread = [(high - low) / 4 for low, high in zip(montecarlo["lower"], montecarlo["upper"])]
    found = [k for k, h in enumerate(header) if h.startswith("found ")]
    for row in page.tables["table1"]["rows"]:
        for k, u in zip(found, spread):
            assert _decimals_shown(row[k]) == max(decimals(u), 0), (header[k], row[k])


def test_the_page_and_its_figures_write_plus_minus_as_one_sign(reported):
    page_path, _, _, drawn = reported
    for text in (page_path.read_text(encoding="utf-8"), (page_path.parent / "report.json").read_text(encoding="utf-8")):
        assert "+-" not in text and "+/-" not in text
    assert "\u00b1" in page_path.read_text(encoding="utf-8")
    for name, figure in drawn.items():
        assert not any("+-" in text for text in figure["texts"]), name
    assert sum("\u00b1" in text for text in drawn["pressure.png"]["texts"]) >= 5    # each landmark's mean ± std


def test_the_misfit_figure_of_a_run_with_refits_says_so(reported):
    page_path, report, _, drawn = reported
    refits = read_json(page_path.parent.parent / "diagnosis.json", "")["refits"]
    assert refits
    title = "misfit before and after the refit" + ("s" if len(refits) > 1 else "")
    assert drawn["misfit.png"]["titles"] == [title]
    comparison = next(t for t in _json_tables(report) if t["id"] == "comparison")
    assert comparison["title"] == title.capitalize()
    assert [len(row) for row in comparison["rows"]] == [9] * (1 + len(refits))


def _bbox_of(artist, renderer) -> Bbox:
    return artist.get_window_extent(renderer)


@pytest.mark.parametrize("ratios, title", [
    ([0.98], "misfit of the identified model (no refit ran)"),
    ([2.6, 1.02], "misfit before and after the refit"),
    ([60.0, 1.02, 30.0], "misfit before and after the refits"),     # a log scale
])
def test_the_misfit_figure_says_what_it_compares_and_its_legend_hides_no_line(ratios, title):
    labels = ["identified model"] + [f"+ effect {k}" for k in range(1, len(ratios))]
    figure = figures.misfit_plot(list(zip(labels, ratios)), 1.5, 1.25)
    try:
        figure.canvas.draw()
        renderer = figure.canvas.get_renderer()
        ax = figure.axes[0]
        assert ax.get_title() == title
        legend = _bbox_of(ax.get_legend(), renderer)
        lines = [line for line in ax.get_lines() if line.get_label() in
                 ("noise floor", "explained (1.5x the floor)", "at the floor within the error model's agreement (1.25x)")]
        assert len(lines) == 3
        ticks = ax.get_xticklabels()
        assert [t.get_text() for t in ticks] == [f"{label}\n{r:.2f}x" for label, r in zip(labels, ratios)]
        texts = [t for t in figure.findobj(matplotlib.text.Text) if t.get_text() and t.get_visible()]
        for line in lines:                   # the 1.5x line, the floor, the agreement: no legend or text over them
            assert not legend.overlaps(_bbox_of(line, renderer)), line.get_label()
            for text in texts:               # the bars' ratios (0.98x under the floor) among them
                assert not _bbox_of(text, renderer).overlaps(_bbox_of(line, renderer)), (text.get_text(), line.get_label())
        low, high = ax.get_ylim()
        assert low < min(ratios) and high > 1.5       # every line and every bar inside the axes
    finally:
        figures.plt.close(figure)


def _key_bbox(key: QuiverKey, renderer) -> Bbox:
    """The scale arrow with its label, in display pixels."""
    vector = key.vector
    anchor = vector.get_offset_transform().transform(vector.get_offsets())[0]
    corners = vector.get_transform().transform(vector.get_paths()[0].vertices) + anchor
    return Bbox.union([key.text.get_window_extent(renderer), Bbox([corners.min(axis=0), corners.max(axis=0)])])


def test_the_dic_figure_s_scale_arrow_lies_inside_the_axes_clear_of_its_title_and_legend():
    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[0:128, 0:128]
    image = 100.0 * ((cols - 64) ** 2 + (rows - 64) ** 2 < 50 ** 2) + rng.normal(0.0, 5.0, (128, 128))
    grid = np.arange(16, 120, 8) * 0.5
    position = np.column_stack([a.ravel() for a in np.meshgrid(grid, grid)])
    kept = np.ones(len(position), bool)
    kept[:3] = False
    table = SimpleNamespace(kept=kept, position_mm=position, displacement_mm=0.02 * (position - 32.0))
    figure = dic_vectors_plot(image, (0.5, 0.5), table, {"window_px": 16, "step_px": 8})
    try:
        figure.canvas.draw()
        renderer = figure.canvas.get_renderer()
        ax = figure.axes[0]
        keys = [child for child in ax.get_children() if isinstance(child, QuiverKey)]
        assert len(keys) == 1 and keys[0].text.get_text().endswith(" mm")
        key = _key_bbox(keys[0], renderer)
        assert not key.overlaps(_bbox_of(ax.title, renderer))
        assert not key.overlaps(_bbox_of(ax.get_legend(), renderer))
        axes = _bbox_of(ax, renderer)
        assert axes.x0 <= key.x0 and key.x1 <= axes.x1 and axes.y0 <= key.y0 and key.y1 <= axes.y1
        assert ax.get_xlabel() == "x (mm)" and ax.get_ylabel() == "y (mm)"
        assert any(a.get_ylabel() == "displacement relative to the bones (mm)" for a in figure.axes)
    finally:
        figures.plt.close(figure)
