"""The figure the setup writes: the muscle compartments found at the septa of I0, named by their place in the leg, for
the user to check (compartments.png)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import matplotlib

from ..core.plotting import DPI, image_axes, plt


def compartments_figure(path: Path, image: np.ndarray, pixel_size_mm, compartments) -> Path:
    """The muscle compartments found in I0 (`imaging.compartments`), each tinted and named at its centroid,
    over the septa they rest on (red), for the user to check before trusting the `compartments` effect."""
    from ..core.tissues import FIRST_COMPARTMENT
    from ..model.regions import compartment_names

    figure, ax = plt.subplots(figsize=(7.5, 7.0))
    image_axes(ax, image, pixel_size_mm)
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
