"""Figures a user reads: matplotlib, axes in mm (image frame of I0: x right, y down), colour bars with values
and units, perceptually uniform colour maps. Written as PNG with the Agg backend (no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend is chosen before pyplot is imported)

DPI = 150


def _image_axes(ax, image: np.ndarray, pixel_size_mm) -> None:
    dy, dx = pixel_size_mm
    height, width = image.shape
    low, high = np.percentile(image, [1, 99.5])
    ax.imshow(image, cmap="gray", vmin=low, vmax=high, extent=(0, width * dx, height * dy, 0), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")


def dic_vectors_figure(path: Path, image: np.ndarray, pixel_size_mm, table, summary: dict) -> Path:
    """The measured displacements drawn on the unloaded image: kept windows as arrows coloured by magnitude
    (mm, with a colour bar), rejected windows as crosses, a scale arrow, the counts in the legend."""
    kept = table.kept
    figure, ax = plt.subplots(figsize=(7.5, 7.0))
    _image_axes(ax, image, pixel_size_mm)
    position, displacement = table.position_mm, table.displacement_mm
    magnitude = np.hypot(displacement[kept, 0], displacement[kept, 1])
    largest = float(np.max(magnitude)) if magnitude.size else 1.0
    spacing = summary.get("step_px", 16) * min(pixel_size_mm)
    scale = largest / (1.5 * spacing) if largest > 0 else 1.0   # the largest arrow spans 1.5 window steps
    arrows = ax.quiver(position[kept, 0], position[kept, 1], displacement[kept, 0], displacement[kept, 1], magnitude,
                       cmap="viridis", angles="xy", scale_units="xy", scale=scale, width=0.003)
    figure.colorbar(arrows, ax=ax, shrink=0.8, label="displacement relative to the bones (mm)")
    rejected = ~kept & np.all(np.isfinite(position), axis=1)
    if rejected.any():
        ax.plot(position[rejected, 0], position[rejected, 1], "x", color="tab:red", markersize=4,
                label=f"rejected windows ({int(rejected.sum())})")
    reference = float(f"{largest:.1g}") if largest > 0 else 1.0
    ax.quiverkey(arrows, 0.80, 1.02, reference, f"{reference:g} mm", labelpos="E", coordinates="axes")
    ax.plot([], [], marker=r"$\rightarrow$", linestyle="none", color="tab:green",
            label=f"kept windows ({int(kept.sum())} of {len(kept)})")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.set_title(f"DIC, {summary['window_px']} px windows ({summary['window_px'] * pixel_size_mm[1]:.1f} mm), "
                 f"arrows x{1 / scale:.0f}", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def compartments_figure(path: Path, image: np.ndarray, pixel_size_mm, compartments) -> Path:
    """The muscle compartments found in I0 (`imaging.compartments`), each tinted and named at its centroid,
    over the septa they rest on (red), for the user to check before trusting the `compartments` effect."""
    from .imaging.compartments import FIRST_COMPARTMENT
    from .regions import compartment_names

    figure, ax = plt.subplots(figsize=(7.5, 7.0))
    _image_axes(ax, image, pixel_size_mm)
    dy, dx = pixel_size_mm
    extent = (0, image.shape[1] * dx, image.shape[0] * dy, 0)
    labels = compartments.labels
    found = sorted(int(v) for v in np.unique(labels[labels >= FIRST_COMPARTMENT]))
    names = compartment_names(labels, pixel_size_mm) if found else {}
    colours = plt.get_cmap("tab10")
    tint = np.zeros(image.shape + (4,))
    for k, label in enumerate(found):
        tint[labels == label] = (*colours(k % 10)[:3], 0.35)
        rows, cols = np.nonzero(labels == label)
        ax.text((cols.mean() + 0.5) * dx, (rows.mean() + 0.5) * dy, str(k + 1), color="white", fontsize=12,
                ha="center", va="center", weight="bold")
        ax.plot([], [], "s", color=colours(k % 10), label=names[label])
    ax.imshow(tint, extent=extent, interpolation="nearest")
    septa = np.ma.masked_where(~compartments.septa, np.ones(image.shape))
    ax.imshow(septa, cmap=matplotlib.colors.ListedColormap(["red"]), extent=extent, interpolation="nearest")
    ax.plot([], [], "-", color="red", label="septa found")
    ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
    ax.set_title(f"muscle compartments found at the septa of I0: {len(found)}" if found else
                 "no muscle compartments found: no septum closes one", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def diagnosis_figure(path: Path, image: np.ndarray, pixel_size_mm, maps, mesh, patch_elements: np.ndarray | None = None,
                     place: str = "") -> Path:
    """The residual of the identified model (u_model - u_measured) as arrows coloured by length (mm, colour bar)
    on the unloaded image, the 30-degree sectors of `regions` about the leg centre with their anatomical names, and
    the place of the proposed local stiffness change shaded."""
    from matplotlib.collections import PolyCollection
    from scipy.spatial import cKDTree

    positions = np.asarray(maps.positions_mm, float)
    residual = np.asarray(maps.residual_mm, float)
    centre = np.asarray(maps.centre_mm, float)
    figure, ax = plt.subplots(figsize=(8.0, 7.5))
    _image_axes(ax, image, pixel_size_mm)
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
    spacing = float(np.median(cKDTree(positions).query(positions, k=2)[0][:, 1])) if len(positions) > 1 else 1.0
    scale = largest / (1.5 * spacing) if largest > 0 else 1.0
    arrows = ax.quiver(positions[:, 0], positions[:, 1], residual[:, 0], residual[:, 1], length, cmap="magma",
                       angles="xy", scale_units="xy", scale=scale, width=0.003)
    figure.colorbar(arrows, ax=ax, shrink=0.8, label="residual u_model - u_measured (mm)")
    reference = float(f"{largest:.1g}") if largest > 0 else 1.0
    ax.quiverkey(arrows, 0.80, 1.02, reference, f"{reference:g} mm", labelpos="E", coordinates="axes")
    if patch_elements is not None and len(patch_elements):
        ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.set_title(f"residual of the identified model, arrows x{1 / scale:.0f}"
                 + (f"; largest share: {maps.worst_region}" if maps.worst_region else ""), fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)
