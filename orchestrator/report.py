"""The report of a run: one HTML page with PNG figures and the analogues of the first paper's tables.

Figures (drawn with numpy + scikit-image, written by imageio): the two images (Avril et al.
Fig. 1), the segmentation with the mesh (Fig. 2), the warped image I(x) = I1(x + u(x)) at the
identified parameters beside the target I0 with the map of the contour distances d_k (Fig. 4,
sec. 2.2.5), and the hydrostatic pressure -tr(sigma)/3 at the central values with the five
landmarks (Fig. 5). Tables: the identifications from the start points (Table 1), the
Monte-Carlo intervals and which parameters are poorly identified (Table 2), the landmark
pressures with their spread over draws in the intervals (Table 3) and with the garment
tension +-10 % (Table 4). The page is written to a temporary name and renamed.
"""

from __future__ import annotations

import html
import shutil
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from skimage.draw import line as draw_line, disk as draw_disk

from .diagnose import model_label
from .forward import MeshInterpolator, field_on_pixels, write_mesh_include
from .imaging.warp import warp_image
from .results import EngineResults
from .runlock import holds_run_folder
from .runner import run_engine
from .study import load_run, read_json

MMHG_PER_KPA = 7.50062
LABEL_COLOURS = np.array([[0, 0, 0], [235, 200, 120], [190, 70, 60], [240, 240, 240]] + [[150, 60, 90]] * 8, np.uint8)
RAMP = np.array([[48, 18, 59], [40, 120, 250], [30, 210, 160], [160, 250, 60], [250, 190, 40], [200, 30, 10]], float)


def colour_ramp(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """RGB uint8 of values on a blue-green-red ramp between low and high."""
    t = np.clip((np.asarray(values, float) - low) / max(high - low, 1e-12), 0.0, 1.0) * (len(RAMP) - 1)
    rgb = np.stack([np.interp(t, np.arange(len(RAMP)), RAMP[:, k]) for k in range(3)], axis=-1)
    return rgb.astype(np.uint8)


def grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, float)
    low, high = np.percentile(image, [1, 99.5])
    g = (np.clip((image - low) / max(high - low, 1e-12), 0, 1) * 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def colour_bar(low: float, high: float, height: int, width: int = 16) -> np.ndarray:
    values = np.linspace(high, low, height)[:, None].repeat(width, axis=1)
    return colour_ramp(values, low, high)


def draw_mesh(canvas: np.ndarray, mesh, pixel_size_mm, colour=(20, 20, 20)) -> np.ndarray:
    dy, dx = pixel_size_mm
    rc = np.column_stack([mesh.nodes[:, 1] / dy - 0.5, mesh.nodes[:, 0] / dx - 0.5]).round().astype(int)
    h, w = canvas.shape[:2]
    for tri in mesh.elements[:, :3]:
        for a, b in ((0, 1), (1, 2), (2, 0)):
            rr, cc = draw_line(*rc[tri[a]], *rc[tri[b]])
            keep = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            canvas[rr[keep], cc[keep]] = colour
    return canvas


def mark(canvas: np.ndarray, positions_mm, pixel_size_mm, colour=(255, 255, 255)) -> np.ndarray:
    dy, dx = pixel_size_mm
    for number, (x, y) in enumerate(positions_mm, start=1):
        rr, cc = draw_disk((y / dy - 0.5, x / dx - 0.5), 4 + 0 * number, shape=canvas.shape[:2])
        canvas[rr, cc] = (0, 0, 0)
        rr, cc = draw_disk((y / dy - 0.5, x / dx - 0.5), 2.5, shape=canvas.shape[:2])
        canvas[rr, cc] = colour
    return canvas


def _side_by_side(*panels: np.ndarray, gap: int = 6) -> np.ndarray:
    height = max(p.shape[0] for p in panels)
    parts = []
    for panel in panels:
        padded = np.full((height, panel.shape[1], 3), 255, np.uint8)
        padded[: panel.shape[0]] = panel
        parts += [padded, np.full((height, gap, 3), 255, np.uint8)]
    return np.concatenate(parts[:-1], axis=1)


def _table(header: list[str], rows: list[list]) -> str:
    def cell(value):
        return f"{value:.4g}" if isinstance(value, float) else html.escape(str(value))
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def central_solution(setup, theta, folder: Path, model=None) -> EngineResults:
    """Solve the run's model (or `model`) at theta, keeping the VTU (pressure field) in folder."""
    model = model if model is not None else setup.model
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh_include(model, folder)
    deck = folder / "deck.inp"
    deck.write_text(model.deck(theta))
    outcome = run_engine(deck, folder / "out", threads=1, timeout_s=300)
    if not outcome.converged:
        raise RuntimeError(f"the engine did not converge at the central values {list(theta)}")
    return EngineResults(outcome.outdir)


def contour_distance_map(setup, nodal: np.ndarray, d_max: float | None = None):
    """(d_k map over a dimmed I0, mismatch result, d_max): the contour distances of Avril et al. Fig. 4."""
    mismatch = setup.mismatch_objective()
    field = field_on_pixels(mismatch.weights, nodal, setup.case.shape)
    result = mismatch.mismatch(field)
    if d_max is None:
        d_max = float(np.nanmax(result.distance_mm)) if np.isfinite(result.distance_mm).any() else 1.0
    d_map = grey(setup.case.unloaded) // 3
    on = np.isfinite(result.distance_mm)
    d_map[on] = colour_ramp(result.distance_mm[on], 0.0, d_max)
    return d_map, result, d_max, field


def residual_arrows(setup, positions_mm, residual_mm, scale_px_per_mm: float, high_mm: float) -> np.ndarray:
    """Residual vectors u_model - u_measured at the points, drawn `scale_px_per_mm` long per mm on a dimmed I0,
    coloured by length (0 to high_mm)."""
    canvas = grey(setup.case.unloaded) // 2
    dy, dx = setup.case.pixel_size_mm
    h, w = canvas.shape[:2]
    positions_mm, residual_mm = np.asarray(positions_mm, float), np.asarray(residual_mm, float)
    colours = colour_ramp(np.linalg.norm(residual_mm, axis=1), 0.0, high_mm)
    for (x, y), (ux, uy), colour in zip(positions_mm, residual_mm, colours):
        r0, c0 = int(round(y / dy - 0.5)), int(round(x / dx - 0.5))
        r1, c1 = int(round(r0 + uy * scale_px_per_mm)), int(round(c0 + ux * scale_px_per_mm))
        rr, cc = draw_line(r0, c0, r1, c1)
        keep = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        canvas[rr[keep], cc[keep]] = colour
        rr, cc = draw_disk((r0, c0), 1.5, shape=(h, w))
        canvas[rr, cc] = colour
    return canvas


def diagnosis_section(setup, identification: dict, diagnosis: dict, staging: Path) -> str:
    """HTML of the diagnosis: ranking, before/after table, residual maps before and after side by side."""
    before_model = setup.model_with(identification.get("effects", ()))
    panels_dk, panels_arrows = [], []
    before = np.asarray(diagnosis["maps"]["residual_mm"], float)
    afters = [np.asarray(m["residual_mm"], float) for m in diagnosis.get("maps_after", [])]
    high = max([float(np.linalg.norm(before, axis=1).max())] + [float(np.linalg.norm(a, axis=1).max()) for a in afters])
    scale = 12.0 / max(high, 1e-9)    # the longest residual is drawn 12 pixels long
    positions = diagnosis["maps"]["positions_mm"]
    nodal = central_solution(setup, diagnosis["theta"], staging / "diagnosis-before", before_model).displacement()
    d_map, result, d_max, _ = contour_distance_map(setup, nodal)
    panels_dk.append(d_map)
    panels_arrows.append(residual_arrows(setup, positions, before, scale, high))
    mismatch_values = [result.value_mm2]
    for k, (fit, after) in enumerate(zip(diagnosis["refits"], afters)):
        model = setup.model_with(fit["effects"])
        nodal = central_solution(setup, fit["theta"], staging / f"diagnosis-after-{k}", model).displacement()
        d_map, result, _, _ = contour_distance_map(setup, nodal, d_max)
        panels_dk.append(d_map)
        panels_arrows.append(residual_arrows(setup, positions, after, scale, high))
        mismatch_values.append(result.value_mm2)
    iio.imwrite(staging / "residuals_before_after.png",
                _side_by_side(*panels_arrows, colour_bar(0.0, high, setup.case.shape[0])))
    iio.imwrite(staging / "dk_before_after.png", _side_by_side(*panels_dk, colour_bar(0.0, d_max, setup.case.shape[0])))
    floor = diagnosis["noise_floor"]
    ranking = _table(["rank", "effect", "parameters", "statistic", "p-value", "predicted misfit / floor",
                      "|g_perp| / |g|", "significant"],
                     [[k, s["effect"], ", ".join(s["parameters"]), s["statistic"], s["p_value"],
                       s["predicted_misfit"] / floor, ", ".join(f"{v:.2f}" for v in s["orthogonal_fraction"]),
                       "YES" if s["significant"] else "no"] for k, s in enumerate(diagnosis["ranking"], 1)])
    fits = [diagnosis["before"]] + diagnosis["refits"]
    comparison = _table(["model", "k", "misfit (mm^2)", "misfit / floor", "AIC", "BIC", "M (mm^2)", "parameters"],
                        [[model_label(f["effects"]), len(f["parameters"]),
                          f["misfit"], f["misfit_over_floor"], f["aic"], f["bic"], m,
                          ", ".join(f"{n} = {v:.4g}" for n, v in zip(f["parameters"], f["theta"]))]
                         for f, m in zip(fits, mismatch_values)])
    maps = diagnosis["maps"]
    names = maps.get("sector_names") or [f"{c:.0f} deg" for c in maps["sector_centre_deg"]]
    sectors = _table(["sector"] + names,
                     [["RMS residual (mm)"] + maps["sector_rms_mm"],
                      ["mean radial (mm, + outwards)"] + maps["sector_radial_mm"],
                      ["measurements"] + maps["sector_count"]])
    worst = (f"<p>Largest share of the squared residual: the {html.escape(maps['worst_region'])} "
             f"({100 * maps['worst_region_share']:.0f} %, RMS {maps['worst_region_rms_mm']:.3f} mm).</p>"
             if maps.get("worst_region") else "")
    labels = " | ".join(["identified model"] + [model_label(f["effects"]) for f in diagnosis["refits"]])
    located = ""
    if _copy_figure(setup.run_dir / "diagnosis.png", staging):
        patch = (diagnosis.get("local") or {}).get("patch")
        located = (f"<h3>Where the residual lies{': the place of a local stiffness change, ' + html.escape(patch['place']) if patch else ''}"
                   "</h3><img src=\"diagnosis.png\">")
    return f"""<h2>Diagnosis: where the model fails and which effect is missing</h2>
<p>{html.escape(diagnosis['verdict'])}.</p>
<p>Misfit {diagnosis['misfit']:.4g} mm^2 against a noise floor of {diagnosis['noise_floor']:.4g} mm^2
(chi^2 = {diagnosis['chi2']:.1f} over {diagnosis['n_residuals']} residuals, lack-of-fit p = {diagnosis['lack_of_fit_p']:.2g});
neighbour correlation of the residual {diagnosis['neighbour_correlation']:.2f}, design effect {diagnosis['design_effect']:.2f};
sensitivities from {html.escape(diagnosis['sensitivities_from'])}, {diagnosis['engine_runs']} engine runs.</p>
{ranking}
<h3>Residual per sector around the leg (angles counter-clockwise on the image from its +x axis, 90 deg at the
top; anterior towards the tibia, lateral towards the fibula)</h3>{sectors}{worst}
<p>RMS residual per tissue: {html.escape(', '.join(f'{k} {v:.3f} mm' for k, v in diagnosis['maps']['per_region_rms_mm'].items()))}.</p>
{located}
<h3>Before and after the refit</h3>{comparison}
<h3>Displacement residual vectors at the measured points ({html.escape(labels)}; 0 to {high:.3f} mm, drawn x{scale * setup.case.pixel_size_mm[1]:.0f})</h3>
<img src="residuals_before_after.png">
<h3>Contour distances d_k (Avril et al. Fig. 4; {html.escape(labels)}; 0 to {d_max:.2f} mm)</h3>
<img src="dk_before_after.png">
"""


def _copy_figure(path: Path, staging: Path) -> bool:
    """Put a figure of the run folder into the report; False when the run has none."""
    if not path.is_file():
        return False
    shutil.copy(path, staging / path.name)
    return True


def _optional_json(path: Path) -> dict | None:
    return read_json(path, "") if path.is_file() else None


@holds_run_folder()
def write_report(run_dir: str | Path, truth: dict | None = None) -> Path:
    """Write RUN_DIR/report/index.html (and its PNGs) from the run's JSON files; returns the page's path.
    identification.json is required; the Monte-Carlo, pressure and diagnosis sections appear when their
    commands have run."""
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    montecarlo = _optional_json(run_dir / "montecarlo.json")
    pressures = _optional_json(run_dir / "pressures.json")
    diagnosis = _optional_json(run_dir / "diagnosis.json")
    final = run_dir / "report"
    staging = Path(tempfile.mkdtemp(prefix=".report.", dir=run_dir))
    try:
        page = _page(setup, identification, montecarlo, pressures, diagnosis, truth, staging)
        (staging / "index.html").write_text(page, encoding="utf-8")
        for sub in staging.iterdir():
            if sub.is_dir():
                shutil.rmtree(sub, ignore_errors=True)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if final.exists():
        old = run_dir / f".report.old.{np.random.default_rng().integers(1 << 30)}"
        final.rename(old)
        shutil.rmtree(old, ignore_errors=True)
    staging.rename(final)
    return final / "index.html"


def _page(setup, identification: dict, montecarlo: dict | None, pressures: dict | None, diagnosis: dict | None,
          truth: dict | None, staging: Path) -> str:
    case, px = setup.case, setup.case.pixel_size_mm
    names = identification["parameters"]
    theta = identification["best"]["theta"]
    model = setup.model_with(identification.get("effects", ()))

    iio.imwrite(staging / "images.png", _side_by_side(grey(case.unloaded), grey(case.loaded)))
    labels_rgb = LABEL_COLOURS[np.clip(setup.labels_unloaded, 0, len(LABEL_COLOURS) - 1)].copy()
    iio.imwrite(staging / "segmentation_mesh.png", draw_mesh(labels_rgb, setup.mesh, px))

    nodal = central_solution(setup, theta, staging / "identified", model).displacement()
    d_map, result, d_max, field = contour_distance_map(setup, nodal)
    warped = warp_image(setup.loaded_aligned, field, px)
    iio.imwrite(staging / "warped_dk.png", _side_by_side(grey(warped), grey(case.unloaded), d_map,
                                                         colour_bar(0.0, d_max, case.shape[0])))
    fits = identification["fits"]
    table1 = _table(["start " + n for n in names] + ["misfit"] + ["found " + n for n in names] + ["iterations", "engine runs"],
                    [f["start"] + [f["cost"]] + f["theta"] + [f["iterations"], f["engine_runs"]] for f in fits])
    effects = identification.get("effects", [])
    compartments = "".join(f"<p>{html.escape(line)}.</p>" for line in setup.setup_lines())
    if _copy_figure(setup.run_dir / "compartments.png", staging):
        compartments = f"<h2>Muscle compartments found at the septa of I0</h2>{compartments}<img src=\"compartments.png\">"
    sections = [f"""<h1>calfit report: {html.escape(case.name)}</h1>
<p>Case <code>{html.escape(str(case.folder))}</code>; garment tension {case.tension_N_per_mm:g} N/mm;
mesh {len(setup.mesh.elements)} {setup.mesh.element_type} elements; objective {html.escape(identification['objective'])},
method {html.escape(identification['method'])}; effects in the model: {html.escape(', '.join(effects) or 'none (baseline)')};
{identification['engine_runs_total']} engine runs in the log.</p>
<h2>Images (unloaded I0, loaded I1)</h2><img src="images.png">
<h2>Segmentation and mesh</h2><img src="segmentation_mesh.png">
{compartments}
<h2>Warped image at the identified parameters, target I0, contour distances d_k (0 to {d_max:.2f} mm)</h2>
<p>M = sum d_k^2 = {result.value_mm2:.1f} mm^2 over {result.contour_pixel_count} contour pixels (rms {result.rms_mm:.3f} mm).</p>
<img src="warped_dk.png">
<h2>Table 1: identification from several starting points</h2>{table1}"""]
    if montecarlo:
        sections.append(_montecarlo_section(names, theta, montecarlo, truth))
    if montecarlo and pressures:
        sections.append(_pressure_section(setup, montecarlo, pressures, staging))
    if diagnosis:
        sections.append(diagnosis_section(setup, identification, diagnosis, staging))
    missing = [cmd for cmd, data in (("calfit montecarlo", montecarlo), ("calfit pressures", pressures),
                                      ("calfit diagnose", diagnosis)) if data is None]
    if missing:
        sections.append(f"<p>Not in this report yet (run them, then calfit report again): {html.escape(', '.join(missing))}.</p>")
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>calfit report: {html.escape(case.name)}</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:2em}} table{{border-collapse:collapse;margin:1em 0}}
td,th{{border:1px solid #999;padding:3px 8px;text-align:right}} img{{max-width:100%}}</style></head><body>
{''.join(sections)}
</body></html>
"""


def _montecarlo_section(names, theta, montecarlo: dict, truth: dict | None) -> str:
    poorly = montecarlo["poorly_identified"]
    noise = montecarlo.get("method") == "noise"
    rows2 = [["lower bound"] + montecarlo["lower"], ["upper bound"] + montecarlo["upper"],
             ["central value"] + montecarlo["central"], ["identified"] + theta]
    if truth:
        rows2.append(["truth (phantom)"] + [truth[n] for n in names])
    if noise:
        rows2.append(["half width (%)"] + [100 * w for w in montecarlo["relative_half_width"]])
    rows2.append(["identification"] + [("NOT identifiable" if noise else "POOR") if n in poorly else "good"
                                       for n in names])
    table2 = _table([""] + [f"{n} (kPa)" for n in names], rows2)
    if noise:
        poorly_text = (f"Not identifiable: <b>{', '.join(poorly)}</b> (95 % interval wider than +-10 % of the value)."
                       if poorly else "Every parameter is identifiable (95 % interval within +-10 % of its value).")
        if montecarlo["on_bound"]:
            poorly_text += f" On a bound of the search box: <b>{', '.join(montecarlo['on_bound'])}</b>."
        inflation = (f", noise variance inflated x{montecarlo['inflation']:.2f} because the misfit is above its floor"
                     if montecarlo["inflation"] > 1.0 else "")
        title = (f"Table 2: parameter intervals ({100 * montecarlo['confidence']:.0f} % Monte-Carlo over the "
                 f"measurement noise, {montecarlo['draws'] - montecarlo['failed']} refitted draws{inflation})")
    else:
        poorly_text = (f"Poorly identified: <b>{', '.join(poorly)}</b> (their accepted values span more than a factor "
                       f"1.5 or reach the edge of the explored range); the pressures below carry that uncertainty."
                       if poorly else "All parameters are well identified (accepted values within a factor 1.5).")
        title = (f"Table 2: parameter intervals (Monte-Carlo, misfit below {montecarlo['threshold']:.4g}, "
                 f"{montecarlo['accepted']} of {montecarlo['draws']} draws kept, {montecarlo['failed']} failed)")
    return f"<h2>{html.escape(title)}</h2>{table2}<p>{poorly_text}</p>"


def _pressure_section(setup, montecarlo: dict, pressures: dict, staging: Path) -> str:
    case, px = setup.case, setup.case.pixel_size_mm
    results = central_solution(setup, montecarlo["central"], staging / "central")
    weights = MeshInterpolator(setup.mesh).pixel_weights(case.shape, px)
    pressure = (weights @ results.point_field("pressure")).reshape(case.shape) * 1e3
    inside = (setup.labels_unloaded > 0) & (setup.labels_unloaded != 3)
    low, high = np.percentile(pressure[inside], [1, 99])
    p_map = np.full((*case.shape, 3), 255, np.uint8)
    p_map[inside] = colour_ramp(pressure[inside], low, high)
    landmarks = [case.landmarks[name] for name in pressures["landmarks"]]
    iio.imwrite(staging / "pressure.png", _side_by_side(mark(p_map, landmarks, px), colour_bar(low, high, case.shape[0])))
    table3 = _table(["landmark", "mean (kPa)", "mean (mmHg)", "std (kPa)", "CV (%)"],
                    [[n, m, m * MMHG_PER_KPA, s, c] for n, m, s, c in
                     zip(pressures["landmarks"], pressures["mean_kPa"], pressures["std_kPa"], pressures["cv_percent"])])
    table4 = _table(["landmark", "pressure (kPa)", "T +10 % (kPa)", "deviation (%)", "T -10 % (kPa)", "deviation (%)"],
                    [[n, b, p, dp, m, dm] for n, b, p, dp, m, dm in
                     zip(pressures["landmarks"], pressures["central_kPa"], pressures["plus_kPa"],
                         pressures["plus_deviation_percent"], pressures["minus_kPa"], pressures["minus_deviation_percent"])])
    return f"""<h2>Hydrostatic pressure at the central values ({low:.2f} to {high:.2f} kPa), landmarks 1-5</h2><img src="pressure.png">
<h2>Table 3: landmark pressures over {pressures['draws']} draws in the intervals ({pressures['failed']} failed)</h2>{table3}
<h2>Table 4: garment tension +-{100 * pressures['tension_rel']:.0f} %</h2>{table4}"""
