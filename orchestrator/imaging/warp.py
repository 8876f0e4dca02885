"""Image warping of the first paper (section 2.1.2).

The warped image I is made from the loaded image I1 by the displacement
u = (u, v) of the FE model: i(x, y) = i1(x + u, y + v), the grey level at the
generally non-integer position (x + u, y + v) being interpolated linearly
from the surrounding pixels of I1 (step 3 of section 2.1.2). Here u is given
on the pixel grid of I0 as a (2, H, W) array in mm (component 0 along x,
component 1 along y) or as a callable u(x_mm, y_mm); interpolating an FE
nodal field onto the pixels is the job of the meshing/results rooms.

Label maps are warped the same way with nearest-neighbour sampling, which
gives the segmentation of the warped image without segmenting it again.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..core.frame import displacement_on_grid


def sample_coordinates(shape: tuple[int, int], displacement, pixel_size_mm) -> np.ndarray:
    """(2, H, W) continuous (row, column) indices of x + u(x) for every pixel x of the grid."""
    field = displacement_on_grid(displacement, shape, pixel_size_mm)
    dy, dx = pixel_size_mm
    rows, cols = np.indices(shape, dtype=float)
    return np.stack([rows + field[1] / dy, cols + field[0] / dx])


def warp_image(loaded: np.ndarray, displacement, pixel_size_mm, *, order: int = 1, cval: float = 0.0) -> np.ndarray:
    """I(x) = I1(x + u(x)) with linear interpolation (order=1), cval outside I1."""
    coordinates = sample_coordinates(loaded.shape, displacement, pixel_size_mm)
    return ndimage.map_coordinates(np.asarray(loaded, float), coordinates, order=order, mode="constant", cval=cval)


def warp_labels(labels: np.ndarray, displacement, pixel_size_mm) -> np.ndarray:
    """Labels of the warped image: L(x) = L1(x + u(x)), nearest neighbour, background (0) outside."""
    coordinates = sample_coordinates(labels.shape, displacement, pixel_size_mm)
    return ndimage.map_coordinates(labels, coordinates, order=0, mode="constant", cval=0)
