"""The diagnosis drawn on the unloaded image: the residual vectors and the place of a local change (diagnosis.png)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.plotting import DPI, image_axes, plt
from .score import FLOOR_AGREEMENT


def diagnosis_figure(path: Path, image: np.ndarray, pixel_size_mm, maps, mesh, patch_elements: np.ndarray | None = None,
                     place: str = "", title: str = "") -> Path:
    """The residual of the identified model (u_model - u_measured) as arrows coloured by length (mm, colour bar)
    on the unloaded image, the 30-degree sectors of `regions` about the leg centre with their anatomical names, and
    the place of the proposed local stiffness change shaded; `title` says which garment level it is, when several."""
    from matplotlib.collections import PolyCollection
    from scipy.spatial import cKDTree

    positions = np.asarray(maps.positions_mm, float)
    residual = np.asarray(maps.residual_mm, float)
    centre = np.asarray(maps.centre_mm, float)
    figure, ax = plt.subplots(figsize=(8.0, 7.5))
    image_axes(ax, image, pixel_size_mm)
    if patch_elements is not None and len(patch_elements):
        corners = mesh.nodes[mesh.elements[np.asarray(patch_elements), :3]]
        ax.add_collection(PolyCollection(corners, facecolors="tab:orange", edgecolors="none", alpha=0.45,
                                         label=f"local stiffness change: {place}"))
    radius = 0.5 * float(min(image.shape[0] * pixel_size_mm[0], image.shape[1] * pixel_size_mm[1]))
    for k, name in enumerate(maps.sector_names):
        angle = np.radians(k * 360.0 / len(maps.sector_names))
        ax.plot([centre[0], centre[0] + radius * np.cos(angle)], [centre[1], centre[1] - radius * np.sin(angle)],
                color="white", linewidth=0.5, alpha=0.5)
        middle = np.radians(maps.sector_centre_deg[k])
        ax.text(centre[0] + 0.9 * radius * np.cos(middle), centre[1] - 0.9 * radius * np.sin(middle),
                name.split(" sector ")[0] + f"\n{maps.sector_centre_deg[k]:.0f} deg", color="white", fontsize=6,
                ha="center", va="center")
    length = np.hypot(residual[:, 0], residual[:, 1])
    largest = float(length.max()) if length.size else 1.0
    places = np.unique(positions, axis=0)   # several garment levels share their windows' places
    spacing = float(np.median(cKDTree(places).query(places, k=2)[0][:, 1])) if len(places) > 1 else 1.0
    scale = largest / (1.5 * spacing) if largest > 0 else 1.0
    arrows = ax.quiver(positions[:, 0], positions[:, 1], residual[:, 0], residual[:, 1], length, cmap="magma",
                       angles="xy", scale_units="xy", scale=scale, width=0.003)
    figure.colorbar(arrows, ax=ax, shrink=0.8, label="residual u_model - u_measured (mm)")
    reference = float(f"{largest:.1g}") if largest > 0 else 1.0
    ax.quiverkey(arrows, 0.80, 0.10, reference, f"{reference:g} mm", labelpos="E", coordinates="axes", color="white",
                 labelcolor="white")
    ax.set_xlim(0.0, image.shape[1] * pixel_size_mm[1])      # the sector lines stop at the image's edge
    ax.set_ylim(image.shape[0] * pixel_size_mm[0], 0.0)
    if patch_elements is not None and len(patch_elements):
        ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.set_title((f"{title}\n" if title else "") + f"residual of the identified model, arrows x{1 / scale:.0f}"
                 + (f"\nlargest share: {maps.worst_region}" if maps.worst_region else ""), fontsize=9, loc="left")
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def _step_label(entry: dict) -> str:
    if entry["action"] == "identified":
        return "identified"
    return f"{'+' if entry['action'] == 'added' else '-'} {entry['effect']}"


def path_figure(path: Path, steps: list[dict], agreement: float = FLOOR_AGREEMENT) -> Path:
    """The error falling (diagnosis-path.png): the misfit over the floor of each model of the stepwise path (log
    scale) against the step, the effect added or removed on each tick, the refits tried at each step in grey, the
    floor (1 x) and the error model's agreement with the measured errors (`agreement` x) marked."""
    figure, ax = plt.subplots(figsize=(max(4.5, 1.6 * len(steps) + 2.0), 3.8))
    x = np.arange(len(steps))
    ratios = [entry["misfit_over_floor"] for entry in steps]
    for k, entry in enumerate(steps):
        tried = [t["misfit_over_floor"] for t in entry.get("tried", []) if t.get("misfit_over_floor") is not None]
        ax.plot([k] * len(tried), tried, "o", color="0.6", markersize=4,
                label="refits tried (the identified fit's weights)" if k == 1 else None)
    ax.plot(x, ratios, "o-", color="tab:blue", linewidth=2, markersize=7, label="the path's model")
    for k, ratio in enumerate(ratios):
        ax.annotate(f"{ratio:.2f}", (k, ratio), textcoords="offset points", xytext=(6, 6), fontsize=8)
    ax.axhline(1.0, color="black", linewidth=1, label="noise floor (1 x)")
    ax.axhline(agreement, color="tab:green", linestyle="--", linewidth=1,
               label=f"error model's agreement ({agreement:g} x)")
    ax.set_yscale("log")
    low = min(0.8, 0.9 * min(ratios))
    ax.set_ylim(low, max(2.0, 1.5 * max(ratios)))
    ax.set_xticks(x, [_step_label(entry) for entry in steps], rotation=20, ha="right", fontsize=8)
    ax.set_xlabel("step")
    ax.set_ylabel("misfit / noise floor")
    ax.set_title("misfit over the noise floor, one effect at a time", fontsize=9, loc="left")
    ax.legend(fontsize=7, loc="upper right")
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def path_maps_figure(path: Path, image: np.ndarray, pixel_size_mm, maps: list, steps: list[dict]) -> Path:
    """The residual of each model of the path side by side (diagnosis-path-maps.png): the arrows of each panel on its
    own scale (said in its title: the pattern that is left), their colour on one scale for every panel (the error
    seen to fall)."""
    from scipy.spatial import cKDTree

    panels = len(maps)
    figure, axes = plt.subplots(1, panels, figsize=(3.9 * panels + 1.2, 4.6), squeeze=False)
    lengths = [np.hypot(*np.asarray(m.residual_mm, float).reshape(-1, 2).T) for m in maps]
    largest = max((float(v.max()) for v in lengths if v.size), default=1.0) or 1.0
    places = np.unique(np.asarray(maps[0].positions_mm, float), axis=0)
    spacing = float(np.median(cKDTree(places).query(places, k=2)[0][:, 1])) if len(places) > 1 else 1.0
    for k, (ax, m, entry, length) in enumerate(zip(axes[0], maps, steps, lengths)):
        image_axes(ax, image, pixel_size_mm)
        where = np.asarray(m.positions_mm, float)
        residual = np.asarray(m.residual_mm, float).reshape(-1, 2)
        own = float(length.max()) if length.size and length.max() > 0 else largest
        scale = own / (1.5 * spacing)
        arrows = ax.quiver(where[:, 0], where[:, 1], residual[:, 0], residual[:, 1], length, cmap="plasma",
                           angles="xy", scale_units="xy", scale=scale, width=0.004, clim=(0.0, largest))
        ax.set_xlim(0.0, image.shape[1] * pixel_size_mm[1])
        ax.set_ylim(image.shape[0] * pixel_size_mm[0], 0.0)
        if k:
            ax.set_ylabel("")
        ax.set_title(f"step {entry['step']}: {_step_label(entry)}\n{entry['misfit_over_floor']:.2f} x the floor, "
                     f"arrows x{1 / scale:.0f}", fontsize=8, loc="left")
    figure.colorbar(arrows, ax=list(axes[0]), shrink=0.8, label="residual u_model - u_measured (mm)")
    figure.suptitle("residual of each model of the path: arrows on each panel's scale, colour on one scale",
                    fontsize=9, x=0.01, ha="left")
    figure.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(figure)
    return Path(path)
