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

Overlapping windows share pixels, so their errors are correlated. With B_i(x) = rows u, v of H_s,i^-1 S_i(x)^T
(H_s the Gauss-Newton matrix of the noiseless reference, `dic.denoised_hessian`) and s_i^2 the intensity-noise
variance of window i,

    Cov(u_i, u_j) = s_i s_j sum_{x in both} B_i(x) B_j(x)^T,

which is s_i^2 H_s^-1 H H_s^-1 on the diagonal (the covariance each window reports) and positive semi-definite (a Gram
matrix scaled by a diagonal). `covariance` assembles it for the fit's weighting, its noise floor and its
Monte-Carlo intervals.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from .dic import denoised_hessian, spline_gradient, steepest_descent


class WindowOperators:
    """The linear maps B_i and K_i of a set of square windows on a reference image (module text)."""

    def __init__(self, reference: np.ndarray, centres_rc, window_px: int, pixel_size_mm, reference_noise_sigma: float,
                 gradients=None):
        self.shape = tuple(np.shape(reference))
        self.centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
        self.window_px = int(window_px)
        dy, dx = (float(v) for v in pixel_size_mm)
        self.to_mm = np.array([dx, dy])
        grad_rows, grad_cols = gradients if gradients is not None else spline_gradient(reference)
        size = self.window_px
        local_rows, local_cols = np.mgrid[0:size, 0:size]
        self.pixels = []      # flat pixel indices of each window
        self.B = []           # (2, size^2) per window, px per intensity unit
        self.K = []           # (2, 2, size^2) per window: centre displacement (px) per pixel displacement (px)
        for row, col in self.centres:
            r0, c0 = row - size // 2, col - size // 2
            rows, cols = local_rows + r0, local_cols + c0
            if r0 < 0 or c0 < 0 or r0 + size > self.shape[0] or c0 + size > self.shape[1]:
                raise ValueError(f"the window centred at row {row}, column {col} does not fit in the image")
            fx, fy = grad_cols[rows, cols], grad_rows[rows, cols]
            steepest = steepest_descent(fx, fy)
            hessian = steepest.T @ steepest
            signal = denoised_hessian(hessian, size, reference_noise_sigma)
            if signal is None:
                raise ValueError(f"the window centred at row {row}, column {col} holds less texture than noise")
            self.pixels.append((rows * self.shape[1] + cols).ravel())
            self.B.append(np.linalg.solve(signal, steepest.T)[[0, 3]])
            fit = np.linalg.solve(hessian, steepest.T)[[0, 3]]
            self.K.append(fit[:, None, :] * np.stack([fx.ravel(), fy.ravel()])[None, :, :])

    def __len__(self) -> int:
        return len(self.centres)

    def observation(self) -> tuple[sparse.csr_matrix, np.ndarray]:
        """(O, pixels): O is the sparse (2N, 2P) map from the displacement (mm, interleaved u_x, u_y) at the P
        pixels `pixels` (flat indices, row-major) to what the N windows measure (mm, interleaved)."""
        pixels, inverse = np.unique(np.concatenate(self.pixels), return_inverse=True)
        rows, cols, values = [], [], []
        start = 0
        for i, (own, k) in enumerate(zip(self.pixels, self.K)):
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

    def observe(self, field_mm: np.ndarray) -> np.ndarray:
        """(N, 2) what the windows measure of a (2, H, W) displacement field in mm."""
        matrix, pixels = self.observation()
        values = np.stack([field_mm[0].ravel()[pixels], field_mm[1].ravel()[pixels]], axis=1).ravel()
        return (matrix @ values).reshape(-1, 2)

    def covariance(self, intensity_variance: np.ndarray) -> np.ndarray:
        """Dense (2N, 2N) covariance (mm^2, interleaved u_x, u_y per window) of the windows' errors, overlaps
        included; intensity_variance: s_i^2 of each window (`DICResult.intensity_variance`)."""
        variance = np.asarray(intensity_variance, float)
        if variance.shape != (len(self),) or not np.all(np.isfinite(variance) & (variance > 0)):
            raise ValueError("the covariance needs a positive, finite intensity variance for every window")
        scale = np.sqrt(variance)
        n = len(self)
        covariance = np.zeros((2 * n, 2 * n))
        reach = self.window_px - 1 + 1e-9
        pairs = cKDTree(self.centres).query_pairs(reach * np.sqrt(2), output_type="ndarray")
        pairs = np.vstack([np.column_stack([np.arange(n), np.arange(n)]), pairs.reshape(-1, 2)])
        to_mm = np.diag(self.to_mm)
        for i, j in pairs:
            if np.any(np.abs(self.centres[i] - self.centres[j]) > reach):
                continue
            shared, in_i, in_j = np.intersect1d(self.pixels[i], self.pixels[j], assume_unique=True, return_indices=True)
            if shared.size == 0:
                continue
            block = scale[i] * scale[j] * to_mm @ (self.B[i][:, in_i] @ self.B[j][:, in_j].T) @ to_mm
            covariance[2 * i:2 * i + 2, 2 * j:2 * j + 2] = block
            covariance[2 * j:2 * j + 2, 2 * i:2 * i + 2] = block.T
        return covariance
