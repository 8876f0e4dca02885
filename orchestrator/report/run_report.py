"""The report of a run: one HTML page, `report/index.html`, rendered from `templates/report.html.j2` (jinja2,
autoescaped), its matplotlib figures beside it, and `report/report.json` holding every number the page shows.

The page answers, at its top, what a user came for: the pressure at each landmark in kPa and mmHg with its
standard deviation over the parameters' intervals, each identified parameter with its interval and whether it
is identifiable, and whether the model fits the measurements or what it lacks. Then the sections, each with
its figures and tables:

- the two slices (Avril et al. Fig. 1) and the segmentation with the mesh and the landmarks (Fig. 2);
- the displacements measured by DIC on I0, when the run measured them;
- the identification: the warped image, the target and the contour distances d_k (Fig. 4, sec. 2.2.5) and the
  fits from each start (Table 1);
- the Monte-Carlo intervals (Table 2) as error bars;
- the hydrostatic pressure map with the landmarks (Fig. 5) and the landmark pressures (Tables 3 and 4);
- the diagnosis: the verdict, the effect ranking as bars against the significance line, the misfit before and
  after the refits against the noise floor, the residual as measured-vs-model arrows and as magnitude and
  radial maps before and after the refit on shared scales, the residual per sector, where a local stiffness
  change would help, and the contour distances before and after.

Every number of a table is shown with the digits its uncertainty allows (`core.digits`, GUM sec. 7.2.6: the
uncertainty to two significant digits, the value to the same place): a parameter to its interval's, a landmark's
pressure to its whole spread (the parameters' and the tension's) in every table, the same number wherever it is
shown; a sector's residual to its standard error. A number that has no uncertainty (a starting value, a misfit, a
test statistic) has SIGNIFICANT significant digits, and each table's header gives the units.

The report is built as a plain dict (`build_report`): sections of paragraphs, alerts, tables (id, header,
rows, the uncertainty that sets each number's digits, the significance of the rest) and figures (file, caption). report.json is that dict; the template only lays it out, so the page and
the JSON cannot disagree. Everything is written into a staging folder that replaces `report/` at the end.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jinja2
import numpy as np

from ..core.digits import (
    PLUS_MINUS,
    decimals,
    interval_uncertainty,
    rounded,
    significant,
)
from ..core.errors import RunFolderError
from ..core.files import read_json, staged_folders
from ..core.run_lock import holds_run_folder
from ..core.tissues import BONE
from ..core.units import MMHG_PER_KPA
from ..diagnose.refit import Refit, refit_model
from ..diagnose.score import ALPHA, EXPLAINED_FACTOR, FLOOR_AGREEMENT
from ..diagnose.verdict import level_rows, model_label
from ..engine.decks import template_dir
from ..fit.identify import pressure_spreads
from ..fit.objectives import leg_rows
from ..imaging.warp import warp_image
from ..measure.measurements import FILES as MEASURE_FILES
from ..model.forward import MeshInterpolator, field_on_pixels
from ..run.discretization import discretization_line
from ..run.setup import load_run
from ..run.stages import floor_sentence, identified_data, sum_only_lines
from . import figures

REPORT_TEMPLATE = "report.html.j2"
REPORT_JSON = "report.json"
SIGNIFICANT = 3              # the significant digits of a table's number that has no uncertainty
# AIC and BIC are read by their differences between models (one of less than 2 tells nothing): shown to the
# place of an uncertainty of 1, their first decimal
INFORMATION_CRITERION_UNCERTAINTY = 1.0


def contour_distances(setup, nodal: np.ndarray):
    """(mismatch result, pixel displacement field) of the model's nodal displacements: the contour distances d_k
    of Avril et al. sec. 2.2.5 between the warped I1's contours and I0's."""
    mismatch = setup.mismatch_objective()
    field = field_on_pixels(mismatch.weights, nodal, setup.case.shape)
    return mismatch.mismatch(field), field


def _table(table_id: str, title: str, header: list[str], rows: list[list], note: str = "",
           uncertainties: list[list] | None = None, significant_digits: int | None = None) -> dict:
    """A table; `uncertainties`, the shape of `rows`, gives the uncertainty that sets each number's digits; a
    number without one has `significant_digits` significant digits (None: `digits.FALLBACK_SIGNIFICANT`, 4, as
    `digits.rounded` shows it)."""
    return {"id": table_id, "title": title, "header": header, "rows": rows, "note": note,
            "uncertainties": uncertainties, "significant": significant_digits}


def _figure(file: str, caption: str) -> dict:
    return {"file": file, "caption": caption}


def _section(section_id: str, title: str, paragraphs=(), tables=(), figures_=(), alerts=()) -> dict:
    return {"id": section_id, "title": title, "paragraphs": list(paragraphs), "alerts": list(alerts),
            "tables": list(tables), "figures": list(figures_)}


def _copy_figure(path: Path, staging: Path) -> bool:
    """Put a figure of the run folder into the report; False when the run has none."""
    if not path.is_file():
        return False
    shutil.copy(path, staging / path.name)
    return True


def _optional_json(path: Path) -> dict | None:
    return read_json(path, "") if path.is_file() else None


def _strict_json(value):
    """The report with numpy scalars as Python numbers and non-finite numbers as None (null in the JSON)."""
    if isinstance(value, dict):
        return {k: _strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict_json(v) for v in value]
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    return value


def format_cell(value, uncertainty: float | None = None, significant_digits: int | None = None) -> str:
    """How a table cell shows a value: a number to the digits its uncertainty allows (`digits`); without a usable
    uncertainty, to `significant_digits` significant digits (None: 4, `digits.rounded`); the rest as text (the
    test of the page reads the numbers back with this precision)."""
    if isinstance(value, bool) or value is None:
        return {True: "yes", False: "no", None: "-"}[value]
    if isinstance(value, float):
        if significant_digits is not None and decimals(uncertainty) is None:
            return significant(value, significant_digits)
        return rounded(value, uncertainty)
    return str(value)


def render_page(report: dict) -> str:
    environment = jinja2.Environment(loader=jinja2.FileSystemLoader(str(template_dir())),
                                     undefined=jinja2.StrictUndefined, autoescape=True)
    environment.filters["cell"] = format_cell
    return environment.get_template(REPORT_TEMPLATE).render(report=report)


@holds_run_folder()
def write_report(run_dir: str | Path, truth: dict | None = None) -> Path:
    """Write RUN_DIR/report/index.html, its PNG figures and report.json from the run's JSON files; returns the
    page's path. identification.json is required; the Monte-Carlo, pressure and diagnosis sections appear when
    their commands have run. truth: the phantom's parameters (name -> value), drawn beside the intervals."""
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    montecarlo = _optional_json(run_dir / "montecarlo.json")
    pressures = _optional_json(run_dir / "pressures.json")
    diagnosis = _optional_json(run_dir / "diagnosis.json")
    final = run_dir / "report"
    with staged_folders(final) as (staging,):
        report = _strict_json(build_report(setup, identification, montecarlo, pressures, diagnosis, truth, staging))
        (staging / REPORT_JSON).write_text(json.dumps(report, indent=1, allow_nan=False), encoding="utf-8")
        (staging / "index.html").write_text(render_page(report), encoding="utf-8")
        for sub in staging.iterdir():
            if sub.is_dir():
                shutil.rmtree(sub, ignore_errors=True)
    return final / "index.html"


def build_report(setup, identification: dict, montecarlo: dict | None, pressures: dict | None,
                 diagnosis: dict | None, truth: dict | None, staging: Path) -> dict:
    """The report as a dict (module text); draws the figures into staging."""
    case = setup.case
    effects = identification.get("effects", [])
    sections = [_images_section(setup, staging), _measurements_section(setup, staging),
                _identification_section(setup, identification, montecarlo, staging)]
    if montecarlo:
        sections.append(_montecarlo_section(identification, montecarlo, truth, staging))
    if montecarlo and pressures:
        sections.append(_pressure_section(setup, montecarlo, pressures, staging))
    if diagnosis:
        sections.append(_diagnosis_section(setup, identification, diagnosis, staging))
        sections.append(_path_section(setup, diagnosis, staging))   # None: the path added nothing
    missing = [command for command, data in (("calfit montecarlo", montecarlo), ("calfit pressures", pressures),
                                             ("calfit diagnose", diagnosis)) if data is None]
    return {
        "title": f"calfit report: {case.name}",
        "case": {"name": case.name, "folder": str(case.folder), "pixel_size_mm": list(case.pixel_size_mm),
                 "tension_N_per_mm": case.tension_N_per_mm},
        "run": {"folder": str(setup.run_dir), "elements": len(setup.mesh.elements),
                "element_type": setup.mesh.element_type, "objective": identification["objective"],
                "method": identification["method"], "effects": effects,
                "engine_runs": identification["engine_runs_total"]},
        "overview": (f"Case {case.folder}; garment tension {case.tension_N_per_mm:g} N/mm; mesh "
                     f"{len(setup.mesh.elements)} {setup.mesh.element_type} elements; objective "
                     f"{identification['objective']}, method {identification['method']}; effects in the model: "
                     f"{', '.join(effects) or 'none (baseline)'}; {identification['engine_runs_total']} engine runs "
                     "in the log."),
        "answers": _answers(identification, montecarlo, pressures, diagnosis),
        "sections": [s for s in sections if s is not None],
        "missing": missing,
    }


def _answers(identification: dict, montecarlo: dict | None, pressures: dict | None, diagnosis: dict | None) -> dict:
    """The top of the page: pressures at the landmarks, parameters with their intervals, the verdict."""
    tables = []
    if pressures:
        parameters, tension, total = pressure_spreads(pressures)
        rows, uncertainties = [], []
        for name, mean, p, t, s in zip(pressures["landmarks"], pressures["mean_kPa"], parameters, tension, total):
            rows.append([name, mean, s, mean * MMHG_PER_KPA, s * MMHG_PER_KPA, p, t])
            uncertainties.append([None, s, s, s * MMHG_PER_KPA, s * MMHG_PER_KPA, p, t])
        tables.append(_table("answers_pressures", "Pressure transmitted by the garment at the landmarks",
                             ["landmark", "mean (kPa)", "std (kPa)", "mean (mmHg)", "std (mmHg)",
                              "std from the parameters (kPa)", "std from the tension (kPa)"], rows,
                             "Hydrostatic pressure -tr(sigma)/3: mean over parameter draws within their intervals; "
                             "std of the parameters' draws (Table 3) and of the garment tension's uncertainty "
                             f"({PLUS_MINUS}{100 * pressures['tension_rel']:g} % as one standard deviation, Table 4), added in "
                             "quadrature. Each number has the digits its uncertainty allows.", uncertainties,
                             significant_digits=SIGNIFICANT))
    names, theta = identification["parameters"], identification["best"]["theta"]
    unit_of = identification.get("unit_of") or ["kPa"] * len(names)
    rows = []
    for k, name in enumerate(names):
        if montecarlo:
            verdict = "NOT identifiable" if name in montecarlo["poorly_identified"] else "identifiable"
            if name in montecarlo.get("on_bound", []):
                verdict += ", on a bound"
            rows.append([name, theta[k], montecarlo["lower"][k], montecarlo["upper"][k], unit_of[k], verdict])
        else:
            rows.append([name, theta[k], None, None, unit_of[k], "no interval yet: calfit montecarlo"])
    spread = _interval_sigmas(montecarlo, len(names))
    tables.append(_table("answers_parameters", "Identified parameters",
                         ["parameter", "identified", "interval low", "interval high", "unit", "verdict"], rows,
                         "Each value to the digits its 95 % interval allows (a quarter of its width as the standard "
                         "uncertainty)." if montecarlo else
                         f"No interval yet: {SIGNIFICANT} significant digits.",
                         uncertainties=[[None, u, u, u, None, None] for u in spread], significant_digits=SIGNIFICANT))
    if diagnosis:
        verdict = f"Diagnosis: {diagnosis['verdict']}."
    elif "misfit_over_floor" in identification:
        verdict = (f"Misfit {identification['misfit_over_floor']:.2f} x its noise floor; run calfit diagnose to see "
                   "where the model fails and what it lacks.")
    else:
        verdict = "Run calfit diagnose to see where the model fails and what it lacks."
    return {"tables": tables, "verdict": verdict}


def _interval_sigmas(montecarlo: dict | None, count: int) -> list[float | None]:
    """Each parameter's standard uncertainty as its interval gives it (`digits.interval_uncertainty`): what sets its
    digits in the tables."""
    if not montecarlo:
        return [None] * count
    return [interval_uncertainty(low, high) for low, high in zip(montecarlo["lower"], montecarlo["upper"])]


def _landmarks(setup) -> dict:
    """The run's landmarks as the pressures read them (case.toml's, or placed from the segmentation), none when
    they cannot be placed."""
    try:
        return setup.landmarks()[0]
    except RunFolderError:
        return {}


def _images_section(setup, staging: Path) -> dict:
    case, px = setup.case, setup.case.pixel_size_mm
    figures.images_figure(staging / "images.png", case.unloaded, setup.loaded_aligned, px)
    figures.segmentation_figure(staging / "segmentation_mesh.png", case.unloaded, setup.labels_unloaded, setup.mesh,
                                px, _landmarks(setup))
    shown = [_figure("images.png", "The two slices: I0 without the garment, I1 with it, aligned on the bones "
                                   "(Avril et al. Fig. 1)."),
             _figure("segmentation_mesh.png", "Segmentation of I0, the finite-element mesh and the landmarks "
                                              "(Fig. 2).")]
    if _copy_figure(setup.run_dir / "compartments.png", staging):
        shown.append(_figure("compartments.png", "Muscle compartments found at the septa of I0."))
    return _section("images", "Images, segmentation and mesh", paragraphs=[f"{line}." for line in setup.setup_lines()],
                    figures_=shown)


def _measurements_section(setup, staging: Path) -> dict | None:
    if not _copy_figure(setup.run_dir / MEASURE_FILES["figure"], staging):
        return None
    summary = _optional_json(setup.run_dir / MEASURE_FILES["summary"]) or {}
    text = (f"{summary['kept']} of {summary['windows']} windows of {summary['window_px']} pixels kept; median "
            f"standard deviation of a displacement {summary['median_sigma_mm']:.4f} mm." if summary else "")
    return _section("measurements", "Displacements measured from the images (DIC)", paragraphs=[text] if text else [],
                    figures_=[_figure(MEASURE_FILES["figure"], "Tissue displacements relative to the bones measured "
                                                               "by digital image correlation, on I0.")])


def _identification_section(setup, identification: dict, montecarlo: dict | None, staging: Path) -> dict:
    case, px = setup.case, setup.case.pixel_size_mm
    names = identification["parameters"]
    unit_of = identification.get("unit_of") or ["kPa"] * len(names)
    model = setup.model_with(identification.get("effects", ()))
    nodal = leg_rows(setup.solve(identification["best"]["theta"], staging / "identified", model).displacement(),
                     len(setup.mesh.nodes))
    result, field = contour_distances(setup, nodal)
    warped = warp_image(setup.loaded_aligned, field, px)
    d_max = float(np.nanmax(result.distance_mm)) if np.isfinite(result.distance_mm).any() else 1.0
    figures.contour_distance_figure(staging / "warped_dk.png", [("contour distances d_k", result.distance_mm)],
                                    case.unloaded, px, d_max, warped=warped)
    fits = identification["fits"]
    spread = _interval_sigmas(montecarlo, len(names))
    table1 = _table("table1", "Table 1: identification from several starting points",
                    [f"start {n} ({u})" for n, u in zip(names, unit_of)] + ["misfit (mm^2)"]
                    + [f"found {n} ({u})" for n, u in zip(names, unit_of)] + ["iterations", "engine runs"],
                    [f["start"] + [f["cost"]] + f["theta"] + [f["iterations"], f["engine_runs"]] for f in fits],
                    ("The values found to the digits their 95 % interval (Table 2) allows; the starts and the misfits, "
                     if montecarlo else "No interval yet: every number ")
                    + f"{SIGNIFICANT} significant digits.",
                    uncertainties=[[None] * len(names) + [None] + spread + [None, None] for _ in fits],
                    significant_digits=SIGNIFICANT)
    paragraphs = [f"Contour mismatch at the identified parameters: M = sum d_k^2 = {result.value_mm2:.1f} mm^2 over "
                  f"{result.contour_pixel_count} contour pixels (RMS {result.rms_mm:.3f} mm)."]
    if "misfit_over_floor" in identification:
        paragraphs.append(f"Displacement misfit {identification['best']['cost']:.4g} mm^2, "
                          f"{identification['misfit_over_floor']:.2f} times its noise floor "
                          f"({identification['noise_floor']:.4g} mm^2).")
        if "floor_calibration" in identification:
            paragraphs.append(floor_sentence(identification["floor_calibration"]))
    check = identification.get("discretization")
    if check:
        paragraphs.append(f"{discretization_line(check)}.")
    alerts = [f"{discretization_line(check)}."] if check and check.get("checked") and not check["adequate"] else []
    return _section("identification", "Identification", paragraphs=paragraphs, tables=[table1], alerts=alerts,
                    figures_=[_figure("warped_dk.png", "I1 warped by the identified model, the target I0, and the "
                                                       "contour distances d_k between their tissue boundaries "
                                                       "(Avril et al. Fig. 4).")])


def _montecarlo_section(identification: dict, montecarlo: dict, truth: dict | None, staging: Path) -> dict:
    names, theta = identification["parameters"], identification["best"]["theta"]
    unit_of = identification.get("unit_of") or ["kPa"] * len(names)
    poorly = montecarlo["poorly_identified"]
    noise = montecarlo.get("method") == "noise"
    rows = [["lower bound"] + montecarlo["lower"], ["upper bound"] + montecarlo["upper"],
            ["central value"] + montecarlo["central"], ["identified"] + theta]
    if truth:
        rows.append(["truth (phantom)"] + [truth.get(n) for n in names])
    if noise:
        rows.append(["half width (%)"] + [100 * w for w in montecarlo["relative_half_width"]])
    rows.append(["identification"] + [("NOT identifiable" if noise else "POOR") if n in poorly else "good"
                                      for n in names])
    alerts = []
    if noise:
        title = (f"Table 2: parameter intervals ({100 * montecarlo['confidence']:.0f} % Monte-Carlo over the "
                 f"measurement noise, {montecarlo['draws'] - montecarlo['failed']} refitted draws)")
        if poorly:
            alerts.append(f"Not identifiable: {', '.join(poorly)} (95 % interval wider than {PLUS_MINUS}10 % of the "
                          "value).")
        if montecarlo["on_bound"]:
            alerts.append(f"On a bound of the search box: {', '.join(montecarlo['on_bound'])}.")
        alerts += sum_only_lines(montecarlo)
        if montecarlo["inflation"] > 1.0:
            alerts.append(f"Noise variance inflated x{montecarlo['inflation']:.2f}: the misfit is above its floor.")
    else:
        title = (f"Table 2: parameter intervals (Monte-Carlo, misfit below {montecarlo['threshold']:.4g}, "
                 f"{montecarlo['accepted']} of {montecarlo['draws']} draws kept, {montecarlo['failed']} failed)")
        if poorly:
            alerts.append(f"Poorly identified: {', '.join(poorly)} (their accepted values span more than a factor "
                          "1.5 or reach the edge of the explored range); the pressures carry that uncertainty.")
    paragraphs = [] if poorly else ["Every parameter is identifiable."]
    figures.intervals_figure(staging / "intervals.png", names, unit_of, theta, montecarlo["lower"],
                             montecarlo["upper"], poorly, title, truth)
    spread = _interval_sigmas(montecarlo, len(names))
    uncertainties = [[None] + (list(row[1:]) if row[0] == "half width (%)" else
                               [u if isinstance(v, float) else None for v, u in zip(row[1:], spread)])
                     for row in rows]
    table2 = _table("table2", title, [""] + [f"{n} ({u})" for n, u in zip(names, unit_of)], rows,
                    "Each column to the digits its interval allows (a quarter of its width as the standard "
                    "uncertainty); the half width, two significant digits.", uncertainties=uncertainties,
                    significant_digits=SIGNIFICANT)
    return _section("montecarlo", "Uncertainty of the parameters", paragraphs=paragraphs, alerts=alerts,
                    tables=[table2], figures_=[_figure("intervals.png", "Parameter intervals as error bars, "
                                                                        "each in its unit.")])


def _pressure_section(setup, montecarlo: dict, pressures: dict, staging: Path) -> dict:
    case, px = setup.case, setup.case.pixel_size_mm
    results = setup.solve(montecarlo["central"], staging / "central")
    weights = MeshInterpolator(setup.mesh).pixel_weights(case.shape, px)
    pressure = leg_rows(results.point_field("pressure"), len(setup.mesh.nodes))
    pressure_kPa = (weights @ pressure).reshape(case.shape) * 1e3   # engine stresses: MPa
    soft = (setup.labels_unloaded > 0) & (setup.labels_unloaded != BONE)
    pressure_kPa[~soft] = np.nan
    parameters, _, total = pressure_spreads(pressures)
    values = {name: (pressures["mean_kPa"][k], total[k]) for k, name in enumerate(pressures["landmarks"])}
    mmhg = [u * MMHG_PER_KPA for u in total]
    figures.pressure_figure(staging / "pressure.png", pressure_kPa, px,
                            {name: _landmarks(setup)[name] for name in pressures["landmarks"]}, values)
    # a landmark's pressure, in every table, to the digits of its whole spread (the parameters' and the tension's,
    # the top of the page): the same number wherever it is shown; the spreads themselves to two significant digits
    table3 = _table("table3", f"Table 3: landmark pressures over {pressures['draws']} draws in the intervals "
                              f"({pressures['failed']} failed)",
                    ["landmark", "mean (kPa)", "mean (mmHg)", "std (kPa)", "std (mmHg)", "CV (%)"],
                    [[n, m, m * MMHG_PER_KPA, s, s * MMHG_PER_KPA, c] for n, m, s, c in
                     zip(pressures["landmarks"], pressures["mean_kPa"], parameters, pressures["cv_percent"])],
                    "std and CV: the spread of the pressure over the parameters' draws, two significant digits. The "
                    "means to the digits of the pressure's whole standard deviation, the parameters' and the garment "
                    "tension's (the top of the page).",
                    uncertainties=[[None, u, v, s, s * MMHG_PER_KPA, c] for s, c, u, v in
                                   zip(parameters, pressures["cv_percent"], total, mmhg)],
                    significant_digits=SIGNIFICANT)
    rel = f"{100 * pressures['tension_rel']:g} %"
    table4 = _table("table4", f"Table 4: garment tension {PLUS_MINUS}{rel}",
                    ["landmark", "pressure (kPa)", f"T +{rel} (kPa)", "deviation (%)", f"T -{rel} (kPa)",
                     "deviation (%)"],
                    [[n, b, p, dp, m, dm] for n, b, p, dp, m, dm in
                     zip(pressures["landmarks"], pressures["central_kPa"], pressures["plus_kPa"],
                         pressures["plus_deviation_percent"], pressures["minus_kPa"],
                         pressures["minus_deviation_percent"])],
                    "The pressures at the central parameters, to the digits of the landmark's whole standard "
                    f"deviation (as in Table 3); the deviations from the first column, {SIGNIFICANT} significant "
                    "digits.",
                    uncertainties=[[None, u, u, None, u, None] for u in total], significant_digits=SIGNIFICANT)
    tables, shown = [table3, table4], [_figure("pressure.png", "Hydrostatic pressure -tr(sigma)/3 at the central "
                                                                "parameters (Avril et al. Fig. 5), the landmarks named "
                                                                f"with their mean {PLUS_MINUS} std (the parameters' "
                                                                "and the tension's).")]
    if pressures.get("band"):
        tables_, figure_ = _band_parts(setup, pressures["band"], staging)
        tables += tables_
        shown.append(figure_)
    return _section("pressures", "Pressure transmitted to the tissues", tables=tables, figures_=shown)


def _band_parts(setup, band: dict, staging: Path) -> tuple[list[dict], dict]:
    """The explicit garment band on the leg at the central parameters: a table and a figure (`garment_state`)."""
    frame = setup.frame()
    figures.band_figure(staging / "band.png", band, frame.direction)
    pressure, tension, share = band["contact_pressure_kPa"], band["hoop_tension_N_per_mm"], band["skin_share"]
    rows = [["contact pressure, mean over the skin (kPa)", pressure["mean"]],
            ["contact pressure, largest (kPa)", pressure["max"]],
            ["band hoop force, mean (N/mm)", tension["mean"]],
            ["band hoop force, smallest to largest (N/mm)",
             f"{significant(tension['min'], SIGNIFICANT)} to {significant(tension['max'], SIGNIFICANT)}"],
            ["skin in contact, sticking (%)", 100 * share["sticking"]],
            ["skin in contact, slipping (%)", 100 * share["slipping"]],
            ["skin under a bridge (%)", 100 * share["open"]],
            ["largest slip since the first touch (mm)", band["max_slip_mm"] if band["friction_mu"] > 0 else
             "not tracked (frictionless)"]]
    rows += [[f"bridge, {b['direction']} ({b['start_deg']:.0f}-{b['end_deg']:.0f} deg)",
              f"{b['length_mm']:.1f} mm of skin, the band up to {b['max_gap_mm']:.2f} mm off it"]
             for b in band["bridges"]]
    table = _table("band", f"The garment band on the leg (friction mu = {band['friction_mu']:g}), at the central "
                           "parameters", ["", "value"], rows, f"{SIGNIFICANT} significant digits.",
                   significant_digits=SIGNIFICANT)
    caption = ("The explicit garment band on the leg at the central parameters: its contact pressure around the "
               "leg, each skin node coloured by its contact status (open where the band bridges a hollow of the "
               "skin, shaded), the band's hoop force" + (", the friction shear and the skin's slip over the band "
                                                         "since it first touched it" if band["friction_mu"] > 0 else "")
               + ".")
    return [table], _figure("band.png", caption)


def _diagnosis_section(setup, identification: dict, diagnosis: dict, staging: Path) -> dict:
    case, px = setup.case, setup.case.pixel_size_mm
    floor = diagnosis["noise_floor"]
    fits = [diagnosis["before"]] + diagnosis["refits"]
    labels = ["identified model"] + [model_label(f["effects"]) for f in diagnosis["refits"]]
    # what the figures and tables compare: the identified model alone when no refit ran
    compared = ("before and after the refit" + ("s" if len(fits) > 2 else "") if len(fits) > 1
                else "of the identified model")
    alone = "" if len(fits) > 1 else " No refit ran."
    maps, maps_after = diagnosis["maps"], diagnosis.get("maps_after", [])
    if diagnosis.get("level_maps"):   # several socks: the first level's points here, every level's own map below
        maps, maps_after = diagnosis["level_maps"][0], [m[0] for m in diagnosis.get("level_maps_after", [])]
    positions = np.asarray(maps["positions_mm"], float)
    residuals = [np.asarray(maps["residual_mm"], float)] + [np.asarray(m["residual_mm"], float) for m in maps_after]
    measured = _measured_displacements(setup, identification, len(positions))
    figures.residual_figure(staging / "residuals_before_after.png", case.unloaded, setup.labels_unloaded > 0, px,
                            positions, measured, list(zip(labels, residuals)), maps["centre_mm"])
    figures.ranking_figure(staging / "ranking.png", diagnosis["ranking"], ALPHA)
    figures.misfit_figure(staging / "misfit.png", [(label, f["misfit_over_floor"]) for label, f in zip(labels, fits)],
                          EXPLAINED_FACTOR, FLOOR_AGREEMENT)

    mismatch_values, distances = [], []
    identified = setup.model_with(diagnosis["before"]["effects"])
    for k, fit in enumerate(fits):
        # as the refit built it: a garment effect (friction, bridging) switches a Laplace-law model to the band
        model = refit_model(identified, fit["effects"][len(diagnosis["before"]["effects"]):])
        nodal = leg_rows(setup.solve(fit["theta"], staging / f"diagnosis-{k}", model).displacement(), len(setup.mesh.nodes))
        result, _ = contour_distances(setup, nodal)
        mismatch_values.append(result.value_mm2)
        distances.append(result.distance_mm)
    d_max = max(float(np.nanmax(d)) if np.isfinite(d).any() else 0.0 for d in distances) or 1.0
    figures.contour_distance_figure(staging / "dk_before_after.png", list(zip(labels, distances)), case.unloaded, px,
                                    d_max)

    ranking = _table("ranking", "Effect ranking (score test against the identified model)",
                     ["rank", "effect", "parameters", "statistic", "p-value", "predicted misfit / floor",
                      "|g_perp| / |g|", "significant"],
                     [[k, s["effect"], ", ".join(s["parameters"]), s["statistic"], s["p_value"],
                       s["predicted_misfit"] / floor, ", ".join(f"{v:.2f}" for v in s["orthogonal_fraction"]),
                       s["significant"]] for k, s in enumerate(diagnosis["ranking"], 1)],
                     f"{SIGNIFICANT} significant digits; |g_perp| / |g|, two decimals.", significant_digits=SIGNIFICANT)
    comparison = _table("comparison", "Misfit " + compared + ("" if len(fits) > 1 else " (no refit ran)"),
                        ["model", "k", "misfit (mm^2)", "misfit / floor", "misfit / floor, the skin's uncertainty at "
                         "this fit", "AIC", "BIC", "M (mm^2)", "parameters [95 % interval, linearized at the fit]"],
                        [[label, len(f["parameters"]), f["misfit"], f["misfit_over_floor"],
                          (f.get("own_floor") or {}).get("misfit_over_floor"), f["aic"], f["bic"], m,
                          parameter_text(f)]
                         for label, f, m in zip(labels, fits, mismatch_values)],
                        f"AIC and BIC to their first decimal (a difference of less than 2 tells the models apart no "
                        f"more than chance); the other numbers {SIGNIFICANT} significant digits; each parameter to the "
                        "digits its interval allows.",
                        uncertainties=[[None] * 5 + [INFORMATION_CRITERION_UNCERTAINTY] * 2 + [None, None] for _ in fits],
                        significant_digits=SIGNIFICANT)
    tables = [ranking, comparison]
    if diagnosis.get("levels"):
        before, after = Refit(**diagnosis["before"]), [Refit(**fit) for fit in diagnosis["refits"]]
        tables.append(_table("levels", "Misfit over each garment level's own noise floor, before and after the refit, "
                                       "and where that level's residual is largest",
                             ["level", "image", "tension (N/mm)"] + labels + ["largest share of the residual"],
                             level_rows(diagnosis["levels"], before, after), f"{SIGNIFICANT} significant digits.",
                             significant_digits=SIGNIFICANT))
    moved = (diagnosis.get("final") or {}).get("landmark_pressures") or {}
    if "final_kPa" in moved:
        # what the missing physics changes where a garment designer reads the pressure
        final = model_label(diagnosis["final"]["effects"])
        tables.append(_table("landmark_change", f"Pressure at the landmarks under the identified model and under the "
                                                f"diagnosis' final model ({final})",
                             ["landmark", "identified (kPa)", "final (kPa)", "identified (mmHg)", "final (mmHg)",
                              "change (%)"],
                             [[name, before, after, before * MMHG_PER_KPA, after * MMHG_PER_KPA,
                               100 * (after - before) / abs(before) if before else None]
                              for name, before, after in zip(moved["landmarks"], moved["baseline_kPa"],
                                                             moved["final_kPa"])],
                             "Each model at its own fitted parameters, the case's garment; "
                             + ("the landmarks placed from I0's segmentation (case.toml names none); "
                                if moved["landmarks_from"] == "segmentation" else "")
                             + f"{SIGNIFICANT} significant digits (the spread over the intervals is in Table 3).",
                             significant_digits=SIGNIFICANT))
    names = maps.get("sector_names") or [f"{c:.0f} deg" for c in maps["sector_centre_deg"]]
    sectors = _table("sectors", "Residual per sector around the leg (angles counter-clockwise on the image from its "
                                "+x axis, 90 deg at the top; anterior towards the tibia, lateral towards the fibula)",
                     ["sector", "RMS residual (mm)", "mean radial (mm, + outwards)", "measurements"],
                     [[name, rms, radial, count] for name, rms, radial, count in
                      zip(names, maps["sector_rms_mm"], maps["sector_radial_mm"], maps["sector_count"])],
                     "Each to the digits of its standard error over the sector's measurements: RMS / sqrt(2 n) for "
                     "the RMS, RMS / sqrt(n) for the mean.",
                     uncertainties=[sector_uncertainties(rms, count)
                                    for rms, count in zip(maps["sector_rms_mm"], maps["sector_count"])],
                     significant_digits=SIGNIFICANT)
    paragraphs = [
        f"Misfit {diagnosis['misfit']:.4g} mm^2 against a noise floor of {floor:.4g} mm^2 (chi^2 = "
        f"{diagnosis['chi2']:.1f} over {diagnosis['n_residuals']} residuals, lack-of-fit p = "
        f"{diagnosis['lack_of_fit_p']:.2g}); neighbour correlation of the residual "
        f"{diagnosis['neighbour_correlation']:.2f}, design effect {diagnosis['design_effect']:.2f}; sensitivities "
        f"from {diagnosis['sensitivities_from']}, {diagnosis['engine_runs']} engine runs.",
        "RMS residual per tissue: " + ", ".join(f"{k} {v:.3f} mm" for k, v in maps["per_region_rms_mm"].items()) + ".",
    ]
    if maps.get("worst_region"):
        paragraphs.append(f"Largest share of the squared residual: the {maps['worst_region']} "
                          f"({100 * maps['worst_region_share']:.0f} %, RMS {maps['worst_region_rms_mm']:.3f} mm).")
    shown = [_figure("ranking.png", "Catalog effects ranked by the score test; the dashed line is the significance "
                                    "level."),
             _figure("misfit.png", f"Misfit over its noise floor {compared}.{alone}"),
             _figure("residuals_before_after.png", "Measured and model displacements (top), the residual's "
                                                   f"magnitude and its radial component (+ outwards) {compared}"
                                                   + (", on shared scales" if len(fits) > 1 else "")
                                                   + f" (mm).{alone}")]
    if _copy_figure(setup.run_dir / "diagnosis.png", staging):
        patch = (diagnosis.get("local") or {}).get("patch")
        shown.append(_figure("diagnosis.png", "Residual of the identified model by sector"
                                              + (f"; shaded: the place of a local stiffness change, {patch['place']}"
                                                 if patch else "") + "."))
    for level in diagnosis.get("levels", []):
        if _copy_figure(setup.run_dir / f"diagnosis-level-{level['level']}.png", staging):
            shown.append(_figure(f"diagnosis-level-{level['level']}.png",
                                 f"Residual of the identified model at garment level {level['level']} "
                                 f"({level['image']}, {level['tension_N_per_mm']:g} N/mm), by sector."))
    shown.append(_figure("dk_before_after.png", f"Contour distances d_k {compared} (mm).{alone}"))
    verdict = [f"{diagnosis['verdict']}."]
    lacking = diagnosis["lack_of_fit_p"] < ALPHA     # the identified model misses something: say it loudly
    return _section("diagnosis", "Diagnosis: where the model fails and which effect is missing",
                    paragraphs=([] if lacking else verdict) + paragraphs, alerts=verdict if lacking else [],
                    tables=tables + [sectors], figures_=shown)


def _path_section(setup, diagnosis: dict, staging: Path) -> dict | None:
    """The stepwise diagnosis (diagnosis.json "path", "final"): the error falling as effects are added one at a time,
    each step's model with its parameters, and the residual of each step side by side; None when the path has
    no step beyond the identified model."""
    path, final = diagnosis.get("path") or [], diagnosis.get("final") or {}
    if len(path) < 2:
        return None

    def parameters(entry: dict) -> str:
        shown = []
        for name, p in entry["parameters"].items():
            low, high = p.get("lower95"), p.get("upper95")
            spread = interval_uncertainty(low, high) if low is not None and high is not None else None
            shown.append(f"{name} = {rounded(p['value'], spread)}" + (
                f" [{rounded(low, spread)}, {rounded(high, spread)}]" if spread is not None else " [unbounded]"))
        return ", ".join(shown)

    change = {"identified": "identified model", "added": "+ {}", "removed": "- {}"}
    steps = _table("path", "The path: one effect added (+) or removed (-) at a time",
                   ["step", "change", "effects in the model", "misfit / floor", "BIC", "engine runs", "wall time (s)",
                    "parameters [95 % interval, linearized at the fit]"],
                   [[e["step"], change[e["action"]].format(e["effect"]), ", ".join(e["effects"]) or "none",
                     e["misfit_over_floor"], e["bic"], e["engine_runs"], e["wall_time_s"], parameters(e)]
                    for e in path],
                   "Misfit over the floor with the skin's uncertainty estimated again at each fit when the images "
                   f"gave it; BIC to its first decimal; the other numbers {SIGNIFICANT} significant digits.",
                   uncertainties=[[None] * 4 + [INFORMATION_CRITERION_UNCERTAINTY] + [None] * 3 for _ in path],
                   significant_digits=SIGNIFICANT)
    tables = [steps]
    if final.get("alternatives"):
        tables.append(_table("alternatives", "Models the data cannot tell from the path's (BIC within 2)",
                             ["effects", "instead of", "at step", "misfit / floor", "BIC"],
                             [[", ".join(a["effects"]), a["instead_of"], a["step"], a["misfit_over_floor"], a["bic"]]
                              for a in final["alternatives"]], "BIC to its first decimal.",
                             uncertainties=[[None] * 4 + [INFORMATION_CRITERION_UNCERTAINTY]
                                            for _ in final["alternatives"]], significant_digits=SIGNIFICANT))
    shown = []
    if _copy_figure(setup.run_dir / "diagnosis-path.png", staging):
        shown.append(_figure("diagnosis-path.png", "Misfit over the noise floor at each step of the path (log scale; "
                                                   "grey: the refits tried at that step; the floor and the error "
                                                   "model's agreement marked)."))
    if _copy_figure(setup.run_dir / "diagnosis-path-maps.png", staging):
        shown.append(_figure("diagnosis-path-maps.png", "Residual of each step's model, side by side."))
    summary = " -> ".join(f"{e['misfit_over_floor']:.2f}" for e in path) + " x the floor"
    section = _section("diagnosis-path", "Diagnosis, step by step: the error falling",
                       paragraphs=[f"{diagnosis['verdict']}.",
                                   f"Final model: {', '.join(final.get('effects', [])) or 'the identified model'}, "
                                   f"{final.get('misfit_over_floor', float('nan')):.2f} x the floor, "
                                   + ("explained" if final.get("explained") else "not explained") + "; "
                                   "calfit identify CASE --out RUN --effects final fits it, and the Monte-Carlo, the "
                                   "pressures and this report then use it."],
                       tables=tables, figures_=shown)
    section["summary"] = summary
    return section


def sector_uncertainties(rms: float | None, count: int) -> list:
    """What sets the digits of a sector's row (sector, RMS, mean radial, count): the standard errors of an RMS and
    of a mean over `count` residuals that scatter by about their RMS (None: no measurement in the sector)."""
    if rms is None or not count or not np.isfinite(rms):
        return [None] * 4
    return [None, rms / np.sqrt(2.0 * count), rms / np.sqrt(count), None]


def parameter_text(fit: dict) -> str:
    """A fit's parameters (diagnosis.json's "before" or a refit) as the comparison table shows them: name = value
    [95 % interval], each to the digits its interval allows, marked where the interval is wider than identify's
    identifiability rule; the value with SIGNIFICANT digits where the fit has no interval."""
    intervals = fit.get("intervals")
    if not intervals:
        return ", ".join(f"{n} = {significant(v, SIGNIFICANT)}" for n, v in zip(fit["parameters"], fit["theta"]))
    parts = []
    for name, value, low, high, ok in zip(fit["parameters"], fit["theta"], intervals["lower"], intervals["upper"],
                                          intervals["identifiable"]):
        if low is not None and high is not None:
            u = interval_uncertainty(low, high)
        elif low is not None or high is not None:   # one side the data do not see: the half the other gives
            u = abs(value - (high if low is None else low)) / 2.0
        else:
            u = None
        shown = (lambda v: rounded(v, u)) if decimals(u) is not None else (lambda v: significant(v, SIGNIFICANT))
        lower = "below unbounded" if low is None else shown(low)
        upper = "above unbounded" if high is None else shown(high)
        parts.append(f"{name} = {shown(value)} [{lower}, {upper}]" + ("" if ok else " not identifiable"))
    return ", ".join(parts)


def _measured_displacements(setup, identification: dict, count: int) -> np.ndarray | None:
    """The measured displacements (mm, one row per point or window) the residual maps were computed against,
    when they can be read back in the same order."""
    try:
        measured = setup.measurements(identified_data(identification))
    except (OSError, ValueError, RuntimeError):
        return None
    displacement = np.asarray(measured.displacement_mm, float).reshape(-1, 2)
    return displacement if len(displacement) == count else None
