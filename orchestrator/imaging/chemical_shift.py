"""The fat's chemical shift, measured on the image across the fat/muscle interface.

Fat and water precess at frequencies 3.5 ppm apart, and the frequency encodes position along the readout: an MR
image shows the fat's signal displaced along the readout by (3.5e-6 x the Larmor frequency) / (the readout's
bandwidth per pixel), one to two pixels at 1.5-3 T, while the water's tissues (muscle, skin) stay where they are.
The displacement is fixed to the scanner's axes and the same in every image of a protocol. On a calf it moves the
bright subcutaneous fat against the muscle it lies on: on the side the fat moves away from, a dark band opens
between them; on the other side the two signals overlap in a band brighter than fat. The edge where the bright fat
ends, which the mesh takes for the fat/muscle interface (`meshing.labels`), is then off the tissues' interface by
the projection of the displacement on its normal: +-0.6 mm on the two sides of a calf imaged at 1.4 pixels of
0.41 mm, enough to thicken the fat layer there by a tenth.

The measurement. Across the interface, along the normal n from the muscle into the fat, a profile p(s) of the
image is modelled as the muscle's level m up to the water's edge b and the fat's level f beyond the fat's edge e,
blurred by the image's point-spread function:

    p(s) = m Phi((b - s) / sigma) + f Phi((s - e) / sigma),   e - b = w + delta . n,

w the width of the dark line between them on the tissues themselves (the deep fascia) and delta the fat's
displacement on the image (the two edges overlap, in a band brighter than fat, where e < b). A scanner's
point-spread function is the band limit's: ringing that no Gaussian follows and whose tails carry the profile's
moments beyond any window (the edges read from the moments of the raw profiles, a blur-free relation, were off by
15-20 % of the shift on a band-limited scene, and came in pairs that the moments could not tell apart). The image
is therefore smoothed first by a Gaussian of PROFILE_SMOOTHING_PX, which makes the blur nearly Gaussian, and sigma
is the one of SIGMA_FACTORS x that Gaussian that fits all the profiles best; per profile, m and f are linear and
(b, e) found on a grid of EDGE_GRID_MM. Over the interface's points, e - b regressed on the normal's components
(a robust least squares, Huber weights) gives w and delta with their standard errors. Septa and streaks that
cross a profile scatter it; the regression does not care which way. Measured (tests/imaging/test_chemical_shift.py, and
the development cases): on scenes made as a scanner makes them, shifts of 1.4, -1.8, 1.2 and -1.5 px read 1.34,
-1.77, 0.98 and -1.43 px (the narrower of the two bands, fascia and shift overlapping, is read a little too
narrow where it is under the blur); on the other program's k-space calves, 1.4 px along x read 1.21 +- 0.05 px, and
another case -1.70 +- 0.03 px; on four calves another program drew without a chemical shift, 0.02-0.11 +- 0.13 px,
not significant. Within 0.1 mm, then, where the shift it corrects is 0.6-0.7 mm.

`fat_shift` returns the estimate and whether it stands out of its error (a chi^2 test of delta = 0 on its two
components at SIGNIFICANCE); the caller moves the fat/muscle interface back by it only then.

The header first. A DICOM image's header gives the shift's size along the readout from the sequence itself
(`case.acquisition`: 3.5 ppm of the imaging frequency over the pixel bandwidth), exact where the profiles' reading is
not: on calfit's k-space renderer, whose fascia is as wide as the shift, the profiles read 1.95 px for 1.40
(docs/validation/scanner-images.md). The sign (which way along the readout the fat moves) is the readout gradient's
polarity, in no standard tag, so the profiles still give it: `fat_shift` with the header's size takes the
profiles' component along the readout (the header's axis, or the larger of the two components when the header does
not say) and keeps its sign when it stands out of its error (a two-sided test at SIGNIFICANCE), the size the
header's. When it does not, the profiles' reading stands alone, and the sentence says why.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage, special, stats
from scipy.spatial import cKDTree

from ..core.digits import PLUS_MINUS

PROFILE_HALF_MM = 3.0     # a profile reaches this far into each tissue: beyond the blur, within the fat layer
PLATEAU_MM = 0.8          # the tissues' levels read over this much of each end of a profile (the contrast check)
PROFILE_STEP_MM = 0.05
PROFILE_SMOOTHING_PX = 1.5   # the Gaussian the image is smoothed with before its profiles are fitted
SIGMA_FACTORS = (0.75, 0.85, 0.95, 1.05, 1.15, 1.25, 1.35)   # the profiles' blur, in units of that Gaussian
EDGE_GRID_MM = 0.025
PROFILE_SPACING_MM = 0.5  # profiles at least this far apart: a septum (0.3-0.6 mm) crossing the interface is in one
MAX_EDGE_MM = 1.5         # a profile whose edges come out farther from its centre than this did not cross the interface
MIN_CONTRAST = 1.3        # the fat at least this much brighter than the muscle on a profile that is used
MIN_PROFILES = 30
SIGNIFICANCE = 0.01       # delta is taken when the chi^2 test of delta = 0 rejects it at this level
HUBER_SCALE = 1.5         # residuals beyond this many robust standard deviations are down-weighted
ROBUST_ROUNDS = 20
HEADER_SIZE_UNCERTAINTY = 0.03   # the header's size: the fat's main resonance lies 3.4-3.5 ppm from water


@dataclass(frozen=True)
class FatShift:
    """The fat's displacement on the image (mm, image frame: x right, y down) and what was measured to find it."""

    shift_mm: tuple[float, float]
    standard_error_mm: tuple[float, float]
    fascia_width_mm: float        # w: the dark line between muscle and fat, the chemical shift apart
    profiles: int
    scatter_mm: float             # robust standard deviation of one profile's e - b about the regression
    p_value: float                # of the chi^2 test of delta = 0 (with the header's size: of the sign's test)
    source: str = "image"         # "image": the profiles' reading; "header": the header's size, the profiles' sign
    header_sentence: str | None = None                 # what the header said (`Acquisition.sentence`)
    image_shift_mm: tuple[float, float] | None = None  # the profiles' own reading, when the header's size is taken

    @property
    def significant(self) -> bool:
        return self.p_value < SIGNIFICANCE

    def in_pixels(self, pixel_size_mm) -> tuple[float, float]:
        """(x, y) in pixels of `pixel_size_mm` (row, column)."""
        dy, dx = (float(v) for v in pixel_size_mm)
        return self.shift_mm[0] / dx, self.shift_mm[1] / dy

    def as_dict(self, pixel_size_mm) -> dict:
        return {"shift_mm": list(self.shift_mm), "standard_error_mm": list(self.standard_error_mm),
                "shift_px": list(self.in_pixels(pixel_size_mm)), "fascia_width_mm": self.fascia_width_mm,
                "profiles": self.profiles, "scatter_mm": self.scatter_mm, "p_value": self.p_value,
                "significant": self.significant, "source": self.source, "header": self.header_sentence,
                "image_shift_mm": None if self.image_shift_mm is None else list(self.image_shift_mm)}

    @classmethod
    def from_dict(cls, info: dict) -> "FatShift":
        image = info.get("image_shift_mm")
        return cls(tuple(info["shift_mm"]), tuple(info["standard_error_mm"]), info["fascia_width_mm"],
                   info["profiles"], info["scatter_mm"], info["p_value"], info.get("source", "image"),
                   info.get("header"), None if image is None else tuple(image))

    def sentence(self, pixel_size_mm) -> str:
        """What a user reads of it (setup lines)."""
        px, py = self.in_pixels(pixel_size_mm)
        dy, dx = (float(v) for v in pixel_size_mm)
        sx, sy = self.standard_error_mm[0] / dx, self.standard_error_mm[1] / dy
        if self.source == "header":
            ix, iy = self.image_shift_mm[0] / dx, self.image_shift_mm[1] / dy
            return (f"chemical shift: the fat's signal lies ({px:+.2f}, {py:+.2f}) px along (x, y): "
                    f"{self.header_sentence}, its sign from {self.profiles} profiles across the fat/muscle interface, "
                    f"which read ({ix:+.2f}, {iy:+.2f}) px; the fat/muscle interface is moved back by it")
        measured = (f"({px:+.2f} {PLUS_MINUS} {sx:.2f}, {py:+.2f} {PLUS_MINUS} {sy:.2f}) px along (x, y), from "
                    f"{self.profiles} profiles across the fat/muscle interface")
        if self.header_sentence:
            measured += f" ({self.header_sentence} is not taken: the profiles do not tell its sign)"
        if self.significant:
            return (f"chemical shift: the fat's signal lies {measured}; the fat/muscle interface is moved back by it "
                    f"(p = {self.p_value:.1g} that there is none)")
        return f"chemical shift: none found, {measured} (p = {self.p_value:.2g}); the fat/muscle interface left as found"


def interface_edges(image: np.ndarray, points_mm: np.ndarray, normals: np.ndarray, pixel_size_mm) -> np.ndarray:
    """(K, 2) the water's and the fat's edges (b, e), mm along the normals from `points_mm` (module text), NaN
    where a profile did not cross a fat/muscle interface (the fat not MIN_CONTRAST times brighter than the muscle,
    an edge at the end of the grid). normals: (K, 2) unit, from the muscle into the fat."""
    dy, dx = (float(v) for v in pixel_size_mm)
    smooth = ndimage.gaussian_filter(np.asarray(image, float), PROFILE_SMOOTHING_PX)
    s = np.arange(-PROFILE_HALF_MM, PROFILE_HALF_MM + 0.5 * PROFILE_STEP_MM, PROFILE_STEP_MM)
    at = np.asarray(points_mm, float)[:, None, :] + s[None, :, None] * np.asarray(normals, float)[:, None, :]
    profile = ndimage.map_coordinates(smooth, [at[..., 1] / dy - 0.5, at[..., 0] / dx - 0.5], order=3, mode="nearest")
    grid = np.arange(-MAX_EDGE_MM, MAX_EDGE_MM + 0.5 * EDGE_GRID_MM, EDGE_GRID_MM)
    best_total, best = np.inf, None
    for factor in SIGMA_FACTORS:
        sigma = factor * PROFILE_SMOOTHING_PX * np.sqrt(dx * dy)
        water = special.ndtr((grid[:, None] - s[None, :]) / sigma)     # (G, S): the muscle up to b
        fat = special.ndtr((s[None, :] - grid[:, None]) / sigma)       # the fat beyond e
        ww, ff, wf = np.sum(water ** 2, axis=1)[:, None], np.sum(fat ** 2, axis=1)[None, :], water @ fat.T
        pw, pf = profile @ water.T, profile @ fat.T                    # (K, G)
        determinant = ww * ff - wf ** 2                                # (G_b, G_e)
        with np.errstate(divide="ignore", invalid="ignore"):
            explained = (pw[:, :, None] ** 2 * ff[None] - 2.0 * pw[:, :, None] * pf[:, None, :] * wf[None]
                         + pf[:, None, :] ** 2 * ww[None]) / determinant[None]
        explained = np.where(np.isfinite(explained), explained, -np.inf).reshape(len(profile), -1)
        pick = np.argmax(explained, axis=1)
        total = float(np.sum(profile ** 2) - explained[np.arange(len(profile)), pick].sum())
        if total < best_total:
            best_total, best = total, pick
    b_index, e_index = np.unravel_index(best, (len(grid), len(grid)))
    edges = np.stack([grid[b_index], grid[e_index]], axis=1)
    ends = int(round(PLATEAU_MM / PROFILE_STEP_MM))
    m, f = profile[:, :ends].mean(axis=1), profile[:, -ends:].mean(axis=1)
    inner = np.all((b_index[:, None] > 0, b_index[:, None] < len(grid) - 1, e_index[:, None] > 0,
                    e_index[:, None] < len(grid) - 1), axis=0)[:, 0]
    edges[~(inner & (m > 0) & (f > MIN_CONTRAST * m))] = np.nan
    return edges


def spaced(points_mm: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Indices of points, in order, each at least spacing_mm from those kept before it."""
    kept: list[int] = []
    tree = cKDTree(points_mm)
    taken = np.zeros(len(points_mm), bool)
    for k in range(len(points_mm)):
        if taken[k]:
            continue
        kept.append(k)
        taken[tree.query_ball_point(points_mm[k], spacing_mm)] = True
    return np.array(kept, int)


def fat_shift(image: np.ndarray, points_mm: np.ndarray, normals: np.ndarray, pixel_size_mm,
              acquisition=None) -> FatShift | None:
    """The fat's displacement on `image` (module text) from profiles along the fat/muscle interface at points_mm
    (N, 2), normals (N, 2) unit from the muscle into the fat; None when fewer than MIN_PROFILES profiles cross it.
    acquisition: the images' `case.acquisition.Acquisition`; when it gives the shift's size, that size is taken and
    the profiles give its sign (module text, "The header first")."""
    found = _profiles_shift(image, points_mm, normals, pixel_size_mm)
    size_mm = None if acquisition is None else acquisition.fat_shift_mm
    if found is None or size_mm is None:
        return found
    axis = {"x": 0, "y": 1}.get(acquisition.readout_axis or "", int(abs(found.shift_mm[1]) > abs(found.shift_mm[0])))
    component, error = found.shift_mm[axis], found.standard_error_mm[axis]
    p_sign = float(2.0 * stats.norm.sf(abs(component) / max(error, 1e-12)))
    if p_sign >= SIGNIFICANCE:
        return replace(found, header_sentence=acquisition.sentence())
    shift = [0.0, 0.0]
    shift[axis] = float(np.copysign(size_mm, component))
    # the header's size is exact up to the fat's spectrum (3.4-3.5 ppm: 3 %)
    spread = [0.0, 0.0]
    spread[axis] = HEADER_SIZE_UNCERTAINTY * size_mm
    return replace(found, shift_mm=tuple(shift), standard_error_mm=tuple(spread), p_value=p_sign, source="header",
                   header_sentence=acquisition.sentence(), image_shift_mm=found.shift_mm)


def _profiles_shift(image: np.ndarray, points_mm: np.ndarray, normals: np.ndarray, pixel_size_mm) -> FatShift | None:
    """The profiles' reading of the fat's displacement (module text), the header left aside."""
    points_mm, normals = (np.asarray(v, float).reshape(-1, 2) for v in (points_mm, normals))
    keep = spaced(points_mm, PROFILE_SPACING_MM)
    points_mm, normals = points_mm[keep], normals[keep]
    edges = interface_edges(image, points_mm, normals, pixel_size_mm)
    used = np.all(np.isfinite(edges), axis=1)
    if used.sum() < MIN_PROFILES:
        return None
    beta, covariance, scale = _robust_line(normals[used], edges[used, 1] - edges[used, 0])
    shift, shift_cov = beta[1:], covariance[1:, 1:]
    statistic = float(shift @ np.linalg.solve(shift_cov, shift))
    return FatShift((float(shift[0]), float(shift[1])), tuple(float(v) for v in np.sqrt(np.diag(shift_cov))),
                    float(beta[0]), int(used.sum()), scale, float(stats.chi2.sf(statistic, 2)))


def _robust_line(normals: np.ndarray, gap: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(w, delta_x, delta_y), their covariance and the residuals' robust scale: gap = w + delta . n fitted by least
    squares with Huber weights."""
    design = np.column_stack([np.ones(len(gap)), normals])
    weights = np.ones(len(gap))
    for _ in range(ROBUST_ROUNDS):
        beta, *_ = np.linalg.lstsq(design * weights[:, None], gap * weights, rcond=None)
        residual = gap - design @ beta
        scale = 1.4826 * float(np.median(np.abs(residual))) + 1e-12
        weights = np.sqrt(np.clip(HUBER_SCALE * scale / np.maximum(np.abs(residual), 1e-12), 0.0, 1.0))
    return beta, scale ** 2 * np.linalg.inv((design * weights[:, None] ** 2).T @ design), scale


FAT_STEP_WIDTH = 0.1   # the fat's share rises from water to fat over this fraction of the two levels' contrast


def fat_signal(image: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(H, W) the fat's share of `image` (`windows`, the chemical shift): the image where it is as bright as fat,
    nothing where it is as dark as the water's tissues, a smooth step between at the middle of the fat's and the
    muscle's levels (their medians over labels 1 and 2). Septa and vessels in the fat, fat streaks in the muscle
    and the fat against the muscle are then the fat's edges; the muscle's texture, its septa and the skin against
    the air the water's."""
    image = np.asarray(image, float)
    labels = np.asarray(labels)
    fat_level = float(np.median(image[labels == 1])) if np.any(labels == 1) else float(np.max(image))
    water_level = float(np.median(image[labels == 2])) if np.any(labels == 2) else 0.0
    contrast = max(fat_level - water_level, 1e-12)
    middle = 0.5 * (fat_level + water_level)
    return image * special.expit((image - middle) / (FAT_STEP_WIDTH * contrast / 4.0))
