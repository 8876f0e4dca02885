"""The diagnosis drawn on the unloaded image: the residual vectors and the place of a local change (diagnosis.png)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.plotting import DPI, image_axes, plt


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
