"""What a DIC window measures of a displacement field, and how the errors of overlapping windows correlate.

A window does not measure the displacement at its centre. Linearised about the match, IC-GN with an affine
shape function (`dic`) returns the affine field a_p that best explains the grey-level change over the window,
p = H^-1 S^T e with e(x) = grad f(x) . u(x) (grad f of the reference image, S the steepest-descent images,
H = S^T S): the gradient-weighted least-squares affine fit of u over the window,

    u_window = sum_x K(x) u(x),   K(x) = [rows u, v of H^-1 S(x)^T] grad f(x)^T   (a 2x2 block per pixel).

Where u is not affine over the window (a fat layer thinner than the window, the skin edge), this differs from
u(centre) by far more than the noise: comparing a model with DIC at window centres is biased by that much.
The model is therefore observed as DIC observes it: `observation` is the sparse matrix of the K(x), applied to
the model's displacement on the pixels (what is known as DIC-levelled finite-element data).

Both images are prefiltered (`prefilter`), so S and grad f are those of the prefiltered reference, and a window's
error is sum_y B~_i(y) e(y) over the raw errors e, with B_i(x) = rows u, v of H_s,i^-1 S_i(x)^T (H_s the Gauss-Newton
matrix of the noiseless reference, `dic.denoised_hessian`) and B~_i = G * B_i its spread by the prefilter, reaching
the kernel's radius beyond the window. Overlapping windows share raw pixels, so their errors are correlated: with
s_i^2 the intensity-noise variance of window i in the tissue, rho its Rician share at each pixel (0.43 in air,
`prefilter.rician_variance_ratio`) and s_edge^2 the variance of the position of the images' edges,

    Cov(u_i, u_j) = sum_{y in both} B~_i(y) [s_i s_j rho(y) + s_edge^2 |grad I0(y)|^2] B~_j(y)^T,

which on the diagonal is the covariance each window reports (with s_edge = 0) and is positive semi-definite (a
Gram matrix scaled by positive weights). `covariance` assembles it for the fit's weighting, its noise floor and its
Monte-Carlo intervals.

The fat's chemical shift (`chemical_shift`). An MR image is the water's signal plus the fat's, the fat's shown
displaced by delta along the readout, the same delta in both sessions and fixed to the scanner. A fat feature
shown at x in I0 is the fat at x - delta; in I1 the loaded fat at y shows at y + delta, and with the bones' motion
M (rotation R) taken out of the match, that feature moves by u(x - delta) + (R^T - I) delta, where a water
feature moves by u(x). Linearised, grad f = grad W + grad F splits each K(x) into the water's and the fat's
parts, K = K_w + K_f (K_f from the gradient of the fat's share of I0, `chemical_shift.fat_signal`), and a window
measures

    u_window = sum_x K_w(x) u(x) + K_f(x) u(x - delta)  +  sum_x K_f(x) (R^T - I) delta:

`observation(delta)` is the first part, the model read at the pixels and at the pixels less delta; the second,
a constant for each window (`fat_offsets`), is taken out of the data (`measure.dic_measurements`). At 1.4 px of
0.41 mm and a turn of 1.9 degrees between the sessions, (R^T - I) delta is 0.019 mm, and u(x - delta) differs from
u(x) by up to 0.02 mm where the fat is compressed (3 % strain over 0.57 mm): both the size of a window's noise in
the fat.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from scipy import ndimage, sparse
from scipy.spatial import cKDTree

from .dic import (
    denoised_hessian,
    edge_strength,
    on_window_square,
    spline_gradient,
    window_pixel_sets,
    zero_normalised_steepest_descent,
)
from .prefilter import Prefilter, rician_variance_ratio
from .shape import AFFINE, WindowShape


class _WindowBasis:
    """What the operators of one set of windows share: the prefiltered reference, its gradients and each prefiltered
    pixel's noise variance over the tissue's, as `dic.correlate` weighs it."""

    def __init__(self, reference: np.ndarray, reference_noise_sigma: float, prefilter: Prefilter, gradients=None,
                 window_shape: WindowShape = AFFINE):
        self.shape = reference.shape
        self.window_shape = window_shape
        self.prefilter = prefilter
        self.reference_noise_sigma = float(reference_noise_sigma)
        self.smooth = prefilter(reference)
        self.grad_rows, self.grad_cols = gradients if gradients is not None else spline_gradient(self.smooth)
        self.noise_ratio = (prefilter.squared_kernel_response(rician_variance_ratio(reference, reference_noise_sigma))
                            / prefilter.noise_gain)

    def window(self, row: int, col: int, size: int, used: np.ndarray):
        """(rows, cols, fx, fy, steepest, hessian, signal) of the window centred at (row, col): its pixels, the
        reference's gradients there, its zero-normalised steepest-descent images and Gauss-Newton matrix, and that
        matrix less the noise's share (`dic.denoised_hessian`; None: the window holds less texture than noise)."""
        r0, c0 = row - size // 2, col - size // 2
        if r0 < 0 or c0 < 0 or r0 + size > self.shape[0] or c0 + size > self.shape[1]:
            raise ValueError(f"the window centred at row {row}, column {col} does not fit in the image")
        rows, cols = np.mgrid[r0:r0 + size, c0:c0 + size]
        fx, fy = self.grad_cols[rows, cols], self.grad_rows[rows, cols]
        steepest, hessian = zero_normalised_steepest_descent(self.smooth[rows, cols], fx, fy, used, self.window_shape)
        signal = denoised_hessian(hessian, size, self.reference_noise_sigma, self.prefilter.derivative_noise_gain,
                                  np.where(used.reshape(size, size), self.noise_ratio[rows, cols], 0.0),
                                  self.window_shape)
        return rows, cols, fx, fy, steepest, hessian, signal


def textured(reference: np.ndarray, centres_rc, window_px: int, reference_noise_sigma: float,
             prefilter: Prefilter | None = None, pixel_masks=None, window_shape: WindowShape = AFFINE) -> np.ndarray:
    """(N,) True where a window's texture rises above the noise of reference_noise_sigma (its Gauss-Newton matrix
    less the noise's share is positive definite, `dic.denoised_hessian`): the windows whose operators exist. A
    window matched with the images' own noise estimate may fall below the noise that the windows' residuals then
    calibrate; `measure.measure_dic` rejects it and counts it, rather than failing every other window with it."""
    basis = _WindowBasis(np.asarray(reference, float), reference_noise_sigma,
                         Prefilter() if prefilter is None else prefilter, window_shape=window_shape)
    centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
    pixel_sets = window_pixel_sets(pixel_masks, len(centres), int(window_px))
    return np.array([basis.window(row, col, int(window_px), used)[-1] is not None
                     for (row, col), used in zip(centres, pixel_sets)], bool)


class WindowOperators:
    """The linear maps B~_i and K_i of a set of square windows on a reference image (module text), for windows
    correlated on images smoothed by `prefilter` (default: `dic.correlate`'s), each over the pixels it matched
    (`pixel_masks`, as `dic.correlate` takes them; None: whole squares), with the shape function `window_shape`
    (affine by default, as `dic.correlate`'s `shape`)."""

    def __init__(self, reference: np.ndarray, centres_rc, window_px: int, pixel_size_mm, reference_noise_sigma: float,
                 gradients=None, prefilter: Prefilter | None = None, pixel_masks=None,
                 fat_signal: np.ndarray | None = None, window_shape: WindowShape = AFFINE):
        reference = np.asarray(reference, float)
        self.shape = tuple(np.shape(reference))
        self.centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
        self.window_px = int(window_px)
        self.window_shape = window_shape
        self.prefilter = Prefilter() if prefilter is None else prefilter
        dy, dx = (float(v) for v in pixel_size_mm)
        self.to_mm = np.array([dx, dy])
        basis = _WindowBasis(reference, reference_noise_sigma, self.prefilter, gradients, window_shape)
        centre = window_shape.translation
        self._reference = reference
        self.reference_noise_sigma = float(reference_noise_sigma)
        size, reach = self.window_px, self.prefilter.radius
        spread_rows, spread_cols = np.mgrid[-reach:size + reach, -reach:size + reach]
        self.pixels = []        # flat indices of the pixels each window matched
        self.K = []             # (2, 2, n) per window: centre displacement (px) per displacement (px) of its n pixels
        self.noise_pixels = []  # flat indices of the raw pixels whose error reaches each window (inside the image)
        self.B = []             # (2, len(noise_pixels)) per window: B~, px per raw intensity unit
        # the fat's part of each K (module text, the chemical shift): grad f split into the fat's and the water's
        fat_rows, fat_cols = (spline_gradient(self.prefilter(np.asarray(fat_signal, float))) if fat_signal is not None
                              else (None, None))
        self.K_fat = [] if fat_signal is not None else None
        for (row, col), used in zip(self.centres, window_pixel_sets(pixel_masks, len(self.centres), size)):
            rows, cols, fx, fy, steepest, hessian, signal = basis.window(row, col, size, used)
            if signal is None:
                raise ValueError(f"the window centred at row {row}, column {col} holds less texture than noise")
            r0, c0 = rows[0, 0], cols[0, 0]
            self.pixels.append((rows * self.shape[1] + cols).ravel()[used])
            fit = np.linalg.solve(hessian, steepest.T)[centre]
            self.K.append(fit[:, None, :] * np.stack([fx.ravel()[used], fy.ravel()[used]])[None, :, :])
            if self.K_fat is not None:
                fat_x, fat_y = fat_cols[rows, cols].ravel()[used], fat_rows[rows, cols].ravel()[used]
                self.K_fat.append(fit[:, None, :] * np.stack([fat_x, fat_y])[None, :, :])
            spread = self.prefilter.spread(on_window_square(np.linalg.solve(signal, steepest.T)[centre], used, size))
            reach_rows, reach_cols = (spread_rows + r0).ravel(), (spread_cols + c0).ravel()
            inside = ((reach_rows >= 0) & (reach_rows < self.shape[0]) & (reach_cols >= 0)
                      & (reach_cols < self.shape[1]))
            self.noise_pixels.append(reach_rows[inside] * self.shape[1] + reach_cols[inside])
            self.B.append(spread.reshape(2, -1)[:, inside])

    def __len__(self) -> int:
        return len(self.centres)

    def _assemble(self, maps) -> tuple[sparse.csr_matrix, np.ndarray]:
        """(O, pixels): the sparse (2N, 2P) map of the per-window blocks `maps` (K or K_fat) from the displacement
        (mm, interleaved u_x, u_y) at the P pixels `pixels` (flat indices, row-major) to the N windows (mm)."""
        pixels, inverse = np.unique(np.concatenate(self.pixels), return_inverse=True)
        rows, cols, values = [], [], []
        start = 0
        for i, (own, k) in enumerate(zip(self.pixels, maps)):
            local = inverse[start:start + own.size]
            start += own.size
            for a in range(2):
                for b in range(2):
                    rows.append(np.full(own.size, 2 * i + a))
                    cols.append(2 * local + b)
                    # mm in, mm out: u_a(px) = u_a(mm) / h_a, centre_a(mm) = h_a centre_a(px)
                    values.append(k[a, b] * self.to_mm[a] / self.to_mm[b])
        matrix = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(2 * len(self), 2 * len(pixels)))
        return matrix, pixels

    def _pixel_positions(self, pixels: np.ndarray) -> np.ndarray:
        rows, cols = np.divmod(pixels, self.shape[1])
        dx, dy = self.to_mm
        return np.column_stack([(cols + 0.5) * dx, (rows + 0.5) * dy])

    def observation(self, fat_shift_mm=None) -> tuple[sparse.csr_matrix, np.ndarray]:
        """(O, positions): O is the sparse (2N, 2Q) map from the displacement (mm, interleaved u_x, u_y) at the Q
        positions (mm, image frame) to what the N windows measure (mm, interleaved). The positions are the pixels
        the windows matched; with the fat's chemical shift `fat_shift_mm` (x, y) (operators made with a
        `fat_signal`), the fat's share of each pixel reads the field where that fat lies, the pixel less the shift,
        and the positions are those pixels and then the same less the shift (module text)."""
        matrix, pixels = self._assemble(self.K)
        positions = self._pixel_positions(pixels)
        if fat_shift_mm is None or self.K_fat is None or not np.any(np.asarray(fat_shift_mm, float) != 0.0):
            return matrix, positions
        fat, _ = self._assemble(self.K_fat)
        return (sparse.hstack([matrix - fat, fat], format="csr"),
                np.vstack([positions, positions - np.asarray(fat_shift_mm, float)[None, :]]))

    def observe(self, field_mm: np.ndarray, fat_shift_mm=None) -> np.ndarray:
        """(N, 2) what the windows measure of a (2, H, W) displacement field in mm (`observation`), the field read
        between its pixels by bilinear interpolation."""
        matrix, positions = self.observation(fat_shift_mm)
        dx, dy = self.to_mm
        at = [positions[:, 1] / dy - 0.5, positions[:, 0] / dx - 0.5]
        values = np.stack([ndimage.map_coordinates(np.asarray(field_mm[c], float), at, order=1, mode="nearest")
                           for c in range(2)], axis=1).ravel()
        return (matrix @ values).reshape(-1, 2)

    def fat_offsets(self, offset_mm) -> np.ndarray:
        """(N, 2) what the windows measure of a uniform displacement offset_mm (x, y) of the fat's signal alone
        (operators made with a `fat_signal`; zeros without one)."""
        if self.K_fat is None:
            return np.zeros((len(self), 2))
        fat, pixels = self._assemble(self.K_fat)
        return (fat @ np.tile(np.asarray(offset_mm, float), len(pixels))).reshape(-1, 2)

    @cached_property
    def noise_ratio(self) -> np.ndarray:
        """rho of every pixel of the reference, flat (`prefilter.rician_variance_ratio`)."""
        return rician_variance_ratio(self._reference, self.reference_noise_sigma).ravel()

    def covariance(self, intensity_variance: np.ndarray, edge_variance_px2: float = 0.0) -> np.ndarray:
        """Dense (2N, 2N) covariance (mm^2, interleaved u_x, u_y per window) of the windows' errors, overlaps
        included; intensity_variance: s_i^2 of each window (`DICResult.intensity_variance`); edge_variance_px2:
        s_edge^2 of the images' edges (`prefilter.EdgeResiduals`)."""
        variance = np.asarray(intensity_variance, float)
        if variance.shape != (len(self),) or not np.all(np.isfinite(variance) & (variance > 0)):
            raise ValueError("the covariance needs a positive, finite intensity variance for every window")
        if not (edge_variance_px2 >= 0.0 and np.isfinite(edge_variance_px2)):
            raise ValueError(f"the variance of the edges' position is a non-negative number, not {edge_variance_px2}")
        scale = np.sqrt(variance)
        rho = self.noise_ratio
        edges = edge_variance_px2 * edge_strength(self._reference).ravel() if edge_variance_px2 > 0 else 0.0
        n = len(self)
        covariance = np.zeros((2 * n, 2 * n))
        reach = self.window_px - 1 + 2 * self.prefilter.radius + 1e-9
        pairs = cKDTree(self.centres).query_pairs(reach * np.sqrt(2), output_type="ndarray")
        pairs = np.vstack([np.column_stack([np.arange(n), np.arange(n)]), pairs.reshape(-1, 2)])
        to_mm = np.diag(self.to_mm)
        for i, j in pairs:
            if np.any(np.abs(self.centres[i] - self.centres[j]) > reach):
                continue
            shared, in_i, in_j = np.intersect1d(self.noise_pixels[i], self.noise_pixels[j], assume_unique=True,
                                                return_indices=True)
            if shared.size == 0:
                continue
            weight = scale[i] * scale[j] * rho[shared] + (edges[shared] if edge_variance_px2 > 0 else 0.0)
            block = to_mm @ ((self.B[i][:, in_i] * weight) @ self.B[j][:, in_j].T) @ to_mm
            covariance[2 * i:2 * i + 2, 2 * j:2 * j + 2] = block
            covariance[2 * j:2 * j + 2, 2 * i:2 * i + 2] = block.T
        return covariance
