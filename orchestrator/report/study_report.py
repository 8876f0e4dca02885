"""The report of a study: DIR/report/index.html, its figures and report.json, from the study's rows.

It is laid out by the run report's page (`report.render_page`, templates/report.html.j2) and answers, at its top:
- for a volume (slices at several heights), the pressure at the compression standard's named heights (B at the
  ankle, B1, C at the calf's widest, D below the knee: `[study] compression_heights_mm`), interpolated linearly
  between the two studied slices around each height, with its spread;
- how many cases fit their model, and which do not.
Then:
- profiles along the leg (a volume): each parameter with its 95 % Monte-Carlo interval as a band, the garment's
  interface pressure (Laplace's law, 2 pi T / perimeter) and the landmark pressures with ± 2 standard deviations,
  the misfit over the noise floor, the named heights marked;
- the distributions over the cases: each parameter's value and interval case by case, and a table of medians
  and ranges;
- the cases whose model fails: a case that failed to run, whose diagnosis finds a lack of fit (p < alpha), or a
  slice of a volume whose skin moves by more than a pixel between the volume's slices (`volume_study`), with why;
- the whole table (DIR/study.csv) on the page, each number with its digits.
A study's rows are written as each case finishes; the report is rewritten at the end of every `calfit study` run.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..core.digits import interval_uncertainty, rounded
from ..core.files import staged_folders
from ..core.units import MMHG_PER_KPA
from .run_report import _figure, _section, _strict_json, _table, render_page

REPORT_FOLDER = "report"
BAND_SIGMAS = 2.0    # the pressure bands: ± 2 standard deviations (about 95 %)
FITS_FACTOR = 1.2    # without a diagnosis, a case fits when its misfit is within this factor of its noise floor


def write_study_report(out: str | Path, rows: list[dict], volume: dict | None = None) -> Path:
    """Write out/report/ (module text) from the rows of the study table (in the cases' order) and, for a volume,
    the record of its slices (`volume_study.slice_volume_case`); returns the page's path."""
    out = Path(out)
    final = out / REPORT_FOLDER
    with staged_folders(final) as (staging,):
        report = _strict_json(build_study_report(rows, volume, staging))
        (staging / "report.json").write_text(json.dumps(report, indent=1, allow_nan=False), encoding="utf-8")
        (staging / "index.html").write_text(render_page(report), encoding="utf-8")
    return final / "index.html"


def build_study_report(rows: list[dict], volume: dict | None, figure_dir: Path) -> dict:
    done = [row for row in rows if row.get("status") == "done"]
    parameters = parameter_names(done)
    pressures = pressure_names(done)
    failing = [row for row in rows if row.get("status") != "done" or row.get("lack_of_fit") or row.get("below_floor")
               or row.get("too_coarse")]
    sections = []
    if volume is not None and volume.get("slide"):
        sections.append(_slide_section(volume))
    if volume is not None and done:
        sections.append(_profiles_section(done, parameters, pressures, volume, figure_dir))
    if done:
        sections.append(_distributions_section(done, parameters, figure_dir))
    sections.append(_failing_section(failing))
    sections.append(_table_section(rows, parameters, pressures))
    kind = "slices of one leg" if volume is not None else "cases"
    title = f"calfit study: {volume['name']}" if volume is not None else "calfit study"
    overview = (f"{len(rows)} {kind}, {len(done)} done. "
                + (f"Slices every {volume['slice_spacing_mm']:.3g} mm of the volume, the loaded session aligned on "
                   f"the bones in 3D: {_motion_words(volume)}. " if volume is not None else "")
                + "Each case was identified from its images, given its Monte-Carlo intervals, its pressures and its "
                  "diagnosis (calfit study).")
    return {"title": title, "overview": overview,
            "answers": _answers(done, rows, failing, pressures, volume), "sections": sections, "missing": []}


def _motion_words(volume: dict) -> str:
    """How the leg moved between the sessions, as the 3D alignment found it: turned and tilted (degrees) and slid
    along the leg (mm, the bones' centre along the slice normal: a loaded slice shows the leg that far higher or
    lower), or the rotation and translation where the study's record predates those words."""
    alignment = volume.get("alignment") or {}
    rotation, translation = alignment.get("rotation_deg"), alignment.get("translation_mm")
    slide = volume.get("slide")
    if rotation is not None and slide is not None:
        return (f"the leg turned {rotation[2]:.2f} deg about its axis, tilted {float(np.hypot(*rotation[:2])):.2f} deg "
                f"and slid {_slide_words(slide['slide_mm'], slide['slide_sd_mm'])} mm along it between the sessions "
                f"(at the leg's centre at {slide['height_mm']:.1f} mm; the bones' centre "
                f"{_slide_words(slide['bones_centre_slide_mm'], slide['bones_centre_slide_sd_mm'])} mm)")
    if rotation is not None and translation is not None:
        return (f"the leg turned {rotation[2]:.2f} deg about its axis, tilted {float(np.hypot(*rotation[:2])):.2f} deg "
                f"and slid {translation[2]:+.2f} mm along it between the sessions (in-plane shift "
                f"{translation[0]:.2f}, {translation[1]:.2f} mm)")
    return (f"rotation {np.linalg.norm(volume['motion']['rotation_vector_deg']):.2f} deg, "
            f"translation ({', '.join(f'{t:.2f}' for t in volume['motion']['translation_mm'])}) mm")


def _slide_words(value: float, sd: float) -> str:
    """A slide with its standard error, to the error's digits (`core.digits.rounded`)."""
    if sd is None or not np.isfinite(sd):
        return f"{value:+.2f}"
    return f"{'+' if value >= 0 else ''}{rounded(value, sd)} ± {rounded(sd, sd)}"


def _slide_section(volume: dict) -> dict:
    """The slide along the leg between the sessions, as the 3D alignment on the bones found it: at the leg's centre
    of each studied slice, with its standard error (the delete-one-slice jackknife of the alignment)."""
    slide = volume["slide"]
    rows = [[entry["height_mm"], entry["slide_mm"], entry["slide_sd_mm"]] for entry in slide.get("slices", [])] or [
        [entry["height_mm"], entry.get("slide_mm"), entry.get("slide_sd_mm")] for entry in volume["slices"]]
    spreads = [[None, sd, None if sd is None else sd / 2.0] for _, _, sd in rows]
    table = _table("slide", "The slide along the leg at each studied slice", ["height (mm)", "slide (mm)", "std (mm)"],
                   rows, "The loaded volume's displacement along the slices' normal at the centre of the unloaded "
                   "slice's leg: a loaded slice shows the leg that much lower (positive: the leg slid towards the "
                   "knee). A tilted leg slides by different amounts across the slice.", spreads)
    paragraphs = [(
        f"The leg slid {_slide_words(slide['slide_mm'], slide['slide_sd_mm'])} mm along itself between the sessions, "
        f"at the leg's centre at {slide['height_mm']:.1f} mm (the bones' centre: "
        f"{_slide_words(slide['bones_centre_slide_mm'], slide['bones_centre_slide_sd_mm'])} mm; tilt "
        f"{slide['tilt_deg']:.2f} deg). The standard error is the spread of the alignment made again without each "
        f"slice in turn ({slide['jackknife_refits']} refits). Each slice case is cut with the loaded volume "
        "resampled through this motion, so that its two images see the same tissue.")]
    return _section("slide", "The slide along the leg", paragraphs, tables=[table])


def parameter_names(rows: list[dict]) -> list[str]:
    """The identified parameters of the rows: the columns that have an interval (<name>_low, <name>_high)."""
    names = []
    for row in rows:
        names += [key for key in row if f"{key}_low" in row and f"{key}_high" in row and key not in names]
    return names


def pressure_names(rows: list[dict]) -> list[str]:
    """The pressure columns (kPa) of the rows, the interface pressure first, each with its _std_kPa."""
    names = []
    for row in rows:
        names += [key for key in row if key.endswith("_kPa") and not key.endswith("_std_kPa")
                  and key.replace("_kPa", "_std_kPa") in row and key not in names]
    return sorted(names, key=lambda name: (name != "interface_pressure_kPa", name))


def pressure_label(column: str) -> str:
    if column == "interface_pressure_kPa":
        return "garment on the skin (2 pi T / perimeter)"
    return column.removeprefix("pressure_").removesuffix("_kPa")


def at_height(rows: list[dict], column: str, height_mm: float) -> tuple[float, float] | None:
    """A pressure and its standard deviation at a height, linear between the two studied slices around it; None
    outside the studied heights."""
    known = sorted((row["height_mm"], row[column], row[column.replace("_kPa", "_std_kPa")]) for row in rows
                   if row.get(column) is not None and row.get("height_mm") is not None)
    if not known or not known[0][0] - 1e-6 <= height_mm <= known[-1][0] + 1e-6:
        return None
    heights, values, spreads = (np.array(c, float) for c in zip(*known))
    return float(np.interp(height_mm, heights, values)), float(np.interp(height_mm, heights, spreads))


def _answers(done, rows, failing, pressures, volume) -> dict:
    tables = []
    named = (volume or {}).get("compression_heights_mm", {})
    if named and pressures:
        table_rows, spreads = [], []
        for name, height in sorted(named.items(), key=lambda item: item[1]):
            cells, sds = [name, height], [None, 0.1]
            for column in pressures:
                found = at_height(done, column, height)
                value, sd = found if found is not None else (None, None)
                cells += [value, sd, None if value is None else value * MMHG_PER_KPA]
                sds += [sd, sd, None if sd is None else sd * MMHG_PER_KPA]
            table_rows.append(cells)
            spreads.append(sds)
        header = ["height", "mm"] + [h for column in pressures for h in
                                     (f"{pressure_label(column)} (kPa)", "std (kPa)", "mmHg")]
        tables.append(_table("answers_heights", "Pressure at the compression standard's heights", header, table_rows,
                             "Linear between the two studied slices around each height; - where the height is outside "
                             "the studied slices. The spread adds the garment tension's uncertainty.", spreads))
    fitting = [row for row in done if not row.get("too_coarse") and not row.get("below_floor") and (
        not row["lack_of_fit"] if "lack_of_fit" in row else (row.get("misfit_over_floor") or np.inf) <= FITS_FACTOR)]
    verdict = (f"{len(fitting)} of {len(rows)} fit their model to the noise floor"
               + (f"; the model fails on {len(failing)}: {', '.join(row['case'] for row in failing)}" if failing else "")
               + ".")
    return {"tables": tables, "verdict": verdict}


def _profiles_section(done, parameters, pressures, volume, figure_dir) -> dict:
    from ..core.plotting import save as save_figure
    from .figures import study_profile_figure

    heights = np.array([row["height_mm"] for row in done])
    order = np.argsort(heights)
    ordered = [done[i] for i in order]
    named = volume.get("compression_heights_mm", {})
    figures_ = []
    panels = [(name, [r[name] for r in ordered], [r[f"{name}_low"] for r in ordered], [r[f"{name}_high"] for r in ordered],
               "kPa") for name in parameters]
    save_figure(study_profile_figure(heights[order], panels, named, "parameter"), figure_dir / "profile_parameters.png")
    figures_.append(_figure("profile_parameters.png", "Each parameter along the leg: the identified value (dots) and its "
                            "95 % Monte-Carlo interval (band); dashed lines mark the named heights of the standard."))
    if pressures:
        pressure_panels = []
        for column in pressures:
            values = np.array([r.get(column, np.nan) for r in ordered], float)
            spread = np.array([r.get(column.replace("_kPa", "_std_kPa"), np.nan) for r in ordered], float)
            pressure_panels.append((pressure_label(column), values, values - BAND_SIGMAS * spread,
                                    values + BAND_SIGMAS * spread, "kPa"))
        save_figure(study_profile_figure(heights[order], pressure_panels, named, "pressure", mmhg=True),
                    figure_dir / "profile_pressures.png")
        figures_.append(_figure("profile_pressures.png", "Pressure along the leg (kPa, mmHg on the right axis): the "
                                "garment's on the skin and at each landmark, with ± 2 standard deviations (the "
                                "parameters' spread and the tension's uncertainty)."))
    misfit = [(r.get("misfit_over_floor") or np.nan) for r in ordered]
    save_figure(study_profile_figure(heights[order], [("misfit / noise floor", misfit, None, None, "")], named, "misfit",
                                     reference=1.0), figure_dir / "profile_misfit.png")
    figures_.append(_figure("profile_misfit.png", "The misfit of each slice over its noise floor; 1 (dotted) is a "
                            "model that fits to the noise."))
    tension = [(r["height_mm"], r.get("tension_N_per_mm")) for r in ordered]
    paragraphs = [f"{len(done)} slices from {heights.min():.1f} to {heights.max():.1f} mm; garment tension "
                  + ", ".join(f"{t:.3g} N/mm at {h:.0f} mm" for h, t in (tension[0], tension[-1]) if t is not None) + "."]
    return _section("profiles", "Profiles along the leg", paragraphs, figures_=figures_)


def _distributions_section(done, parameters, figure_dir) -> dict:
    from ..core.plotting import save as save_figure
    from .figures import study_distribution_figure

    panels = [(name, [r["case"] for r in done], [r[name] for r in done], [r[f"{name}_low"] for r in done],
               [r[f"{name}_high"] for r in done]) for name in parameters]
    save_figure(study_distribution_figure(panels), figure_dir / "distributions.png")
    table_rows, spreads = [], []
    for name in parameters:
        values = np.array([r[name] for r in done], float)
        widths = np.array([r[f"{name}_high"] - r[f"{name}_low"] for r in done], float)
        identifiable = sum(1 for r in done if r.get(f"{name}_identifiable"))
        typical = float(np.median(widths)) / 4.0
        table_rows.append([name, float(np.median(values)), float(values.min()), float(values.max()),
                           float(np.median(widths)), f"{identifiable} of {len(done)}"])
        spreads.append([None, typical, typical, typical, typical, None])
    table = _table("distribution", "Parameters over the cases (kPa)",
                   ["parameter", "median", "lowest", "highest", "median 95 % interval width", "identifiable"],
                   table_rows, "A spread of the values much wider than the intervals is a spread of the tissues; "
                   "one as narrow is the measurement's.", spreads)
    return _section("distributions", "Distributions over the cases", tables=[table], figures_=[_figure(
        "distributions.png", "Each case's value (dot) and 95 % interval (bar), per parameter; the line is the median.")])


def _failing_section(failing) -> dict:
    if not failing:
        return _section("failing", "Cases whose model fails", ["None: every case ran and fits its model to the noise "
                                                               "floor (no lack of fit in its diagnosis)."])
    rows = [[row["case"], row.get("status"), row.get("misfit_over_floor"), _why(row)] for row in failing]
    table = _table("failing_cases", "Cases that failed or whose model lacks something",
                   ["case", "status", "misfit / floor", "verdict or error"], rows,
                   "Open a case's run folder (DIR/cases/<case>) and its report (calfit report) to see where.")
    return _section("failing", "Cases whose model fails", tables=[table])


def _why(row: dict) -> str:
    reasons = [row.get("verdict") or row.get("error") or ""]
    if row.get("too_coarse"):
        reasons.insert(0, f"the skin moves {row['skin_shift_px']:.1f} px between the volume's slices here: the "
                          "loaded slice, resampled between them, carries edge errors above the noise")
    return "; ".join(reason for reason in reasons if reason) or "-"


def _table_section(rows, parameters, pressures) -> dict:
    columns = (["case"] + (["height_mm"] if any("height_mm" in r for r in rows) else [])
               + [c for name in parameters for c in (name, f"{name}_low", f"{name}_high")]
               + [c for name in pressures for c in (name, name.replace("_kPa", "_std_kPa"))]
               + ["misfit_over_floor", "status"])
    table_rows, spreads = [], []
    for row in rows:
        table_rows.append([row.get(column) for column in columns])
        spreads.append([cell_uncertainty(column, row) for column in columns])
    return _section("table", "The study table", ["The same numbers as study.csv (full precision in study.parquet)."],
                    tables=[_table("study_table", "One row per case", columns, table_rows, "", spreads)])


def cell_uncertainty(column: str, row: dict) -> float | None:
    """What sets a number's digits in the CSV: a parameter's interval (`digits.interval_uncertainty`), a pressure's
    spread; None (4 significant digits) for the rest."""
    for name in (column, column.removesuffix("_low"), column.removesuffix("_high")):
        if f"{name}_low" in row and f"{name}_high" in row:
            return interval_uncertainty(row[f"{name}_low"], row[f"{name}_high"])
    if column.startswith(("pressure_", "interface_pressure_")):   # <pressure>_kPa or _std_kPa: by its spread
        return row.get(column.replace("_std_kPa", "_kPa").replace("_kPa", "_std_kPa"))
    return None
