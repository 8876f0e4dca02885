"""What every figure shares: matplotlib on the Agg backend (no display needed), the resolution, and the axes of an
image in mm of the image frame of I0 (x right, y down) with its landmarks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402,F401  (the backend is chosen before pyplot is imported)

DPI = 150


def image_axes(ax, image: np.ndarray, pixel_size_mm) -> None:
    dy, dx = pixel_size_mm
    height, width = image.shape
    low, high = np.percentile(image, [1, 99.5])
    ax.imshow(image, cmap="gray", vmin=low, vmax=high, extent=(0, width * dx, height * dy, 0), interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")


def save(figure, path: Path) -> Path:
    figure.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(figure)
    return Path(path)


def extent(shape, pixel_size_mm) -> tuple[float, float, float, float]:
    return (0.0, shape[1] * pixel_size_mm[1], shape[0] * pixel_size_mm[0], 0.0)


def landmark_markers(ax, landmarks: dict[str, tuple[float, float]], colour: str = "white") -> None:
    """Numbered markers at the landmarks, named in the legend (1 great_saphenous, ...)."""
    for number, (name, (x, y)) in enumerate(landmarks.items(), start=1):
        ax.plot(x, y, "o", markersize=9, markerfacecolor="black", markeredgecolor=colour, markeredgewidth=1.2,
                label=f"{number} {name}")
        ax.text(x, y, str(number), color=colour, fontsize=6.5, ha="center", va="center", weight="bold")


def scattered_map(positions_mm: np.ndarray, values: np.ndarray, mask: np.ndarray, pixel_size_mm) -> np.ndarray:
    """Values at scattered points interpolated linearly over the pixels of `mask` (NaN elsewhere and outside the
    points' convex hull)."""
    from scipy.interpolate import griddata

    rows, cols = np.nonzero(mask)
    out = np.full(mask.shape, np.nan)
    if len(positions_mm) >= 3:
        out[rows, cols] = griddata(positions_mm, values, ((cols + 0.5) * pixel_size_mm[1], (rows + 0.5) * pixel_size_mm[0]),
                                   method="linear")
    return out


def zoom_to(ax, mask: np.ndarray, pixel_size_mm, margin_mm: float = 6.0) -> None:
    """Show only the part of the image around the mask (the leg), axes still in mm of the image frame."""
    rows, cols = np.nonzero(mask)
    if rows.size:
        dy, dx = pixel_size_mm
        ax.set_xlim(cols.min() * dx - margin_mm, (cols.max() + 1) * dx + margin_mm)
        ax.set_ylim((rows.max() + 1) * dy + margin_mm, rows.min() * dy - margin_mm)
