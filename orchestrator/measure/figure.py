"""The measured displacements drawn on the unloaded image (measurements.png)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.plotting import DPI, image_axes, plt


def dic_vectors_figure(path: Path, image: np.ndarray, pixel_size_mm, table, summary: dict) -> Path:
    """`dic_vectors_plot` written to path."""
    figure = dic_vectors_plot(image, pixel_size_mm, table, summary)
    figure.savefig(path, dpi=DPI)
    plt.close(figure)
    return Path(path)


def dic_vectors_plot(image: np.ndarray, pixel_size_mm, table, summary: dict):
    """The measured displacements drawn on the unloaded image: kept windows as arrows coloured by magnitude
    (mm, with a colour bar), rejected windows as crosses, a scale arrow in the image's lower right corner (inside
    the axes, clear of the title), the counts in the legend at the lower left. Returns the figure."""
    kept = table.kept
    figure, ax = plt.subplots(figsize=(7.5, 7.0))
    image_axes(ax, image, pixel_size_mm)
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
    ax.quiverkey(arrows, 0.80, 0.05, reference, f"{reference:g} mm", labelpos="E", coordinates="axes", color="white",
                 labelcolor="white")
    ax.plot([], [], marker=r"$\rightarrow$", linestyle="none", color="tab:green",
            label=f"kept windows ({int(kept.sum())} of {len(kept)})")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    ax.set_title(f"DIC, {summary['window_px']} px windows ({summary['window_px'] * pixel_size_mm[1]:.1f} mm), "
                 f"arrows x{1 / scale:.0f}", fontsize=10)
    figure.tight_layout()
    return figure
