"""The image frame of a case and rigid motions in it.

Every position in a case is in millimetres in the frame of the unloaded image
I0 (docs/design.md, "The case folder"): origin at the top-left corner, x to the
right (columns), y downwards (rows); pixel (row i, column j) has its centre at
((j + 0.5) dx, (i + 0.5) dy), with ``pixel_size_mm = (dy, dx)`` (row, column).

A displacement field on the pixel grid is an array of shape (2, H, W) in mm,
component 0 = u_x (along columns), component 1 = u_y (along rows).

`RigidMotion` maps a point x to R(angle) (x - c) + c + t. With y pointing down
a positive angle turns the picture clockwise on screen. The second paper
(section 3.1) aligns the loaded image on the unloaded one by such a rotation
and translation of the bones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

DisplacementFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def pixel_centres_mm(shape: tuple[int, int], pixel_size_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Return (x_mm, y_mm), each of the given shape, at the pixel centres."""
    dy, dx = pixel_size_mm
    rows, cols = np.indices(shape, dtype=float)
    return (cols + 0.5) * dx, (rows + 0.5) * dy


def mm_to_index(x_mm, y_mm, pixel_size_mm) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (row, column) indices of positions given in mm."""
    dy, dx = pixel_size_mm
    return np.asarray(y_mm) / dy - 0.5, np.asarray(x_mm) / dx - 0.5


def index_to_mm(rows, cols, pixel_size_mm) -> tuple[np.ndarray, np.ndarray]:
    """Positions (x_mm, y_mm) of continuous (row, column) indices."""
    dy, dx = pixel_size_mm
    return (np.asarray(cols) + 0.5) * dx, (np.asarray(rows) + 0.5) * dy


def displacement_on_grid(displacement, shape: tuple[int, int], pixel_size_mm) -> np.ndarray:
    """Evaluate a displacement (callable u(x_mm, y_mm) or (2, H, W) array, mm) on the pixel grid."""
    if callable(displacement):
        x, y = pixel_centres_mm(shape, pixel_size_mm)
        ux, uy = displacement(x, y)
        return np.stack([np.broadcast_to(ux, shape), np.broadcast_to(uy, shape)]).astype(float)
    field = np.asarray(displacement, dtype=float)
    if field.shape != (2, *shape):
        raise ValueError(f"displacement field has shape {field.shape}, expected (2, {shape[0]}, {shape[1]})")
    return field


@dataclass(frozen=True)
class RigidMotion:
    """x -> R(angle_deg) (x - centre_mm) + centre_mm + translation_mm, all in mm."""

    angle_deg: float = 0.0
    translation_mm: tuple[float, float] = (0.0, 0.0)
    centre_mm: tuple[float, float] = (0.0, 0.0)

    @property
    def rotation(self) -> np.ndarray:
        a = np.deg2rad(self.angle_deg)
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    def apply(self, x_mm, y_mm) -> tuple[np.ndarray, np.ndarray]:
        (r00, r01), (r10, r11) = self.rotation
        cx, cy = self.centre_mm
        tx, ty = self.translation_mm
        dx, dy = np.asarray(x_mm) - cx, np.asarray(y_mm) - cy
        return r00 * dx + r01 * dy + cx + tx, r10 * dx + r11 * dy + cy + ty

    def inverse(self) -> "RigidMotion":
        """The motion that undoes this one, about the same centre."""
        cx, cy = self.centre_mm
        tx, ty = self.translation_mm
        (r00, r01), (r10, r11) = self.rotation.T
        return RigidMotion(-self.angle_deg, (-(r00 * tx + r01 * ty), -(r10 * tx + r11 * ty)), (cx, cy))

    def about(self, centre_mm: tuple[float, float]) -> "RigidMotion":
        """The same motion written about another centre (the translation changes, the map does not)."""
        tx, ty = self.apply(*centre_mm)
        return RigidMotion(self.angle_deg, (float(tx - centre_mm[0]), float(ty - centre_mm[1])), tuple(map(float, centre_mm)))
