"""Where the DIC windows' error comes from, on cases whose true field is known (issue 28). Prints figures, asserts
nothing.

    PYTHONPATH=. .venv/bin/python benchmarks/error_budget.py [--foreign DIR [--renderers]]

DIR holds case folders made by another program, DIR/truth/<case>.npz their true fields and DIR/answers.json their
scanner motions (`scanner_motion_image_frame`). Without --foreign, or with --renderers, one engine-made case of each
of calfit's renderers.
Each case is measured as `calfit measure` does (32-pixel windows, prefiltered, error model calibrated), then:

- The true images' error. The loaded image, prefiltered, is pulled back through the true field and the scanner motion
  onto I0's pixels: D = (G * I1)(M(X + u(X))) - G * I0 is what the images hold besides the motion (noise, and how
  each image was rendered or acquired). Through a window's own linearised map, e = H^-1 S^T D (`dic`: S the
  zero-normalised steepest-descent images of the prefiltered reference) is that window's error as the images make
  it. Per band: sum e^2 over what the calibrated error model predicts for the same windows (noise and edges), which
  gives the band's chi^2/n back where the window's error scales as the images' (the linearised observation is
  exact to 0.01 of chi^2/n on the other program's drainage case: a DIC of I0 warped by the true field agrees with
  it); the same over the noise's part alone; and the edges' share of the prediction. These maps use the noisy
  reference's Gauss-Newton matrix, as IC-GN steps with; the measured error is larger than e (1.1 in the muscle to
  2.7 times in the skin band of the other program's cases) by about as much as the measurement's own prediction
  (H_s, the noiseless matrix, `windows`) is larger than the maps': both ratios are printed.
- The measured errors, whitened window by window, along the radius (across the skin and the fascia) and around it;
  and the windows' residual over what the error model predicts (`measurements.csv`): an error the windows take
  whole into their displacement leaves none there.
- The images' own error of position per kind of structure: D^2 - f v regressed on G^2 * (|grad I0|^2 on each kind)
  (v the calibrated noise of a prefiltered pixel, f the ratio D^2 / v where there is no structure: the spline's
  sampling of the prefiltered noise), for the skin and air, the inner boundaries (fat, muscle, bone), the fat's
  texture and the muscle's; against the one value the windows' residuals calibrate (`prefilter`).
- Where the images draw a boundary against where the truth puts it: D against the derivative of the prefiltered I0
  across the boundary (its normal from the labels) gives, per 45 degree sector, the offset delta of the boundary in
  I1 pulled back (D ~ -delta dI/dn), for the fascia (fat | muscle) and the skin (air | fat). Its RMS over the sectors
  is set against the same estimate on D rolled by 40 pixels eight ways (the noise's alone, no boundary under it):
  what exceeds it, sqrt(RMS^2 - null^2), is an offset steady over a sector, which a window takes whole for a
  displacement.
- Over the other program's cases (one anatomy, one noiseless I0, independent noise): the correlation between cases
  of the same window's normalised error. Independent errors give 0; a part of the error that the anatomy's rendering
  fixes, the same in every case, gives more, and no noise draw averages it out.
- With --splice, which pixels of the other program's loaded image carry the error. The same leg is warped instead:
  the mean of the other cases' I0 (one anatomy, independent noise) sampled at the material points of the loaded
  pixels (the truth and the scanner motion, `phantom.material_points`), with fresh Rician noise of the loaded
  image's sigma; it moves every structure exactly with the tissue. Loaded images spliced from the two along the
  boundaries between the labels (air, fat, muscle, bone; their pixels within SPLICE_REACH_PX, pulled into the
  loaded frame) are measured as `calfit measure` does: per band chi^2/n against the truth for the warped image, for
  it with the loaded image's boundaries, for the loaded image with the warped boundaries, and for the loaded image.
  The windows are linear in the image, so a window's error on the loaded image less that on the warped one is the
  sum of what its boundaries and the rest add (printed: the RMS of that non-linearity); their correlation over the
  deep-fat windows, along the radius, says whether the two parts of the loaded image share one error (> 0) or add
  independent ones (0). The same with a second noise draw of the warped image in place of the loaded one is the
  control: independent noise in disjoint pixels gives 0. More noise draws of the warped image (--draws) show how far
  a band's chi^2/n scatters where the images move exactly with the tissue: the yardstick for the loaded image's.
- With --sampling S, how a renderer that averages S x S samples per pixel draws the skin and the fascia in both
  images, against where the true mesh puts them (the other program's cases say they were made so, S = 3; their truth
  holds the mesh). Each pixel's coverage by air (or bone), fat and muscle is counted on S x S samples and on
  SAMPLED_FINE x SAMPLED_FINE (taken as exact; 30 changes the figures by <= 0.01), in I0 through the mesh and in I1
  through the mesh moved by the truth and the scanner motion; the difference times the tissues' median grey levels
  is the error with which the renderer draws each image's boundaries: a function of where the boundary crosses the
  pixel, the same for every boundary that crosses alike. A window's error from it is B~ (dI0 - dI1 o phi) (`windows`:
  B~ its map, dI1 pulled back to I0's pixels; IC-GN composes the inverse of its step, hence the signs), the bones'
  rigid motion removed as the fit does. Per band, against the windows' error model without the drawing's own term
  (which calfit adds when it finds the images point-sampled, `imaging.drawing`): chi^2/n as measured, with that error
  taken out, of that error alone, and its correlation with the measured error. Where a boundary runs along the pixel grid, its pixels cross
  alike and their errors add up over a window instead of averaging out; the window takes them for motion, and its
  residual, on which calfit calibrates s_edge^2, does not show them. The same with S - 1 and S + 1 is the control.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from functools import cached_property
from itertools import combinations
from pathlib import Path

import numpy as np
from matplotlib.tri import Triangulation
from scipy import ndimage
from skimage import io

from orchestrator.core.frame import RigidMotion
from orchestrator.core.tissues import BONE, FAT, MUSCLE
from orchestrator.measure.dic import (
    edge_strength,
    spline_gradient,
    zero_normalised_steepest_descent,
)
from orchestrator.measure.measurements import loaded_index_map, read_window_table
from orchestrator.measure.prefilter import Prefilter, rician_variance_ratio
from orchestrator.measure.verification import (
    band_errors,
    band_masks,
    errors_against,
    field_from_mesh_file,
    symmetric_roots,
    without_rigid_motion,
)
from orchestrator.phantom import (
    CalfPhantom,
    MRIPhantom,
    as_displacement_fn,
    material_points,
)
from orchestrator.phantom.appearance import add_rician_noise
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import random_truth
from orchestrator.run.setup import load_run
from orchestrator.run.stages import run_measure

RENDERER_MOTION = RigidMotion(-1.2, (1.1, 0.7), (75.6, 75.6))
SKIN_REACH_PX = 3        # pixels of the air and the leg counted as the skin's edge
BOUNDARY_REACH_PX = 2    # pixels either side of a boundary between tissues
QUIET_SHARE = 0.1        # the share of the leg's pixels with the least structure, where D is noise alone
BOUNDARY_BAND_PX = 3     # pixels either side of a boundary in which its offset is read
SECTOR_DEG = 45          # the boundary's offset is read per sector of this angle about the leg's centre
NULL_ROLL_PX = 40        # D rolled this far (eight ways) has no boundary under it: the offset's noise alone
SPLICE_REACH_PX = 1      # pixels either side of a boundary between labels taken from the other image in a splice
DEEP_FAT = "other fat"   # the band whose excess the splices take apart
SAMPLED_FINE = 15        # samples per pixel side taken as a pixel's exact coverage by each tissue
BONE_MARGIN_PX = 3       # pixels near a bone left out of the sampled edges' error (the mesh has holes there)


def boundaries_between(masks: list[np.ndarray], reach_px: int) -> np.ndarray:
    """The pixels within reach_px of two of the masks at once: the boundaries between them."""
    grown = [ndimage.binary_dilation(mask, iterations=reach_px) for mask in masks]
    out = np.zeros(grown[0].shape, bool)
    for a, b in combinations(grown, 2):
        out |= a & b
    return out


def structure_kinds(labels: np.ndarray) -> dict[str, np.ndarray]:
    """Masks of the raw pixels by the kind of structure they show (module text)."""
    leg = labels > 0
    skin = boundaries_between([~leg, leg], SKIN_REACH_PX)
    tissues = [labels == FAT, labels == MUSCLE, labels == BONE]
    boundary = boundaries_between(tissues, BOUNDARY_REACH_PX) & ~skin
    return {"skin and air": skin, "inner boundaries": boundary, "fat texture": tissues[0] & ~boundary & ~skin,
            "muscle texture": tissues[1] & ~boundary & ~skin}


class Case:
    """One measured case with its true field and scanner motion."""

    def __init__(self, name: str, case: Path, run: Path, field, motion: RigidMotion, labels: np.ndarray | None = None):
        self.name = name
        self.case_dir = case
        run_measure(case, run)
        self.setup = load_run(run)
        self.measured = self.setup.measurements("dic")
        self.meta = json.loads((run / "measurements.json").read_text())
        table = read_window_table(run)
        self.centres = table.centres_rc[table.kept]
        self.residual_over_model = table.residual_over_model[table.kept]
        self.drawing_factor = table.drawing_factor_mm   # None unless the images were found point-sampled
        self.reference = self.setup.case.unloaded.astype(float)
        self.pixel = self.setup.case.pixel_size_mm
        self.field = field(self.reference.shape, self.pixel)
        self.motion = motion
        self.labels = labels if labels is not None else self.setup.labels_unloaded
        self.prefilter = Prefilter(self.meta["prefilter_px"])
        self.bands = band_masks(self.measured, self.setup.frame())

    def pulled_back_difference(self) -> np.ndarray:
        loaded = self.setup.case.loaded.astype(float)
        spline = ndimage.spline_filter(self.prefilter(loaded), order=3)
        back = ndimage.map_coordinates(spline, self.loaded_grid(), order=3, prefilter=False, mode="nearest")
        return back - self.prefilter(self.reference)

    def loaded_grid(self) -> np.ndarray:
        """(2, H, W) where the loaded image shows each reference pixel (rows, columns)."""
        shape = self.reference.shape
        return self.to_loaded(np.indices(shape, dtype=float).reshape(2, -1).T).T.reshape(2, *shape)

    def window_budget(self, difference: np.ndarray) -> np.ndarray:
        """(N, 3) per kept window: e.e of the images' error through its map, the noise's and the edges' predicted
        variance through the same map (px^2), calibrated as the measurement was. Error and prediction share the map
        H^-1 S^T of the noisy reference's Gauss-Newton matrix, as IC-GN steps with it: the measurement's own
        covariance (H_s, the noiseless one) is a different linearisation, and set against e it no longer gives the
        band's chi^2 back."""
        smooth = self.prefilter(self.reference)
        grad_rows, grad_cols = spline_gradient(smooth)
        size, reach = self.meta["window_px"], self.prefilter.radius
        edges = np.pad(edge_strength(self.reference), reach, mode="edge")
        rho = np.pad(rician_variance_ratio(self.reference, self.meta["noise_sigma"][0]), reach, mode="edge")
        noise = float(np.sum(np.square(self.meta["noise_sigma"])))
        rows = []
        for row, col in self.centres:
            r0, c0 = row - size // 2, col - size // 2
            window = (slice(r0, r0 + size), slice(c0, c0 + size))
            steepest, hessian = zero_normalised_steepest_descent(smooth[window], grad_cols[window], grad_rows[window])
            fit = np.linalg.solve(hessian, steepest.T)[[0, 3]]
            error = fit @ difference[window].ravel()
            spread = self.prefilter.spread(fit.reshape(2, size, size)).reshape(2, -1) ** 2
            grown = (slice(r0, r0 + size + 2 * reach), slice(c0, c0 + size + 2 * reach))
            rows.append((error @ error if np.all(np.isfinite(error)) else np.nan,
                         noise * float(np.sum(spread @ rho[grown].ravel())),
                         self.meta["edge_variance_px2"] * float(np.sum(spread @ edges[grown].ravel()))))
        return np.array(rows)

    @cached_property
    def whiten(self) -> np.ndarray:
        """The inverse square root of the measurement covariance (`verification.symmetric_roots`)."""
        return symmetric_roots(np.asarray(self.measured.covariance_mm2, float), "the measurement covariance")[0]

    @cached_property
    def errors(self) -> np.ndarray:
        """(N, 2) measured less what the windows see of the truth, the bones' rigid motion removed as the fit does."""
        errors = errors_against(self.measured, None, self.field)
        return without_rigid_motion(self.measured, errors, self.whiten).reshape(-1, 2)

    @cached_property
    def to_loaded(self):
        """Reference indices (M, 2) -> where the loaded image shows them, through the truth and the scanner motion."""
        return loaded_index_map(np.nan_to_num(self.field), self.motion, self.pixel)

    def radial_tangential(self, errors: np.ndarray) -> np.ndarray:
        """(N, 2) each window's error along the radius from the leg's centre and around it, over its predicted sd."""
        covariance = np.asarray(self.measured.covariance_mm2, float)
        position = self.measured.position_mm
        radial = position - position.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        out = np.empty((len(errors), 2))
        for k, direction in enumerate(radial):
            block = covariance[2 * k:2 * k + 2, 2 * k:2 * k + 2]
            for j, d in enumerate((direction, np.array([-direction[1], direction[0]]))):
                out[k, j] = (d @ errors[k]) / np.sqrt(d @ block @ d)
        return out

    def position_error_by_kind(self, difference: np.ndarray) -> dict[str, float]:
        """s_edge^2 (px^2) of each kind of structure from the true images (module text)."""
        leg = ndimage.binary_erosion(np.isfinite(self.field[0]), iterations=2)
        edges = edge_strength(self.reference)
        q = {kind: self.prefilter.squared_kernel_response(edges * mask)
             for kind, mask in structure_kinds(self.labels).items()}
        noise = (float(np.sum(np.square(self.meta["noise_sigma"])))
                 * self.prefilter.squared_kernel_response(rician_variance_ratio(self.reference,
                                                                                self.meta["noise_sigma"][0])))
        total = sum(q.values())
        quiet = leg & (total <= np.quantile(total[leg], QUIET_SHARE))
        sampling = float(np.mean(difference[quiet] ** 2) / np.mean(noise[quiet]))
        design = np.column_stack([q[kind][leg] for kind in q])
        slopes, *_ = np.linalg.lstsq(design, difference[leg] ** 2 - sampling * noise[leg], rcond=None)
        return {"D^2 / v where quiet": sampling, **dict(zip(q, slopes))}


    def boundary_offsets(self, difference: np.ndarray) -> dict[str, tuple[float, float]]:
        """(RMS over the sectors of the boundary's offset, that of the noise alone) in px, for the fascia and the skin
        (module text)."""
        smooth = self.prefilter(self.reference)
        grad_rows, grad_cols = spline_gradient(smooth)
        difference = np.nan_to_num(difference)
        leg, fat = self.labels > 0, self.labels == FAT
        rows, cols = np.indices(self.reference.shape)
        angle = np.degrees(np.arctan2(-(rows - rows[leg].mean()), cols - cols[leg].mean())) % 360.0
        out = {}
        for name, inner, outer in (("fascia", self.labels == MUSCLE, fat), ("skin", fat, ~leg)):
            near = (ndimage.binary_dilation(inner, iterations=BOUNDARY_BAND_PX)
                    & ndimage.binary_dilation(outer, iterations=BOUNDARY_BAND_PX))
            normal_rows, normal_cols = np.gradient(ndimage.gaussian_filter(outer.astype(float), 2.0))
            across = (grad_rows * normal_rows + grad_cols * normal_cols) / (np.hypot(normal_rows, normal_cols) + 1e-12)
            sectors = [near & (angle >= start) & (angle < start + SECTOR_DEG) for start in range(0, 360, SECTOR_DEG)]

            def rms_offset(d: np.ndarray) -> float:
                return float(np.sqrt(np.mean([(np.sum(d[m] * across[m]) / np.sum(across[m] ** 2)) ** 2
                                              for m in sectors if m.any()])))

            null = [rms_offset(np.roll(difference, (dr * NULL_ROLL_PX, dc * NULL_ROLL_PX), axis=(0, 1)))
                    for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
            out[name] = (rms_offset(difference), float(np.sqrt(np.mean(np.square(null)))))
        return out


def report(title: str, cases: list[Case]) -> None:
    print(f"\n{title}")
    budgets, directions, residuals = {}, {}, {}
    for case in cases:
        difference = case.pulled_back_difference()
        dy, dx = case.pixel
        to_px2 = np.array([1.0 / dx ** 2, 1.0 / dy ** 2])
        covariance = np.diagonal(np.asarray(case.measured.covariance_mm2, float)).reshape(-1, 2)
        # beside the maps' figures: the measured error and the measurement's own prediction (px^2)
        budget = np.column_stack([case.window_budget(difference), (case.errors ** 2) @ to_px2, covariance @ to_px2])
        along = case.radial_tangential(case.errors)
        kinds = case.position_error_by_kind(difference)
        offsets = case.boundary_offsets(difference)
        print(f"  {case.name}: the windows calibrated s_edge^2 {case.meta['edge_variance_px2']:.4f} px^2; the true "
              f"images per kind: " + ", ".join(f"{k} {v:.4f}" for k, v in list(kinds.items())[1:])
              + f" (D^2 / v where quiet {kinds['D^2 / v where quiet']:.2f})")
        print("    boundaries drawn off the truth, RMS over 45 degree sectors (px): " + ", ".join(
            f"{name} {rms:.4f} (noise alone {null:.4f}; beyond it {np.sqrt(max(rms ** 2 - null ** 2, 0.0)):.4f})"
            for name, (rms, null) in offsets.items()))
        for band, mask in case.bands.items():
            budgets.setdefault(band, []).append(budget[mask])
            directions.setdefault(band, []).append(along[mask])
            residuals.setdefault(band, []).append(case.residual_over_model[mask])
    print("  per band, pooled:  the images' error through the windows' maps / predicted (/ its noise part; the edges' "
          "share of the prediction)  |  the measured error / the maps' e, the measurement's prediction / the maps'  "
          "|  measured chi^2 along the radius, around it  |  the windows' residual over the model")
    for band in budgets:
        b = np.vstack(budgets[band])
        b = b[np.isfinite(b[:, 0])]
        d = np.vstack(directions[band])
        print(f"    {band:<28s} n {len(b):4d}: {b[:, 0].sum() / (b[:, 1] + b[:, 2]).sum():.2f} "
              f"(/ noise {b[:, 0].sum() / b[:, 1].sum():.2f}; edges {b[:, 2].sum() / (b[:, 1] + b[:, 2]).sum():.2f})"
              f"  |  {b[:, 3].sum() / b[:, 0].sum():.2f}, {b[:, 4].sum() / (b[:, 1] + b[:, 2]).sum():.2f}"
              f"  |  {np.mean(d[:, 0] ** 2):.2f}, {np.mean(d[:, 1] ** 2):.2f}"
              f"  |  {np.nanmean(np.concatenate(residuals[band])):.2f}")


def shared_between_cases(cases: list[Case]) -> None:
    """The correlation between cases of the normalised errors of the windows they share (module text)."""
    print("  between cases, the same window's normalised error (0 when independent): mean correlation over pairs")
    normalised = [case.errors / np.sqrt(np.diagonal(np.asarray(case.measured.covariance_mm2, float))).reshape(-1, 2)
                  for case in cases]
    for band in cases[0].bands:
        tables = []
        for case, values in zip(cases, normalised):
            mask = case.bands[band]
            key = [tuple(np.round(p, 2)) for p in case.measured.position_mm[mask]]
            tables.append(dict(zip(key, values[mask])))
        common = sorted(set(tables[0]).intersection(*tables[1:]))
        if len(common) < 5:
            continue
        values = np.array([[table[k] for k in common] for table in tables]).reshape(len(cases), -1)
        pairs = [np.corrcoef(values[i], values[j])[0, 1] for i, j in combinations(range(len(cases)), 2)]
        print(f"    {band:<28s} {len(common)} windows: {np.mean(pairs):+.2f} (pairs {min(pairs):+.2f} to "
              f"{max(pairs):+.2f})")


class Splicer:
    """One case's loaded image, the same leg warped by the truth instead, and splices of the two (module text)."""

    def __init__(self, case: Case, others: list[Case], seed: int):
        dy, dx = case.pixel
        rows, cols = np.indices(case.reference.shape, dtype=float)
        x, y = material_points((cols + 0.5) * dx, (rows + 0.5) * dy,
                               as_displacement_fn(np.nan_to_num(case.field), case.pixel), case.motion)
        at_material = [y / dy - 0.5, x / dx - 0.5]
        anatomy = np.mean([other.reference for other in others], axis=0)
        self.noiseless = ndimage.map_coordinates(anatomy, at_material, order=3, mode="nearest")
        self.sigma = float(case.meta["noise_sigma"][1])
        self.rng = np.random.default_rng(seed)
        self.case = case
        self.loaded = case.setup.case.loaded.astype(float)
        self.warped, self.warped_again = self.warped_draw(), self.warped_draw()
        labels = ndimage.map_coordinates(case.labels, at_material, order=0, mode="nearest")
        self.boundaries = boundaries_between([labels == value for value in np.unique(labels)], SPLICE_REACH_PX)

    def warped_draw(self) -> np.ndarray:
        """The warped leg with a fresh draw of Rician noise of the loaded image's sigma."""
        return add_rician_noise(self.noiseless, self.sigma, self.rng)

    def splice(self, rest: np.ndarray, boundaries: np.ndarray) -> np.ndarray:
        return np.where(self.boundaries, boundaries, rest)

    def measure(self, loaded: np.ndarray, folder: Path) -> tuple[dict[str, float], dict[tuple, np.ndarray]]:
        """`calfit measure` on the case with this loaded image: (chi^2/n per band, {window position: its error
        (px), the bones' rigid motion removed}) against the truth."""
        source = self.case.case_dir
        folder.mkdir(parents=True)
        for item in source.iterdir():
            if item.is_file() and item.name not in ("points.csv", "loaded.png"):
                (folder / item.name).write_bytes(item.read_bytes())
        io.imsave(folder / "loaded.png", np.clip(np.round(loaded), 0, 65535).astype(np.uint16), check_contrast=False)
        run = folder.with_name(folder.name + "-run")
        run_measure(folder, run)
        setup = load_run(run)
        measured = setup.measurements("dic")
        errors = errors_against(measured, None, self.case.field)
        rows, _ = band_errors(measured, errors, setup.frame())
        whiten, _ = symmetric_roots(np.asarray(measured.covariance_mm2, float), "the measurement covariance")
        errors = without_rigid_motion(measured, errors, whiten).reshape(-1, 2) / np.array(self.case.pixel[::-1])
        return ({row.band: (row.chi2_per_value, row.count) for row in rows},
                {tuple(np.round(p, 2)): e for p, e in zip(measured.position_mm, errors)})


def spliced(cases: list[Case], scratch: Path, draws: int) -> None:
    """Which pixels of the other program's loaded image carry the windows' excess, and how far a band's chi^2/n of
    the warped leg scatters over `draws` more noise draws (module text)."""
    kinds = {"warped": lambda s: s.warped,
             "warped, its boundaries from the loaded image": lambda s: s.splice(s.warped, s.loaded),
             "loaded, its boundaries from the warped image": lambda s: s.splice(s.loaded, s.warped),
             "loaded": lambda s: s.loaded,
             "control: a second draw of the warped image": lambda s: s.warped_again,
             "control: warped, boundaries from the second draw": lambda s: s.splice(s.warped, s.warped_again),
             "control: second draw, boundaries from the first": lambda s: s.splice(s.warped_again, s.warped)}
    chi2 = {kind: {} for kind in kinds}
    radial = {kind: [] for kind in kinds}
    scatter = {}   # band -> (draws, 2) sums of chi^2 and of values over the cases
    for index, case in enumerate(cases):
        splicer = Splicer(case, [other for other in cases if other is not case], seed=index)
        centre = case.measured.position_mm.mean(axis=0)
        errors = {}
        for number, (kind, image) in enumerate(kinds.items()):
            bands, errors[kind] = splicer.measure(image(splicer), scratch / f"splice-{case.name}-{number}")
            for band, (value, count) in bands.items():
                chi2[kind].setdefault(band, []).append((value * count, count))
        for draw in range(draws):
            bands, _ = splicer.measure(splicer.warped_draw(), scratch / f"splice-{case.name}-draw-{draw}")
            for band, (value, count) in bands.items():
                scatter.setdefault(band, np.zeros((draws, 2)))[draw] += (value * count, count)
        deep = {tuple(np.round(p, 2)) for p, m in zip(case.measured.position_mm, case.bands[DEEP_FAT]) if m}
        shared = sorted(deep.intersection(*[set(e) for e in errors.values()]))
        for kind in kinds:
            direction = np.array(shared) - centre
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            radial[kind].append(np.einsum("ij,ij->i", np.array([errors[kind][k] for k in shared]), direction))
    print("  the loaded image spliced with the same leg warped by the truth: chi^2/n per band, pooled over the cases")
    for kind, bands in chi2.items():
        print(f"    {kind:<52s} " + "  ".join(f"{band} {sum(v for v, _ in rows) / sum(n for _, n in rows):.2f}"
                                                for band, rows in bands.items()))
    if draws:
        print(f"  the warped image over {draws} more noise draws, pooled over the cases: " + "  ".join(
            f"{band} {np.mean(v[:, 0] / v[:, 1]):.2f} (sd {np.std(v[:, 0] / v[:, 1], ddof=1) if draws > 1 else 0:.2f}, "
            f"{np.min(v[:, 0] / v[:, 1]):.2f}-{np.max(v[:, 0] / v[:, 1]):.2f})" for band, v in scatter.items()))
    print(f"  the {DEEP_FAT} windows along the radius (px): what the boundaries and the rest of an image add to the "
          "warped image's error")
    for image, (rest, edges) in (("loaded", ("loaded, its boundaries from the warped image",
                                             "warped, its boundaries from the loaded image")),
                                 ("control: a second draw of the warped image",
                                  ("control: second draw, boundaries from the first",
                                   "control: warped, boundaries from the second draw"))):
        base, whole = np.concatenate(radial["warped"]), np.concatenate(radial[image])
        from_rest, from_edges = np.concatenate(radial[rest]) - base, np.concatenate(radial[edges]) - base
        print(f"    {image:<52s} boundaries {np.sqrt(np.mean(from_edges ** 2)):.4f}, the rest "
              f"{np.sqrt(np.mean(from_rest ** 2)):.4f}, both {np.sqrt(np.mean((whole - base) ** 2)):.4f} "
              f"(non-linearity {np.sqrt(np.mean((whole - base - from_rest - from_edges) ** 2)):.4f}); their correlation "
              f"{np.corrcoef(from_edges, from_rest)[0, 1]:+.2f} over {len(base)} windows")


class SampledEdges:
    """How a renderer that averages S x S samples per pixel draws a case's skin and fascia, against the true mesh's
    boundaries (module text)."""

    def __init__(self, case: Case, truth: Path):
        mesh = np.load(truth)
        nodes, corners = mesh["nodes_mm"], mesh["cells"][:, :3]
        self.tissue = np.where(mesh["material"] == "FAT", 1, 2)   # 0: outside the mesh (air, bone)
        self.reference = Triangulation(nodes[:, 0], nodes[:, 1], corners)
        moved = nodes + mesh["u_mm"]
        self.deformed = Triangulation(moved[:, 0], moved[:, 1], corners)
        self.case = case
        labels = case.labels
        levels = [np.median(case.reference[ndimage.binary_erosion(labels == value, iterations=3)])
                  for value in (0, FAT, MUSCLE)]
        self.levels = np.array(levels)
        self.near_bone = ndimage.binary_dilation(labels == BONE, iterations=BONE_MARGIN_PX)

    def coverage(self, mesh: Triangulation, rows, cols, samples: int, to_mesh) -> np.ndarray:
        """(n, 3) the share of each pixel's samples x samples points outside the mesh, in fat, in muscle."""
        dy, dx = self.case.pixel
        offsets = (np.arange(samples) + 0.5) / samples
        sub_rows, sub_cols = (a.ravel() for a in np.meshgrid(offsets, offsets, indexing="ij"))
        x, y = to_mesh(((cols[:, None] + sub_cols) * dx).ravel(), ((rows[:, None] + sub_rows) * dy).ravel())
        triangle = mesh.get_trifinder()(x, y)
        tissue = np.where(triangle >= 0, self.tissue[triangle], 0).reshape(len(rows), -1)
        return np.stack([(tissue == value).mean(axis=1) for value in range(3)], axis=1)

    def drawing_error(self, mesh: Triangulation, to_mesh, samples: int) -> np.ndarray:
        """The grey-level error of an image drawn with samples x samples per pixel, on the pixels its boundaries
        cross."""
        shape = self.case.reference.shape
        rows, cols = (a.ravel() for a in np.indices(shape))
        coarse = self.coverage(mesh, rows, cols, samples, to_mesh).reshape(*shape, 3)
        crossed = ndimage.binary_dilation(coarse.max(axis=2) < 1.0)
        rows, cols = np.nonzero(crossed)
        error = np.zeros(shape)
        error[rows, cols] = (coarse[rows, cols] - self.coverage(mesh, rows, cols, SAMPLED_FINE, to_mesh)) @ self.levels
        return error

    def window_errors(self, samples: int, whiten: np.ndarray) -> np.ndarray:
        """(2N,) mm: each window's error from how both images draw their boundaries, the bones' motion removed (by
        generalised least squares with `whiten`)."""
        case = self.case
        reference = self.drawing_error(self.reference, lambda x, y: (x, y), samples)
        loaded = self.drawing_error(self.deformed, case.motion.inverse().apply, samples)
        pulled_back = ndimage.map_coordinates(loaded, case.loaded_grid(), order=1, mode="constant")
        difference = np.where(self.near_bone, 0.0, reference - pulled_back).ravel()
        operators = case.measured.operators
        errors = np.concatenate([(B @ difference[pixels]) * operators.to_mm
                                 for B, pixels in zip(operators.B, operators.noise_pixels)])
        return without_rigid_motion(case.measured, errors, whiten)


def sampled_edges(cases: list[Case], folder: Path, samples: int) -> None:
    """What the boundaries drawn with samples x samples per pixel make of each band's chi^2/n (module text); the same
    with one sample less and one more per side is the control: another renderer's error, which the images do not
    carry, raises the bands instead."""
    print("  the skin and the fascia drawn with S x S samples per pixel, against the true mesh: chi^2/n per band, "
          "pooled over the cases; measured, less the drawn boundaries' error (that error alone; its correlation with "
          "the measured error)")
    drawings = [SampledEdges(case, folder / "truth" / f"{case.name}.npz") for case in cases]
    # against the windows' error model without the drawing's own term (`imaging.drawing`), which calfit adds when it
    # finds the images point-sampled: what the drawn error explains of that model's excess
    models = []
    for case in cases:
        covariance = np.asarray(case.measured.covariance_mm2, float)
        if case.drawing_factor is not None:
            covariance = covariance - case.drawing_factor @ case.drawing_factor.T
        whiten = symmetric_roots(covariance, "the measurement covariance")[0]
        models.append((covariance, whiten, without_rigid_motion(case.measured, errors_against(case.measured, None,
                                                                                               case.field), whiten)))
    for count in [samples] + [s for s in (samples - 1, samples + 1) if s > 1]:
        pooled = {}
        for case, drawing, (covariance, whiten, measured) in zip(cases, drawings, models):
            drawn = drawing.window_errors(count, whiten)
            for band, mask in case.bands.items():
                values = np.repeat(mask, 2)
                if not values.any():
                    continue
                block = covariance[np.ix_(values, values)]
                row = pooled.setdefault(band, {"sums": np.zeros(3), "n": 0, "measured": [], "drawn": []})
                row["sums"] += [e @ np.linalg.solve(block, e) for e in (measured[values],
                                                                         measured[values] - drawn[values],
                                                                         drawn[values])]
                row["n"] += int(values.sum())
                row["measured"].append(measured[values])
                row["drawn"].append(drawn[values])
        label = f"S = {count}" + ("" if count == samples else " (control)")
        print(f"    {label:<14s} " + "  ".join(
            f"{band} {row['sums'][0] / row['n']:.2f} -> {row['sums'][1] / row['n']:.2f} "
            f"({row['sums'][2] / row['n']:.2f}; "
            f"{np.corrcoef(np.concatenate(row['measured']), np.concatenate(row['drawn']))[0, 1]:+.2f})"
            for band, row in pooled.items()))


def foreign_cases(folder: Path, scratch: Path) -> list[Case]:
    answers = json.loads((folder / "answers.json").read_text())
    cases = []
    for case in sorted(p for p in folder.iterdir() if (p / "case.toml").is_file()):
        truth = folder / "truth" / f"{case.name}.npz"
        if not truth.is_file() or case.name not in answers:
            continue
        motion = answers[case.name]["scanner_motion_image_frame"]
        labels = io.imread(case / "labels.png") if (case / "labels.png").is_file() else None
        # measured from the two images (and the case's labels, as `benchmarks/imaging.py` does); points.csv unused
        cases.append(Case(case.name, case, scratch / f"run-{case.name}",
                          lambda shape, pixel, truth=truth: field_from_mesh_file(truth, shape, pixel),
                          RigidMotion(motion["rotation_deg"], tuple(motion["shift_mm"]), tuple(motion["about_mm"])),
                          labels))
    return cases


def renderer_cases(scratch: Path, seed: int = 3) -> list[Case]:
    cases = []
    for name, phantom in (("CalfPhantom", CalfPhantom()), ("MRIPhantom", MRIPhantom.at_resolution(0.36))):
        case, truth = make_phantom_case(scratch / name, phantom=phantom, theta_kPa=random_truth(seed), n_elements=4000,
                                        labels=None, points_spacing_mm=None, noise_seeds=(10, 20),
                                        rigid=RENDERER_MOTION)
        cases.append(Case(name, case, scratch / f"run-{name}",
                          lambda shape, pixel, truth=truth: np.load(truth / "displacement_mm.npy"), RENDERER_MOTION))
    return cases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--foreign", type=Path, help="case folders of another program, with truth/ and answers.json")
    parser.add_argument("--renderers", action="store_true",
                        help="with --foreign, also a case of each of calfit's renderers (the default without it)")
    parser.add_argument("--splice", action="store_true",
                        help="with --foreign, splice each loaded image with the same leg warped by the truth (module "
                             "text; about 7 minutes for four cases)")
    parser.add_argument("--draws", type=int, default=6,
                        help="with --splice, more noise draws of the warped leg, for the scatter of a band's chi^2/n "
                             "(default 6, a minute each for four cases)")
    parser.add_argument("--sampling", type=int, metavar="S",
                        help="with --foreign, the error of the skin and the fascia drawn with S x S samples per pixel "
                             "in both images, from the true mesh (module text; the other program's cases: S = 3)")
    arguments = parser.parse_args()
    arguments.renderers |= arguments.foreign is None
    with tempfile.TemporaryDirectory(prefix="calfit-bench-budget-") as scratch:
        scratch = Path(scratch)
        if arguments.foreign:
            cases = foreign_cases(arguments.foreign, scratch)
            report(f"The other program's {len(cases)} cases", cases)
            if len(cases) > 1:
                shared_between_cases(cases)
            if arguments.sampling:
                sampled_edges(cases, arguments.foreign, arguments.sampling)
            if arguments.splice and len(cases) > 1:
                spliced(cases, scratch, arguments.draws)
        if arguments.renderers:
            for case in renderer_cases(scratch):
                report(f"calfit's {case.name}, one case", [case])


if __name__ == "__main__":
    main()
