"""The design's page: DIR/report/index.html with the targets and their probabilities, the FE model beside
Laplace's law at each landmark and height, the tension along the leg and around it (N/mm, design-tension.png), and
the pressure maps of the designed garment (design-maps.png: the hydrostatic pressure, mmHg, of each slice with a
target, on its deformed mesh). Numbers with the digits their uncertainty allows (`core.digits`)."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..core.digits import with_uncertainty
from ..core.files import atomic_write_text
from ..core.plotting import plt


def probability_text(p: float, se: float) -> str:
    """A probability with its draws' standard error, to the digits that allows ("0.92 ± 0.03"); three decimals when
    the draws agree to better than 0.001 (the tension's 400 quantiles then set its resolution); "1.00", "0.00"
    when every pair agrees."""
    if p in (0.0, 1.0):
        return f"{p:.2f}"
    if not np.isfinite(se) or se < 1e-3:   # the draws agree: the tension's quadrature sets the digits
        return f"{p:.3f}"
    return with_uncertainty(p, se)


def target_lines(result: dict) -> list[str]:
    lines = []
    for row in result["targets"]:
        bounds = _bounds(row)
        lines.append(f"{row['name']} {bounds}: {with_uncertainty(row['value'], row['std_mmHg'], 'mmHg')}, "
                     f"probability met {probability_text(row['probability_met'], row['probability_se'])}")
    return lines


def _bounds(row: dict) -> str:
    if row["min_mmHg"] is not None and row["max_mmHg"] is not None:
        return f"{row['min_mmHg']:g}-{row['max_mmHg']:g} mmHg"
    return f">= {row['min_mmHg']:g} mmHg" if row["min_mmHg"] is not None else f"<= {row['max_mmHg']:g} mmHg"


def _figures(folder: Path, result: dict, slices, problem, solution) -> list[str]:
    from .slices import evaluate

    names = []
    heights = [row["height_mm"] if row["height_mm"] is not None else k for k, row in enumerate(result["slices"])]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    axes[0].plot(heights, [row["tension_N_per_mm"] for row in result["slices"]], "o-", label="FE design")
    axes[0].plot(heights, [row["tension_N_per_mm"] for row in result["laplace"]["slices"]], "s--",
                 label="Laplace's law alone")
    for row, h in zip(result["slices"], heights):
        if row["height_name"]:
            axes[0].annotate(row["height_name"], (h, row["tension_N_per_mm"]), textcoords="offset points",
                             xytext=(4, 6))
    axes[0].set_xlabel("height (mm)" if result["slices"][0]["height_mm"] is not None else "slice")
    axes[0].set_ylabel("tension (N/mm)")
    axes[0].legend()
    axes[0].set_title("tension along the leg")
    angles = np.radians(np.arange(0, 361, 5))
    for row in result["slices"]:
        factor = np.ones_like(angles)
        for name, c in zip(("a1", "b1", "a2", "b2"), row["profile"]):
            factor += c * (np.cos if name[0] == "a" else np.sin)(int(name[1]) * angles)
        axes[1].plot(np.degrees(angles), row["tension_N_per_mm"] * factor, label=row["height_name"] or row["slice"])
    axes[1].set_xlabel("angle about the skin's centroid (deg, image frame)")
    axes[1].set_ylabel("tension (N/mm)")
    axes[1].set_title("tension around the leg")
    fig.tight_layout()
    fig.savefig(folder / "design-tension.png")
    plt.close(fig)
    names.append("design-tension.png")
    shown = [k for k, piece in enumerate(slices) if piece.height_name] or [0]
    shown = shown[:4]
    fig, axes = plt.subplots(1, len(shown), figsize=(4.2 * len(shown), 4.2), squeeze=False)
    for ax, k in zip(axes[0], shown):
        tension, profile = problem.split(solution.v)[k]
        response = evaluate(slices[k], tension, profile, keep_fields=True)
        nodes, corners = response.deformed_nodes, slices[k].mesh.elements[:, :3]
        shade = ax.tripcolor(nodes[:, 0], nodes[:, 1], corners, response.nodal_pressure_mmHg[:len(nodes)],
                             shading="gouraud", cmap="viridis")
        for name, (x, y) in slices[k].landmarks.items():
            ax.plot(x, y, "w+")
            ax.annotate(name, (x, y), color="w", fontsize=7)
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(f"{slices[k].height_name or slices[k].name}: T = {tension:.3f} N/mm")
        fig.colorbar(shade, ax=ax, label="pressure -tr(sigma)/3 (mmHg)")
    fig.tight_layout()
    fig.savefig(folder / "design-maps.png")
    plt.close(fig)
    names.append("design-maps.png")
    return names


def write_design_report(out: Path, result: dict, slices, problem, solution) -> Path:
    folder = Path(out) / "report"
    folder.mkdir(parents=True, exist_ok=True)
    figures = _figures(folder, result, slices, problem, solution)
    e = html.escape
    rows = "".join(
        f"<tr><td>{e(row['name'])}</td><td>{e(_bounds(row))}</td>"
        f"<td>{e(with_uncertainty(row['value'], row['std_mmHg']))}</td>"
        f"<td>{e(probability_text(row['probability_met'], row['probability_se']))}</td>"
        f"<td>{e(with_uncertainty(law['value'], law['std_mmHg']))}</td>"
        f"<td>{e(probability_text(law['probability_met'], law['probability_se']))}</td></tr>"
        for row, law in zip(result["targets"], result["laplace"]["targets"]))
    compare = []
    for fe, law in zip(result["slices"], result["laplace"]["slices"]):
        where = e(fe["height_name"] or fe["slice"])
        for name, value in fe["landmarks_mmHg"].items():
            compare.append(f"<tr><td>{where}</td><td>{e(name)}</td><td>{value:.1f}</td>"
                           f"<td>{fe['laplace_landmarks_mmHg'][name]:.1f}</td>"
                           f"<td>{law['landmarks_mmHg'][name]:.1f}</td></tr>")
        compare.append(f"<tr><td>{where}</td><td>skin, mean</td><td>{fe['skin_mean_mmHg']:.1f}</td>"
                       f"<td>{fe['laplace_skin_mean_mmHg']:.1f}</td><td>{law['skin_mean_mmHg']:.1f}</td></tr>")
        compare.append(f"<tr><td>{where}</td><td>skin, tibial crest max</td>"
                       f"<td>{fe['skin_max_mmHg']['tibial_crest']:.1f}</td>"
                       f"<td>{fe['laplace_skin_max_mmHg']['tibial_crest']:.1f}</td>"
                       f"<td>{law['skin_max_mmHg']['tibial_crest']:.1f}</td></tr>")
    tensions = "".join(f"<tr><td>{e(fe['height_name'] or fe['slice'])}</td><td>{fe['tension_N_per_mm']:.4f}</td>"
                       f"<td>{law['tension_N_per_mm']:.4f}</td></tr>"
                       for fe, law in zip(result["slices"], result["laplace"]["slices"]))
    status = "every target met at the identified parameters" if result["feasible"] else \
        "infeasible: the closest design within the fabric's range is shown; missed: " + "; ".join(
            f"{s['name']} by {s['shortfall_mmHg']:.2f} mmHg" for s in result["shortfalls"])
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>calfit design</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}td,th{{padding:2px 8px;border-bottom:1px solid #ddd}}
</style></head><body><h1>The garment this leg needs</h1>
<p>{e(status)}. Tension sensitivity: {e(result['sensitivity'])}. Probabilities over {result['draws']} Monte-Carlo
draws of the identified parameters and the tension's relative uncertainty of {result['tension_rel_uncertainty']:g}.</p>
<h2>Targets</h2><table><tr><th>target</th><th>asked</th><th>designed (mmHg)</th><th>probability met</th>
<th>Laplace-only garment, through the FE model (mmHg)</th><th>its probability</th></tr>{rows}</table>
<h2>Tension per height (N/mm)</h2><table><tr><th>slice</th><th>FE design</th><th>Laplace's law alone</th></tr>
{tensions}</table><img src="{figures[0]}" width="100%">
<h2>The FE model beside Laplace's law (mmHg)</h2><table><tr><th>slice</th><th>where</th>
<th>designed garment, FE</th><th>same garment, Laplace P = T/r</th><th>Laplace-chosen garment, FE</th></tr>
{''.join(compare)}</table>
<h2>Pressure maps of the designed garment</h2><img src="{figures[1]}" width="100%">
</body></html>"""
    path = folder / "index.html"
    atomic_write_text(path, page)
    return path
