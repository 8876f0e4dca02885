"""3D lattice gradient noise for the k-space phantom's structure: vectorised, seeded, with its exact gradient.

Perlin's gradient noise in 3D (Perlin 2002, "Improving noise"): random unit gradients at the corners of a cubic
lattice, picked by hashing the corner's integer coordinates through a permutation table, each corner contributing
g . (f - corner) blended by the quintic fade 6t^5 - 15t^4 + 10t^3 along each axis. The lattice may be anisotropic
(cells of cx, cy, cz mm: a field elongated along the leg has cz >> cx) and rotated (`rotation`, applied to the
point before the lattice: an elongation oblique to the leg). The value is scaled to unit standard deviation
(measured once on a probe), and the gradient (per mm, in the unrotated frame) comes with it, so that a level set's
distance |n| / |grad n| is at hand for drawing sheets with partial volume. Eight corner evaluations per point and
no per-point sum over Fourier modes: a few tens of ns per point and corner.
"""

from __future__ import annotations

import numpy as np

TABLE_SIZE = 4096      # lattice period 4096 cells along each axis: no visible repetition


class GradientNoise3D:
    """Unit-variance 3D gradient noise with cells `cell_mm` ((cx, cy, cz) or one size) (module text)."""

    def __init__(self, seed, cell_mm, rotation: np.ndarray | None = None):
        rng = np.random.default_rng(seed)
        vectors = rng.standard_normal((TABLE_SIZE, 3))
        self._gradients = vectors / np.linalg.norm(vectors, axis=1)[:, None]
        self._permutation = rng.permutation(TABLE_SIZE)
        self.cell_mm = np.broadcast_to(np.asarray(cell_mm, float), (3,)).copy()
        if np.any(self.cell_mm <= 0):
            raise ValueError(f"noise cells must be positive sizes in mm, got {self.cell_mm}")
        self.rotation = None if rotation is None else np.asarray(rotation, float)
        self._scale = 1.0
        probe = np.random.default_rng(12345).uniform(0.0, 300.0, (3, 60000)) * self.cell_mm[:, None]
        self._scale = 1.0 / float(np.std(self(*probe)))

    def __call__(self, x, y, z, gradient: bool = False):
        """Noise at points (mm); with gradient, also (d/dx, d/dy, d/dz) per mm."""
        x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
        if self.rotation is not None:
            r = self.rotation
            x, y, z = (r[0, 0] * x + r[0, 1] * y + r[0, 2] * z, r[1, 0] * x + r[1, 1] * y + r[1, 2] * z,
                       r[2, 0] * x + r[2, 1] * y + r[2, 2] * z)
        u, v, w = x / self.cell_mm[0], y / self.cell_mm[1], z / self.cell_mm[2]
        i, j, k = (np.floor(c).astype(np.int64) for c in (u, v, w))
        fu, fv, fw = u - i, v - j, w - k
        su, sv, sw = _fade(fu), _fade(fv), _fade(fw)
        mask, p = TABLE_SIZE - 1, self._permutation
        first = [p[(i + a) & mask] for a in (0, 1)]                      # the hash's first level, shared by corners
        second = [[p[(first[a] + j + b) & mask] for b in (0, 1)] for a in (0, 1)]
        value = np.zeros(u.shape)
        if gradient:
            du, dv, dw = np.zeros(u.shape), np.zeros(u.shape), np.zeros(u.shape)
            tu, tv, tw = _fade_slope(fu), _fade_slope(fv), _fade_slope(fw)
        for a in (0, 1):
            wu = su if a else 1.0 - su
            for b in (0, 1):
                wv = sv if b else 1.0 - sv
                for c in (0, 1):
                    ww = sw if c else 1.0 - sw
                    g = self._gradients[p[(second[a][b] + k + c) & mask]]
                    ou, ov, ow = fu - a, fv - b, fw - c
                    dot = g[..., 0] * ou + g[..., 1] * ov + g[..., 2] * ow
                    weight = wu * wv * ww
                    value += weight * dot
                    if gradient:
                        du += weight * g[..., 0] + (tu if a else -tu) * wv * ww * dot
                        dv += weight * g[..., 1] + wu * (tv if b else -tv) * ww * dot
                        dw += weight * g[..., 2] + wu * wv * (tw if c else -tw) * dot
        value *= self._scale
        if not gradient:
            return value
        grad = [d * self._scale / cell for d, cell in zip((du, dv, dw), self.cell_mm)]
        if self.rotation is not None:   # d/dx_original = R^T d/dx_rotated
            r = self.rotation
            grad = [r[0, n] * grad[0] + r[1, n] * grad[1] + r[2, n] * grad[2] for n in range(3)]
        return value, grad[0], grad[1], grad[2]


def _fade(t):
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def _fade_slope(t):
    return 30.0 * t * t * (t - 1.0) ** 2


def tilt_rotation(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """The rotation that tilts the z axis by tilt_deg towards the in-plane direction azimuth_deg."""
    t, a = np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg)
    axis = np.array([-np.sin(a), np.cos(a), 0.0])        # perpendicular to the tilt's direction, in the plane
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1.0 - np.cos(t)) * K @ K
