"""A DIC window's shape function: how the window's pixels may move, first order (affine) or second order (quadratic).

A window's map is x' = x + u(x), u a polynomial in the offsets (dx, dy) from the window centre, the same basis for
both components:
- first order (affine): 1, dx, dy, so p = (u, u_x, u_y, v, v_x, v_y);
- second order (quadratic): 1, dx, dy, dx^2 / 2, dx dy, dy^2 / 2, so p = (u, u_x, u_y, u_xx, u_xy, u_yy, v, ...)
  (Lu and Cary, Exp. Mech. 40, 2000, eq. 3). A second-order window follows a field that bends inside it, a crest
  or the fat pressed against stiffer muscle, which an affine window averages over its side (the DIC Challenge 2.0's
  star: the quadratic codes' spatial resolution is half the affine codes' at the same noise).

Inverse-compositional Gauss-Newton composes the current map with the inverse of each step's, W <- W o W(dp)^-1. An
affine map composes exactly as a 3x3 matrix on (dx, dy, 1). A quadratic map is written as the 6x6 matrix that takes
the monomials (dx^2, dx dy, dy^2, dx, dy, 1) to those of (x', y') with the terms above second order dropped (Gao,
Cheng, Su and Xiong, Opt. Lasers Eng. 65, 2015, eqs. 8-10): the composition and the inverse are then those of the
matrices, exact to first order in the step, so Gauss-Newton converges to the same stationary point of the
zero-normalised SSD. In both the last three monomials are (dx, dy, 1): rows -3 and -2 of a map's matrix are x' and
y' over the monomials, and its last column holds the window centre's displacement.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

SHAPE_ORDERS = {"affine": 1, "quadratic": 2}   # the words the command line takes, and their orders

# the monomials of a quadratic map's 6x6 matrix, as exponents of (dx, dy); the affine ones are its last three
_QUADRATIC_MONOMIALS = ((2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0))


@dataclass(frozen=True)
class WindowShape:
    """A window's shape function of `order` 1 (affine) or 2 (quadratic) (module text)."""

    order: int = 1

    def __post_init__(self):
        if self.order not in (1, 2):
            raise ValueError(f"a window's shape function is of order 1 (affine) or 2 (quadratic), not {self.order}")

    @classmethod
    def named(cls, name: str) -> "WindowShape":
        """The shape called `name` ("affine" or "quadratic"), the word `calfit measure --window-shape` takes."""
        if name not in SHAPE_ORDERS:
            raise ValueError(f"the window shape is 'affine' or 'quadratic', not {name!r}")
        return cls(SHAPE_ORDERS[name])

    @property
    def name(self) -> str:
        return next(name for name, order in SHAPE_ORDERS.items() if order == self.order)

    @property
    def terms(self) -> int:
        """Basis functions per displacement component: 3 or 6."""
        return 3 if self.order == 1 else 6

    @property
    def parameters(self) -> int:
        return 2 * self.terms

    @property
    def translation(self) -> list[int]:
        """The indices of (u, v) in p."""
        return [0, self.terms]

    @property
    def deformation(self) -> list[int]:
        """The indices in p of everything but the translation: the displacement gradient (and, quadratic, its
        derivatives), whose step Gauss-Newton's convergence test bounds apart from the translation's."""
        return [k for k in range(self.parameters) if k not in self.translation]

    def basis(self, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """(terms, n) the basis at the offsets (dx, dy): what d(x + u)/dp holds for either component."""
        dx, dy = np.ravel(dx).astype(float), np.ravel(dy).astype(float)
        columns = [np.ones_like(dx), dx, dy]
        if self.order == 2:
            columns += [0.5 * dx * dx, dx * dy, 0.5 * dy * dy]
        return np.stack(columns)

    def monomials(self, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """(terms, n) the monomials a map's matrix acts on, ending with (dx, dy, 1)."""
        dx, dy = np.ravel(dx).astype(float), np.ravel(dy).astype(float)
        if self.order == 1:
            return np.stack([dx, dy, np.ones_like(dx)])
        return np.stack([dx ** a * dy ** b for a, b in _QUADRATIC_MONOMIALS])

    def matrix(self, p: np.ndarray) -> np.ndarray:
        """(terms, terms) the matrix of the map x + u_p(x) on the monomials (module text)."""
        p = np.asarray(p, float)
        if self.order == 1:
            u, ux, uy, v, vx, vy = p
            return np.array([[1.0 + ux, uy, u], [vx, 1.0 + vy, v], [0.0, 0.0, 1.0]])
        u, ux, uy, uxx, uxy, uyy, v, vx, vy, vxx, vxy, vyy = p
        rows = np.array([[0.5 * uxx, uxy, 0.5 * uyy, 1.0 + ux, uy, u],
                         [0.5 * vxx, vxy, 0.5 * vyy, vx, 1.0 + vy, v]])
        return lift(rows)

    def translated(self, displacement) -> np.ndarray:
        """The matrix of a pure translation by (d_col, d_row) px."""
        p = np.zeros(self.parameters)
        p[self.translation] = displacement
        return self.matrix(p)

    def from_rows(self, rows: np.ndarray) -> np.ndarray:
        """The map's matrix from its two rows x', y' over the monomials ((2, terms), as the compiled loops return it)."""
        rows = np.asarray(rows, float)
        if self.order == 1:
            return np.vstack([rows, [0.0, 0.0, 1.0]])
        return lift(rows)

    def moments(self, size: int, weights: np.ndarray | None = None) -> np.ndarray:
        """M = sum over a size x size window of w X^T X, X the basis at each pixel (w = 1 by default, else the (size,
        size) `weights`), for both displacement components (parameters x parameters)."""
        basis = self.window_basis(size)
        weights = np.ones(size * size) if weights is None else np.asarray(weights, float).ravel()
        moments = np.zeros((self.parameters, self.parameters))
        moments[:self.terms, :self.terms] = moments[self.terms:, self.terms:] = (basis * weights) @ basis.T
        return moments

    def window_basis(self, size: int) -> np.ndarray:
        """(terms, size^2) the basis at a size x size window's pixels, row-major, read-only (`window_offsets`)."""
        return _over_window(self, size, "basis")

    def window_monomials(self, size: int) -> np.ndarray:
        """(terms, size^2) the monomials at a size x size window's pixels, row-major, read-only."""
        return _over_window(self, size, "monomials")


@functools.lru_cache(maxsize=16)
def window_offsets(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) offsets of a size x size window's pixels from its centre, read-only: every window of a
    correlation asks for the same grid several times, and making it anew took several per cent of a compiled window."""
    offset_rows, offset_cols = np.mgrid[0:size, 0:size].astype(float) - (size - 1) / 2.0
    offset_rows.flags.writeable = offset_cols.flags.writeable = False
    return offset_rows, offset_cols


@functools.lru_cache(maxsize=64)
def _over_window(shape: WindowShape, size: int, kind: str) -> np.ndarray:
    """shape.basis or shape.monomials at the window's offsets, made once per shape and size."""
    offset_rows, offset_cols = window_offsets(size)
    values = getattr(shape, kind)(offset_cols, offset_rows)
    values.flags.writeable = False
    return values


AFFINE = WindowShape(1)
QUADRATIC = WindowShape(2)


def _truncated_product_table() -> np.ndarray:
    """(6, 36) T with T (a outer b).ravel() the coefficients of the product of two polynomials over the quadratic
    monomials, the terms above second order dropped."""
    table = np.zeros((6, 36))
    index = {exponents: k for k, exponents in enumerate(_QUADRATIC_MONOMIALS)}
    for i, (ai, bi) in enumerate(_QUADRATIC_MONOMIALS):
        for j, (aj, bj) in enumerate(_QUADRATIC_MONOMIALS):
            if ai + bi + aj + bj <= 2:
                table[index[(ai + aj, bi + bj)], 6 * i + j] = 1.0
    return table


_PRODUCT = _truncated_product_table()


def lift(rows: np.ndarray) -> np.ndarray:
    """The 6x6 matrix taking the monomials (dx^2, dx dy, dy^2, dx, dy, 1) to those of (x', y'), the map's two rows
    `rows` ((2, 6) over the same monomials), each product's terms above second order dropped (module text)."""
    x, y = np.asarray(rows, float)
    products = _PRODUCT @ np.stack([np.outer(x, x).ravel(), np.outer(x, y).ravel(), np.outer(y, y).ravel()], axis=1)
    return np.vstack([products.T, x, y, np.eye(6)[5]])
