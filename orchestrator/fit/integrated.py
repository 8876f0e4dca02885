"""Integrated DIC (I-DIC): the material parameters fitted to the grey levels of the two images directly.

The windows (`measure`, `dic`, `windows`) first turn the images into displacements, then the fit compares the model
with those. Integrated DIC skips the intermediate field: the model's own displacement u(X; theta) warps the loaded
image back onto the unloaded one and the grey-level difference is the residual (Hild and Roux, "Comparison of local
and global approaches to digital image correlation", Exp. Mech. 52, 2012; Mathieu, Leclerc, Hild and Roux,
"Estimation of elastoplastic parameters via weighted FEMU and integrated-DIC", Exp. Mech. 55:105-119, 2015, eqs. 1-2
and 10-13):

    r(X) = (1 + b_0 + b_x xi + b_y eta) I1(M(R_q(X + u(X; theta)))) - I0(X)      over the pixels X of the region,

with I0, I1 both smoothed by the windows' 1-pixel Gaussian (`prefilter`: the other program's images draw edges by
partial volume, an aliased staircase that the cubic spline interpolates wrongly; the prefilter made them nearly
band-limited and removed the windows' edge bias, and the grey-level residual needs that even more), I1 interpolated
by cubic splines, M the bones' rigid motion of the run (`align.align_on_bones`), and the nuisances q = (t_x, t_y,
omega) a residual rigid motion of the bones about the leg's centre (what the windows' fit profiles out, `measure`
module text) and b = (b_0, b_x, b_y) an affine change of brightness over the leg's coordinates (xi, eta): the
phantoms' coil bias is fixed in the scanner while the leg moves in it (`phantom.render`), and a global scale is the
zero-mean, zero-scale normalisation the windows' ZNCC does per window (`IntegratedDIC` brightness: or a bias field
fixed in the scanner, or none). The region is the tissue of I0 (fat and muscle; the bones are clamped and carry
only the rigid motion) plus a band of `air_band_px` pixels of air outside the skin: the skin/air edge is the
strongest grey-level step of the slice and the garment moves it most.

Each pixel is weighted by its noise (Mathieu et al. eq. 13: the grey-level residual over the image noise): with
s_0, s_1 the images' noise (`dic._signal_noise`, the estimate the windows use) and rho the Rician share
(`prefilter.rician_variance_ratio`: 0.43 where there is no signal, the air band), a prefiltered pixel of the
difference has the variance v(X) = (s_0^2 + s_1^2) (G^2 * rho)(X). The whitened residual r / sqrt(v) has unit
variance where the model is right; prefiltered pixels are correlated (one independent value spreads over about
1 / sum G^2 pixels), which leaves chi^2's expectation n but widens its spread, and makes the fit's loss of degrees
of freedom at most that many pixels per fitted parameter (`noise_floor`).

The Jacobian (Mathieu et al. eq. 12, the "I-DIC" sensitivity): dr/dtheta(X) = (1 + b . phi) grad I1(M(y)) . R_M
du/dtheta(X), with du/dtheta the engine's nodal sensitivities (`*SENSITIVITY`) interpolated to the pixels by the FE
shape functions (`forward.MeshInterpolator`), and grad I1 the cubic spline's derivative at the warped point (the
Gauss-Newton of the deformed image: exact at the point it is evaluated). The six nuisances are profiled out at every
evaluation (variable projection: Golub and Pereyra, SIAM J. Numer. Anal. 10, 1973; Kaufman's Jacobian, BIT 15,
1975): a few Gauss-Newton steps in q, b at fixed theta, then the residual at that optimum and the theta columns
projected orthogonally to the nuisance columns. So the object has the interface of
`objectives.DisplacementResidualObjective` that `identify.levenberg_marquardt` drives (residuals, cost, noise floor,
the Jacobian per engine parameter from the engine's sensitivities), and the existing Levenberg-Marquardt fits it
with one engine run per iteration.

What it does not model: an error of the position of the images' edges (the windows calibrate one, `prefilter`
module text); it shows as a residual above the noise at the edges (`band_ratios`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import ndimage

from ..core.frame import RigidMotion, mm_to_index
from ..core.tissues import BONE
from ..measure.prefilter import PREFILTER_SIGMA_PX, Prefilter, rician_variance_ratio

AIR_BAND_PX = 3               # pixels of air outside the skin of I0 kept in the region
NUISANCE_ITERATIONS = 8       # at most this many Gauss-Newton steps on the nuisances per evaluation
NUISANCE_TOLERANCE = 1e-9     # stop when the step changes the squared residual by less than this share
RIGID = ("t_x_mm", "t_y_mm", "omega_rad")
NUISANCE_NAMES = {"scanner": RIGID + ("gain", "c_x", "c_y", "c_xx", "c_xy", "c_yy"),
                  "affine": RIGID + ("b_0", "b_x", "b_y"), "none": RIGID}
BRIGHTNESS = tuple(NUISANCE_NAMES)


def region_mask(labels: np.ndarray, air_band_px: int = AIR_BAND_PX) -> tuple[np.ndarray, np.ndarray]:
    """(region, air band): the tissue of I0 (every label but background and bone) and the `air_band_px` pixels of
    background next to the leg (8-connected dilation), which hold the skin's edge."""
    labels = np.asarray(labels)
    leg = labels > 0
    tissue = leg & (labels != BONE)
    band = np.zeros_like(leg)
    if air_band_px > 0:
        band = ndimage.binary_dilation(leg, structure=np.ones((3, 3), bool), iterations=int(air_band_px)) & ~leg
    return tissue | band, band


class IntegratedDIC:
    """The I-DIC residual of one mesh and one pair of images (module text), as an objective of `runner.Evaluator`.

    unloaded, loaded: the raw images I0 and I1 (the loaded one NOT aligned: the bones' motion `motion` is composed
    into the warp, so that I1 is interpolated once, by the cubic spline); labels: the labels of I0 (the region).
    noise_sigma: the raw noise of (I0, I1), default estimated as the windows do. brightness: the model of the grey
    levels' change besides the motion, "affine" (an affine gain that moves with the tissue, the default), "scanner"
    (a gain and a log-quadratic bias field fixed in the scanner) or "none" (`_warp`). On the small phantom of
    tests/fit/test_integrated_dic.py, whose coil bias is fixed in the scanner, the three leave the same noiseless
    residual at the truth (4.5-4.8 % of the noise variance) and the same parameters to 0.5 %: the coil bias is not
    what limits I-DIC there."""

    name = "integrated_dic"
    needs_vtu = False

    def __init__(self, mesh, unloaded: np.ndarray, loaded: np.ndarray, labels: np.ndarray, pixel_size_mm,
                 motion: RigidMotion, *, prefilter_px: float = PREFILTER_SIGMA_PX, air_band_px: int = AIR_BAND_PX,
                 noise_sigma: tuple[float, float] | None = None, brightness: str = "affine"):
        from ..measure.dic import _signal_noise  # the windows' own estimate of each image's noise where it has signal
        from ..model.forward import MeshInterpolator
        from .objectives import _array_sha

        unloaded, loaded = np.asarray(unloaded, float), np.asarray(loaded, float)
        if unloaded.shape != loaded.shape or unloaded.shape != np.shape(labels):
            raise ValueError("I-DIC needs I0, I1 and the labels of I0 on one pixel grid")
        self.shape = unloaded.shape
        self.pixel_size_mm = tuple(float(v) for v in pixel_size_mm)
        self.motion = motion
        self.prefilter = Prefilter(prefilter_px)
        self.air_band_px = int(air_band_px)
        self.mask, band = region_mask(labels, air_band_px)
        self.air_band = band[self.mask]
        rows, cols = np.nonzero(self.mask)
        dy, dx = self.pixel_size_mm
        self.positions_mm = np.column_stack([(cols + 0.5) * dx, (rows + 0.5) * dy])
        self.centre_mm = self.positions_mm.mean(axis=0)
        # the FE interpolation at the pixels: u(X) = W u_nodes (outside the mesh, the nearest point of the nearest
        # element: the air band takes the skin's displacement)
        self.weights = MeshInterpolator(mesh).weights(self.positions_mm)
        self.n_nodes = self.weights.shape[1]
        self.reference = self.prefilter(unloaded)[self.mask]
        self._spline = ndimage.spline_filter(self.prefilter(loaded), order=3)
        self.noise_sigma = tuple(float(s) for s in (noise_sigma or (_signal_noise(unloaded), _signal_noise(loaded))))
        self._rho = rician_variance_ratio(unloaded, self.noise_sigma[0])   # raw pixels' Rician share
        rho = self.prefilter.squared_kernel_response(self._rho)[self.mask]
        self.variance = (self.noise_sigma[0] ** 2 + self.noise_sigma[1] ** 2) * rho   # v(X), intensity^2
        self._whiten = 1.0 / np.sqrt(self.variance)
        self.reference_variance = float(np.mean(self.variance))
        # pixels one independent value of a prefiltered image spreads over: 1 / sum G^2 (sum G = 1)
        self.pixels_per_value = 1.0 / self.prefilter.noise_gain
        self._extent = max(float(np.ptp(self.positions_mm[:, 0])), float(np.ptp(self.positions_mm[:, 1])), 1e-9) / 2
        if brightness not in BRIGHTNESS:
            raise ValueError(f"the I-DIC brightness model is one of {BRIGHTNESS}, not {brightness!r}")
        self.brightness = brightness
        self._phi_X = self._bias_terms(self.positions_mm)[0]
        self._phi_affine = np.column_stack([np.ones(len(rows)), self._phi_X[:, :2]])
        self.nuisance_names = NUISANCE_NAMES[brightness]
        self.nuisance_dof = len(self.nuisance_names)
        self.fingerprint = (f"IDIC:{_array_sha(unloaded, loaded, self.mask)}:{prefilter_px:g}:{air_band_px}:"
                            f"{self.brightness}:{motion.angle_deg:.12g},{motion.translation_mm},{motion.centre_mm}:"
                            f"{self.noise_sigma[0]:.9g},{self.noise_sigma[1]:.9g}")

    @classmethod
    def from_setup(cls, setup, **options) -> "IntegratedDIC":
        """The I-DIC of a prepared run (`study.RunSetup`): its mesh, I0's labels and the bones' motion."""
        case = setup.case
        return cls(setup.mesh, case.unloaded, case.loaded, setup.labels_unloaded, case.pixel_size_mm, setup.motion,
                   **options)

    # --- the warp ---------------------------------------------------------------------------------

    @property
    def n_residuals(self) -> int:
        return len(self.reference)

    def _sample(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """I1 (prefiltered, cubic spline) at z = M(points), its gradient with respect to the points (per mm, in the
        unloaded frame: the gradient in the loaded image turned back by M's rotation), and z (mm)."""
        from ..measure.dic import spline_derivatives

        x, y = self.motion.apply(points_mm[:, 0], points_mm[:, 1])
        rows, cols = mm_to_index(x, y, self.pixel_size_mm)
        value = ndimage.map_coordinates(self._spline, [rows, cols], order=3, prefilter=False, mode="nearest")
        d_rows, d_cols = spline_derivatives(self._spline, rows, cols)
        dy, dx = self.pixel_size_mm
        gradient = np.column_stack([d_cols / dx, d_rows / dy])
        # d/dp I1(M p) = R^T grad I1, row-wise: grad @ R
        return value, gradient @ self.motion.rotation, np.column_stack([x, y])

    def _bias_terms(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The log-quadratic bias field's monomials phi_k(x) (n, 5) and their gradients (n, 5, 2), in coordinates
        of the leg's centre and half extent."""
        xi, eta = ((points_mm - self.centre_mm) / self._extent).T
        zero, one = np.zeros_like(xi), np.ones_like(xi)
        values = np.column_stack([xi, eta, xi * xi, xi * eta, eta * eta])
        gradients = np.stack([np.column_stack(pair) for pair in
                              ((one, zero), (zero, one), (2 * xi, zero), (eta, xi), (zero, 2 * eta))], axis=1)
        return values, gradients / self._extent

    def _warp(self, displacement_mm: np.ndarray, q: np.ndarray):
        """Residual (unwhitened), the gradient of the brightness-corrected I1 with respect to the warped point, the
        nuisance Jacobian (unwhitened, n x nuisance_dof) at the nuisances q (module text):
        - "scanner": (1 + b_0) exp(c . (phi(X) - phi(z))) I1(z), the bias field exp(c . phi) fixed in the scanner
          (divided out of I1 where the point is, put back where it was in I0);
        - "affine": (1 + b_0 + b_x xi + b_y eta)(X) I1(z), a change of brightness that moves with the tissue;
        - "none": I1(z)."""
        p = self.positions_mm + displacement_mm
        offset = p - self.centre_mm
        moved = p + q[:2] + q[2] * np.column_stack([-offset[:, 1], offset[:, 0]])
        value, gradient, z = self._sample(moved)
        columns = []
        if self.brightness == "scanner":
            phi_z, dphi_z = self._bias_terms(z)
            factor = np.exp((self._phi_X - phi_z) @ q[4:])
            scale = (1.0 + q[3]) * factor
            # the bias at z moves with the point too: d/dp of -c . phi(M p) = -(c . dphi(z)) R
            gradient = gradient - value[:, None] * (np.einsum("k,nkj->nj", q[4:], dphi_z) @ self.motion.rotation)
            columns = [(factor * value)[:, None], (scale * value)[:, None] * (self._phi_X - phi_z)]
        elif self.brightness == "affine":
            scale = self._phi_affine @ (np.r_[1.0, 0.0, 0.0] + q[3:])
            columns = [value[:, None] * self._phi_affine]
        else:
            scale = np.ones(len(p))
        residual = scale * value - self.reference
        g = scale[:, None] * gradient
        nuisance = np.column_stack([g[:, 0], g[:, 1], g[:, 1] * offset[:, 0] - g[:, 0] * offset[:, 1]] + columns)
        return residual, g, nuisance

    def profile(self, displacement_mm: np.ndarray):
        """(whitened residual, g, orthonormal basis of the whitened nuisance columns, q) at the nuisances that
        minimise the residual for this displacement (Gauss-Newton from zero: deterministic, so that the
        residual is a function of theta alone)."""
        q = np.zeros(self.nuisance_dof)
        residual, g, nuisance = self._warp(displacement_mm, q)
        r = self._whiten * residual
        chi2 = float(r @ r)
        for _ in range(NUISANCE_ITERATIONS):
            A = self._whiten[:, None] * nuisance
            step, *_ = np.linalg.lstsq(A, -r, rcond=None)
            trial_q = q + step
            trial = self._warp(displacement_mm, trial_q)
            trial_r = self._whiten * trial[0]
            trial_chi2 = float(trial_r @ trial_r)
            if trial_chi2 > chi2:
                break
            q, (residual, g, nuisance), r, drop = trial_q, trial, trial_r, (chi2 - trial_chi2) / max(chi2, 1e-300)
            chi2 = trial_chi2
            if drop < NUISANCE_TOLERANCE:
                break
        basis, _ = np.linalg.qr(self._whiten[:, None] * nuisance)
        return r, g, basis, q

    def displacement(self, nodal_u: np.ndarray) -> np.ndarray:
        """(n, 2) u(X) at the region's pixels (mm) from the nodal field (the leg's rows)."""
        return self.weights @ np.asarray(nodal_u, float)[:self.n_nodes]

    # --- the objective's interface (`objectives.DisplacementResidualObjective`) -------------------------

    def residuals(self, nodal_u: np.ndarray) -> np.ndarray:
        return self.profile(self.displacement(nodal_u))[0]

    def cost_of(self, residuals: np.ndarray) -> float:
        """The misfit (intensity^2): the mean pixel variance times r.r / n (the noise variance at the floor)."""
        residuals = np.asarray(residuals, float)
        return float(self.reference_variance * (residuals @ residuals) / len(residuals))

    def noise_floor(self, n_parameters: int) -> float:
        """The expected misfit of a correct model: each fitted parameter (and nuisance) takes at most one
        independent value, `pixels_per_value` prefiltered pixels' worth (module text)."""
        n = self.n_residuals
        return float(self.reference_variance * (n - (n_parameters + self.nuisance_dof) * self.pixels_per_value) / n)

    def jacobian_columns(self, g: np.ndarray, basis: np.ndarray, nodal_du: np.ndarray) -> np.ndarray:
        """dr/dtheta for one nodal sensitivity du/dtheta: the whitened g . W du projected off the nuisances."""
        column = self._whiten * np.einsum("ij,ij->i", g, self.displacement(nodal_du))
        return column - basis @ (basis.T @ column)

    def outputs(self, nodal_u: np.ndarray, outdir: Path) -> dict:
        """Cost, whitened residuals, the fitted nuisances and, with the engine's sensitivities (a deck with
        *SENSITIVITY), dr/d(engine parameter) per engine parameter name (what `identify.residual_jacobian`
        combines into dr/dtheta)."""
        from ..engine.results import EngineResults

        r, g, basis, q = self.profile(self.displacement(nodal_u))
        out = {"cost": self.cost_of(r), "residuals": r.tolist(), "nuisance": dict(zip(self.nuisance_names, map(float, q)))}
        sensitivities = EngineResults(Path(outdir)).sensitivities()
        if sensitivities:
            out["sensitivity"] = {name: self.jacobian_columns(g, basis, du).tolist()
                                  for name, du in sensitivities.items()}
        return out

    def parameter_covariance(self, jacobian: np.ndarray) -> np.ndarray:
        """The linearised covariance of parameters fitted by Gauss-Newton on this residual, given its (projected,
        whitened) Jacobian J (n x p): the sandwich H^-1 J^T S J H^-1, H = J^T J, with S the covariance of the
        whitened residual. Its pixels are not independent: r_w = w G * (e_1 - e_0), e the raw noise of variance
        (s_0^2 + s_1^2) rho, so J^T S J = sum_y (s_0^2 + s_1^2) rho(y) (G * wJ)(y) (G * wJ)(y)^T (G symmetric; both
        images' noise taken on I0's grid). (J^T J)^-1 alone, as if the pixels were independent, is 2.7 x too narrow in
        standard deviation with the 1-pixel prefilter on the phantom of tests/fit/test_integrated_dic.py, where this
        sandwich matched the spread of 40 noise draws within 20 %."""
        jacobian = np.asarray(jacobian, float)
        spread = []
        for column in jacobian.T:
            image = np.zeros(self.shape)
            image[self.mask] = self._whiten * column
            spread.append(self.prefilter(image).ravel())
        spread = np.array(spread)
        weight = (self.noise_sigma[0] ** 2 + self.noise_sigma[1] ** 2) * self._rho.ravel()
        middle = (spread * weight) @ spread.T
        bread = np.linalg.inv(jacobian.T @ jacobian)
        return bread @ middle @ bread

    # --- what the residual shows --------------------------------------------------------------------

    def residual_image(self, nodal_u: np.ndarray) -> np.ndarray:
        """(H, W) the grey-level residual at the fitted nuisances (NaN outside the region)."""
        r = self.residuals(nodal_u)
        image = np.full(self.shape, np.nan)
        image[self.mask] = r / self._whiten
        return image

    def band_ratios(self, frame, nodal_u: np.ndarray | None = None,
                    displacement_mm: np.ndarray | None = None) -> dict[str, dict]:
        """Per band of `verification.BANDS` (by the tissue of I0 and the depth under the skin, as the windows' table
        of benchmarks/imaging.py) and for the air band outside the skin: the grey-level residual's variance over the
        predicted noise variance (mean r^2 / v over the band; 1 when the residual is the images' noise) and the
        pixel count, for the model's nodal field or for a displacement given at the region's pixels (a true field:
        `displacement_mm`, (n, 2) mm at `positions_mm`), the nuisances fitted in both cases."""
        from types import SimpleNamespace

        from ..measure.verification import band_masks

        if displacement_mm is None:
            displacement_mm = self.displacement(nodal_u)
        r = self.profile(np.asarray(displacement_mm, float))[0]
        masks = band_masks(SimpleNamespace(position_mm=self.positions_mm), frame)
        masks[f"air within {self.air_band_px} px of the skin"] = self.air_band
        masks["all"] = np.ones(len(r), bool)
        return {band: {"pixels": int(mask.sum()),
                       "ratio": float(np.mean(r[mask] ** 2)) if mask.any() else float("nan")}
                for band, mask in masks.items()}


def identify_integrated(setup, run_dir, *, effects: Sequence[str] = (), start: Sequence[float] | None = None,
                        workers: int = 1, progress: bool = False, **options) -> tuple[object, "IntegratedDIC", dict]:
    """Fit a prepared run's model (`setup`, `study.RunSetup`) with these catalog effects to the images by I-DIC, with
    `identify.levenberg_marquardt` and the engine's sensitivities, from `start` (the laws' constants, then the
    effects' parameters; default the model's start). The evaluations are logged in run_dir (not the windows' run
    folder: they share no cache key, the fingerprints differ, but the logs grow large). Returns (FitResult, the
    objective, a summary: the noise floor, misfit over it, the fitted nuisances, the parameters' linearised standard
    deviations (`parameter_covariance`, not inflated by a misfit above the floor), wall time)."""
    from ..engine.runner import Evaluator
    from .identify import levenberg_marquardt, residual_jacobian

    began = time.perf_counter()
    objective = IntegratedDIC.from_setup(setup, **options)
    model = setup.model_with(effects, sensitivities=True)
    if start is None:
        start = model.start()
    elif len(start) == model.law_size:
        start = model.start(start)
    with Evaluator(model, objective, run_dir, workers=workers, progress=progress, label="I-DIC") as evaluator:
        fit = levenberg_marquardt(evaluator, list(map(float, start)))
        record = evaluator(fit.theta)
    floor = objective.noise_floor(model.space.size)
    jacobian = residual_jacobian(model, record, fit.theta)
    sigma = (np.sqrt(np.diagonal(objective.parameter_covariance(jacobian))).tolist() if jacobian is not None
             else [float("nan")] * model.space.size)
    summary = {"standard_deviation": sigma, "pixels": objective.n_residuals, "noise_sigma": list(objective.noise_sigma),
               "noise_floor": floor, "misfit_over_floor": fit.cost / floor,
               "nuisance": record["outputs"].get("nuisance"), "wall_time_s": time.perf_counter() - began,
               "parameters": list(model.space.names)}
    return fit, objective, summary
