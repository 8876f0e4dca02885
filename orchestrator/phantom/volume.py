"""A 3D phantom leg: unloaded and loaded volumes of the calf, sliced by height, for volume studies.

The leg is a stack of the calf slices of `geometry` (Avril et al., section 2.1.1 and Fig. 1: tibia, fibula, fat
with skin, muscle; the landmarks of section 3.2), one `CalfShape` per height z (mm along the leg, the slices'
normal, +z towards the knee). `LegProfile` makes that shape vary smoothly with z: the outline is widest at the
calf's largest girth and narrows by 15 % towards the ankle, the fat at the back thickens higher up, and the tibia
and fibula change radius and drift a little, so the bones are not perfect prisms.

The tissue texture (`appearance.TextureField`, the structure that digital image correlation tracks) is coherent
along the leg, as septa and fibres run along it: at height z it is cos(a) g1 + sin(a) g2 of two fixed 2D fields
g1, g2 of the slice frame, with a(z) turning by a quarter turn over `LegProfile.texture_turn_mm`. Its variance is
1 at every height, and two slices 8 mm apart correlate at cos(pi/2 * 8/100) = 0.99.

The truth varies along the leg too: the four constants of the first paper's law (C10 and Kv of fat and muscle,
`forward.TABLE2_CENTRAL_KPA` order) and the garment's tension (graduated compression, highest at the ankle end)
are `HeightProfile`s, linear between their knots.

`write_volume_case` solves, for each height it needs, the plane-strain leg model of that slice at its truth with
the engine, on a truth mesh of the phantom's own geometry (2,000 T6 elements by default: not the fit's mesh, so no
inverse crime), and interpolates the nodal displacement on the slice's pixels, as `study.make_phantom_case` does.

The unloaded volume's slice k is the `CalfPhantom` of height z_k rendered at its material points (its own noise
seed). The loaded volume is what the scanner sees after the leg moved rigidly between the sessions
(`RigidMotion3D`, patient mm, the unloaded session's frame to the loaded one's): the scanner point P of a loaded
voxel is the point p = motion^-1(P) of the unloaded session, at a height p_z between two solved heights; its
material point X solves X + u(X, p_z) = (p_x, p_y), u interpolated linearly in z between the two heights' fields
(the fixed point of `render.undeform`), and its grey level blends the leg's slices 0.5 mm apart at X linearly in
z (the displacement varies slowly along the leg, the outline does not: blending the solved slices 8 mm apart would
put every edge on a chord of its course along the leg). Each loaded slice is sampled 3 times finer than its pixels and keeps the k-space of its pixel grid, as
`CalfPhantom.render` does (a 2D acquisition: the slice's own thickness is not modelled), then the scanner's bias
and Rician noise. Nothing of the loaded volume is resampled from the unloaded one.

Frames: a volume's affine is `imaging.volume.volume_affine(pixel_size, spacing, (0, 0, first height))`, so slice
positions are heights. The affine maps voxel (row, column, slice) to the patient point (column dx, row dy, z),
while the slice frame of a 2D case (`imaging.frame`) puts that pixel's centre at ((column + 0.5) dx,
(row + 0.5) dy): patient x, y are the slice frame's less half a pixel. The motion is in patient mm; geometry,
landmarks and displacement fields are in the slice frame.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import ndimage

from ..case._formats import write_png16
from ..case.volume import RigidMotion3D, volume_affine, write_nifti_volume
from ..core.files import staged_folders
from ..core.frame import mm_to_index, pixel_centres_mm
from ..meshing import Mesh
from ..model.forward import LEG_PARAMETERS, LegModel, MeshInterpolator, field_on_pixels
from .appearance import T1Contrast, TextureField, add_rician_noise, bias_field
from .geometry import LANDMARK_NAMES, CalfGeometry, CalfShape
from .mesh import truth_mesh
from .render import CalfPhantom, _keep_pixel_bandwidth, render_unloaded, undeform

DEFAULT_HEIGHTS_MM = tuple(196.0 + 8.0 * k for k in range(14))
# Slices close enough for the DIC: from one slice to the next the skin moves by less than a pixel (0.1-0.7 px here,
# where it moves 1-4 px between the default's slices 8 mm apart below 270 mm), so that a loaded slice resampled
# between slices is one tissue plane (`volume_study.skin_shift_px`). What the demo and the volume study test use.
FINE_HEIGHTS_MM = tuple(247.0 + 3.0 * k for k in range(15))
FINE_STUDIED_MM = FINE_HEIGHTS_MM[3:]   # the 12 that the loaded session holds after DEFAULT_MOTION's slide of 6 mm
LEG_MARGIN_MM = 2.0              # the skin must stay this far inside the field of view in both sessions
COMPRESSION_POINTS = ("B", "B1", "C", "D")


@dataclass(frozen=True)
class HeightProfile:
    """A value (a float or a vector) as a function of height, linear between knots and constant beyond them."""

    heights_mm: tuple[float, ...]
    values: tuple

    def __post_init__(self):
        if len(self.heights_mm) != len(self.values) or not self.heights_mm:
            raise ValueError("a height profile needs one value per knot height, and at least one knot")
        if np.any(np.diff(self.heights_mm) <= 0):
            raise ValueError(f"the knot heights of a profile must increase: {self.heights_mm}")

    def at(self, height_mm: float):
        """The value at that height: a float, or a tuple of floats for a vector profile."""
        table = np.asarray(self.values, float)
        if table.ndim == 1:
            return float(np.interp(height_mm, self.heights_mm, table))
        return tuple(float(np.interp(height_mm, self.heights_mm, column)) for column in table.T)

    def as_dict(self) -> dict:
        return {"heights_mm": [float(h) for h in self.heights_mm],
                "values": np.asarray(self.values, float).tolist()}


# The truth of the default leg: stiffer muscle and fat at the ankle end, every constant at least 10 % away from
# Table 2's central values (the fits' default start) at every height, inside the box of materials.AVRIL_BOUNDS_KPA.
DEFAULT_TRUTH = HeightProfile((196.0, 300.0), ((6.0, 14.0, 82.0, 84.0), (5.0, 12.4, 94.0, 77.0)))
# Graduated compression: the garment pulls hardest at the ankle end.
DEFAULT_TENSION = HeightProfile((196.0, 300.0), (0.20, 0.14))
# Between the sessions the leg slid 6 mm along itself (towards the ankle), turned 3 degrees about its axis, tilted
# by 0.9 degree and moved 2.5 mm across; about the leg's axis at mid-volume.
DEFAULT_MOTION = RigidMotion3D(rotation_vector_deg=(0.7, -0.6, 3.0), translation_mm=(2.0, -1.5, -6.0),
                               centre_mm=(68.0, 70.0, 248.0))


@dataclass(frozen=True)
class LegProfile:
    """The calf slice's shape as a function of height z (mm).

    `reference` is the slice at the largest girth (`widest_height_mm`). Below and above it the outline (half
    width and half depth) and the fibula's offset from the leg's centre are scaled by
    1 - narrowing ((z - widest) / (narrowest - widest))^2: 15 % narrower at `narrowest_height_mm`. The fat at the
    back, the bones' radii, the tibia's direction and the fibula's place change linearly with z (per 100 mm), and
    the leg's axis drifts by `axis_slope` mm per mm of height, as a real leg's axis is not the scanner's normal."""

    reference: CalfShape = CalfShape(centre_mm=(68.4, 66.0))   # the back bulges: centred in the field of view
    widest_height_mm: float = 284.0
    narrowest_height_mm: float = 200.0
    narrowing: float = 0.15
    fat_back_per_100mm: float = 3.0          # the back's fat thickens higher up
    tibia_radius_per_100mm: float = 0.7
    fibula_radius_per_100mm: float = 0.4
    tibia_turn_deg_per_100mm: float = -4.0
    fibula_drift_per_100mm: tuple[float, float] = (1.0, 1.5)
    axis_slope: tuple[float, float] = (0.010, -0.006)
    texture_turn_mm: float = 100.0           # the texture turns from its first field to its second over this height

    def outline_scale(self, height_mm: float) -> float:
        relative = (height_mm - self.widest_height_mm) / (self.narrowest_height_mm - self.widest_height_mm)
        return 1.0 - self.narrowing * relative ** 2

    def shape_at(self, height_mm: float) -> CalfShape:
        """The `CalfShape` of the slice at that height."""
        s, scale = self.reference, self.outline_scale(height_mm)
        rise = height_mm - self.widest_height_mm
        above = rise / 100.0   # the rates are per 100 mm; negative below the widest
        centre = (s.centre_mm[0] + self.axis_slope[0] * rise, s.centre_mm[1] + self.axis_slope[1] * rise)
        fibula = (scale * s.fibula_offset_mm[0] + self.fibula_drift_per_100mm[0] * above,
                  scale * s.fibula_offset_mm[1] + self.fibula_drift_per_100mm[1] * above)
        return dataclasses.replace(
            s, centre_mm=centre, half_width_mm=scale * s.half_width_mm, half_depth_mm=scale * s.half_depth_mm,
            fat_back_mm=s.fat_back_mm + self.fat_back_per_100mm * above,
            tibia_radius_mm=s.tibia_radius_mm + self.tibia_radius_per_100mm * above,
            tibia_angle_deg=s.tibia_angle_deg + self.tibia_turn_deg_per_100mm * above,
            fibula_radius_mm=s.fibula_radius_mm + self.fibula_radius_per_100mm * above, fibula_offset_mm=fibula)

    def geometry_at(self, height_mm: float) -> CalfGeometry:
        """The slice at that height (ValueError if its parts overlap there: the profile went too far)."""
        return CalfGeometry(self.shape_at(height_mm))

    def texture_angle(self, height_mm: float) -> float:
        """The angle a(z) of the texture's blend cos(a) g1 + sin(a) g2 (radians)."""
        return 0.5 * math.pi * (height_mm - self.widest_height_mm) / self.texture_turn_mm


class BlendedTexture:
    """cos(a) g1 + sin(a) g2 of two texture fields: unit variance at any a, the same texture along the leg."""

    def __init__(self, first: TextureField, second: TextureField, angle: float):
        self.first, self.second, self.angle = first, second, angle

    def __call__(self, x, y) -> np.ndarray:
        return math.cos(self.angle) * self.first(x, y) + math.sin(self.angle) * self.second(x, y)


@dataclass
class PhantomLeg:
    """The 3D phantom leg as a scanner with that pixel size and square field of view sees it: a `CalfPhantom` at
    any height, whose texture is the leg's blended texture at that height."""

    profile: LegProfile = field(default_factory=LegProfile)
    contrast: T1Contrast = field(default_factory=T1Contrast)
    pixel_size_mm: tuple[float, float] = (0.36, 0.36)
    field_of_view_mm: float = 136.8          # the widest slice (116 x 104 mm) with 10-16 mm on each side
    supersampling: int = 3

    def __post_init__(self):
        self.pixel_size_mm = tuple(float(v) for v in self.pixel_size_mm)
        extent = (self.image_shape[1] * self.pixel_size_mm[1], self.image_shape[0] * self.pixel_size_mm[0])
        seed = self.contrast.texture_seed
        self._fields = tuple(TextureField(extent, self.contrast.texture_correlation_mm, seed + k) for k in (0, 1))

    @property
    def image_shape(self) -> tuple[int, int]:
        dy, dx = self.pixel_size_mm
        return int(round(self.field_of_view_mm / dy)), int(round(self.field_of_view_mm / dx))

    def slice_phantom(self, height_mm: float) -> CalfPhantom:
        phantom = CalfPhantom(self.profile.geometry_at(height_mm), self.contrast, self.image_shape,
                              self.pixel_size_mm, self.supersampling)
        phantom.texture = BlendedTexture(*self._fields, self.profile.texture_angle(height_mm))
        return phantom


def solve_slice(phantom: CalfPhantom, theta_kPa: Sequence[float], tension_N_per_mm: float,
                n_elements: int = 2000) -> tuple[np.ndarray, Mesh]:
    """The plane-strain displacement (2, H, W) mm of the slice at theta_kPa under the garment, on the slice's
    pixels, with the truth mesh it was solved on."""
    from ..engine.runner import solve_once
    from ..fit.objectives import leg_rows

    mesh = truth_mesh(phantom, n_elements=n_elements)
    model = LegModel(mesh, tension_N_per_mm)
    nodal = leg_rows(solve_once(model, model.deck(theta_kPa),
                                f"the engine did not converge on the phantom slice at theta = {list(theta_kPa)} kPa, "
                                f"tension {tension_N_per_mm} N/mm; choose stiffer parameters or a smaller tension"),
                     len(mesh.nodes))
    weights = MeshInterpolator(mesh).pixel_weights(phantom.image_shape, phantom.pixel_size_mm)
    return field_on_pixels(weights, nodal, phantom.image_shape), mesh


def motion_matrix(motion: RigidMotion3D) -> np.ndarray:
    """The 4x4 matrix of a rigid motion of patient points."""
    origin = motion.apply(np.zeros(3))
    matrix = np.eye(4)
    matrix[:3, :3] = np.stack([motion.apply(axis) - origin for axis in np.eye(3)], axis=1)
    matrix[:3, 3] = origin
    return matrix


@dataclass
class LoadedSession:
    """The leg under the garment as the loaded session's scanner sees it (module text).

    phantoms: the slices at `fe_heights_mm` (evenly spaced, increasing); fields_mm (n, 2, H, W): each one's
    plane-strain displacement on its pixels (slice frame); affine: the loaded volume's (patient mm), the same
    convention as the unloaded one's; motion: unloaded session -> loaded session (patient mm)."""

    phantoms: Sequence[CalfPhantom]
    fe_heights_mm: np.ndarray
    fields_mm: np.ndarray
    affine: np.ndarray
    motion: RigidMotion3D
    # The leg whose slices give the grey levels between the solved heights, every geometry_step_mm. Blending the
    # solved slices 8 mm apart puts an edge on the chord between its two positions: 0.03 mm inside a skin whose
    # girth curves along the leg, twice the DIC's noise, an error of the phantom and not of what a scanner sees
    # (w (1 - w) |d2r/dz2| h^2 falls as the step squared). None: blend the solved slices.
    leg: "PhantomLeg | None" = None
    geometry_step_mm: float = 0.5
    _slices: dict = field(default_factory=dict, init=False, repr=False)   # the leg's slices made so far, by step

    def __post_init__(self):
        self.fe_heights_mm = np.asarray(self.fe_heights_mm, float)
        steps = np.diff(self.fe_heights_mm)
        if len(self.fe_heights_mm) < 2 or not np.allclose(steps, steps[0]) or steps[0] <= 0:
            raise ValueError("the solved heights must be at least two, increasing and evenly spaced")
        if len(self.phantoms) != len(self.fe_heights_mm) or self.fields_mm.shape[0] != len(self.phantoms):
            raise ValueError("one phantom and one displacement field per solved height")
        self._spacing = float(steps[0])
        # loaded voxel index -> unloaded voxel index: the affine, the motion undone, the affine undone
        self._index_map = np.linalg.inv(self.affine) @ motion_matrix(self.motion.inverse()) @ self.affine

    @property
    def pixel_size_mm(self) -> tuple[float, float]:
        return self.phantoms[0].pixel_size_mm

    def unloaded_points(self, x, y, slice_index: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The unloaded session's point p = motion^-1(P) of the loaded scanner points P at slice-frame (x, y) of
        loaded slice `slice_index`: its slice-frame (x, y) and its height as a continuous index into
        fe_heights_mm."""
        dy, dx = self.pixel_size_mm
        rows, cols = mm_to_index(x, y, self.pixel_size_mm)
        loaded_index = np.stack([rows, cols, np.full(np.shape(rows), float(slice_index))])
        shape = (3,) + (1,) * np.ndim(rows)
        index = np.tensordot(self._index_map[:3, :3], loaded_index, axes=1) + self._index_map[:3, 3].reshape(shape)
        height = np.tensordot(self.affine[2, :3], index, axes=1) + self.affine[2, 3]   # patient z: the affine is axial
        return (index[1] + 0.5) * dx, (index[0] + 0.5) * dy, (height - self.fe_heights_mm[0]) / self._spacing

    def displacement(self, X, Y, height_index) -> tuple[np.ndarray, np.ndarray]:
        """u(X, z) of the slice-frame points X, Y at continuous height index: bilinear on each height's pixels
        (`render.as_displacement_fn`), linear between heights, held constant beyond the edges."""
        rows, cols = mm_to_index(X, Y, self.pixel_size_mm)
        coordinates = np.stack([np.ravel(height_index), np.ravel(rows), np.ravel(cols)])
        return tuple(ndimage.map_coordinates(self.fields_mm[:, component], coordinates, order=1, mode="nearest")
                     .reshape(np.shape(X)) for component in (0, 1))

    def material_points(self, x, y, slice_index: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Material points (X, Y) and height index of the loaded scanner points at slice-frame (x, y) of loaded
        slice `slice_index`: X + u(X, z) = p, by `render.undeform`'s fixed point."""
        px, py, height_index = self.unloaded_points(x, y, slice_index)
        heights = np.ravel(height_index)
        X, Y = undeform(px, py, lambda X, Y, index: self.displacement(X, Y, heights[index]))
        return X, Y, height_index

    def intensity_at(self, X, Y, height_index, edge_mm: float = 0.0) -> np.ndarray:
        """Noise- and bias-free grey level of material points at continuous height index: the two bracketing
        slices' phantoms at X, blended linearly in height; the slices are the leg's every geometry_step_mm when
        `leg` is given, else the solved ones (constant beyond the solved heights)."""
        heights = self.fe_heights_mm[0] + np.clip(height_index, 0.0, len(self.phantoms) - 1.0) * self._spacing
        step = self.geometry_step_mm if self.leg is not None else self._spacing
        position = (heights - self.fe_heights_mm[0]) / step
        last = int(round((self.fe_heights_mm[-1] - self.fe_heights_mm[0]) / step))
        below = np.clip(np.floor(position).astype(int), 0, last - 1)
        weight = np.clip(position - below, 0.0, 1.0)
        value = np.zeros(np.shape(X))
        for k in np.unique(below):
            here = below == k
            lower = self._slice(int(k), step).intensity_at(X[here], Y[here], edge_mm)
            upper = self._slice(int(k) + 1, step).intensity_at(X[here], Y[here], edge_mm)
            value[here] = lower + weight[here] * (upper - lower)
        return value

    def _slice(self, k: int, step: float) -> CalfPhantom:
        """The phantom k steps above the lowest solved height (made once)."""
        if self.leg is None:
            return self.phantoms[k]
        if k not in self._slices:
            self._slices[k] = self.leg.slice_phantom(float(self.fe_heights_mm[0] + k * step))
        return self._slices[k]

    def render(self, slice_index: int, noise_seed: int | None) -> np.ndarray:
        """Loaded slice `slice_index`: the fine samples' material intensity, the pixel grid's k-space, the
        scanner's bias and Rician noise, as `CalfPhantom.render` makes a 2D slice."""
        phantom = self.phantoms[0]
        n = phantom.supersampling
        height, width = phantom.image_shape
        dy, dx = phantom.pixel_size_mm
        fine_rows, fine_cols = np.indices((height * n, width * n), dtype=float)
        X, Y, height_index = self.material_points((fine_cols + 0.5) * dx / n, (fine_rows + 0.5) * dy / n, slice_index)
        fine = self.intensity_at(X, Y, height_index, edge_mm=min(dx, dy) / n)
        signal = _keep_pixel_bandwidth(np.roll(fine, (-(n // 2), -(n // 2)), axis=(0, 1)), (height, width))
        signal *= bias_field(*pixel_centres_mm(phantom.image_shape, phantom.pixel_size_mm), phantom.extent_mm,
                             phantom.contrast.bias_amplitude)
        if noise_seed is None:
            return signal
        return add_rician_noise(signal, phantom.contrast.noise_sigma, np.random.default_rng(noise_seed))


def solved_heights(heights_mm: Sequence[float], image_shape: tuple[int, int], affine: np.ndarray,
                   motion: RigidMotion3D) -> np.ndarray:
    """The volume's heights extended by whole spacings until they bracket the height of every point of the
    unloaded session that a loaded voxel sees (the corners of the volume's box, mapped back by the motion)."""
    heights = np.asarray(heights_mm, float)
    spacing = heights[1] - heights[0]
    corners = np.array([[r, c, k, 1.0] for r in (-0.5, image_shape[0] - 0.5) for c in (-0.5, image_shape[1] - 0.5)
                        for k in (0, len(heights) - 1)]).T
    seen = (motion_matrix(motion.inverse()) @ affine @ corners)[2]
    below = int(max(0, math.ceil((heights[0] - seen.min()) / spacing - 1e-9)))
    above = int(max(0, math.ceil((seen.max() - heights[-1]) / spacing - 1e-9)))
    return heights[0] + spacing * np.arange(-below, len(heights) + above)


def compression_heights(profile: LegProfile, studied_mm: Sequence[float]) -> dict[str, float]:
    """The measuring points of compression hosiery (RAL-GZ 387) among the studied heights:
    B the lowest (ankle end), C the calf's largest girth, B1 a third of the way from B to C, D the highest."""
    studied = np.asarray(sorted(studied_mm), float)

    def nearest(height: float) -> float:
        return float(studied[np.argmin(np.abs(studied - height))])

    lowest, widest = float(studied[0]), nearest(profile.widest_height_mm)
    return {"B": lowest, "B1": nearest(lowest + (widest - lowest) / 3.0), "C": widest, "D": float(studied[-1])}


def height_tag(height_mm: float) -> str:
    """The height as it appears in the truth's file names: 204 for 204.0 mm, 204.5 for 204.5 mm."""
    return f"{height_mm:g}"


def write_volume_case(folder, truth_folder=None, *, profile: LegProfile = LegProfile(),
                      heights_mm: Sequence[float] = DEFAULT_HEIGHTS_MM, studied: Sequence[float] | None = None,
                      truth: HeightProfile = DEFAULT_TRUTH, tension: HeightProfile = DEFAULT_TENSION,
                      motion: RigidMotion3D = DEFAULT_MOTION, noise_seed: int = 0, n_truth_elements: int = 2000,
                      pixel_size_mm: tuple[float, float] = (0.36, 0.36), field_of_view_mm: float = 136.8,
                      contrast: T1Contrast | None = None, name: str = "phantom-leg",
                      tension_rel_uncertainty: float = 0.10, overwrite: bool = False) -> tuple[Path, Path]:
    """Write a volume case (unloaded.nii.gz, loaded.nii.gz, case.toml) and its truth folder (default the sibling
    `<folder>.truth`: truth.json, and per studied height displacement_<h>mm.npy and labels_<h>mm.png); both staged
    in temporary siblings and renamed into place when complete. Returns (case folder, truth folder).

    heights_mm: the volume's slice heights (evenly spaced, increasing); studied: the heights identified (default all
    but the first and the last); truth: C10_fat, C10_muscle, Kv_fat, Kv_muscle (kPa) along the leg; tension: the
    garment's (N/mm) along the leg; motion: the leg's rigid motion from the unloaded session to the loaded one
    (patient mm); noise_seed: unloaded slice k's noise has the seed 10000 noise_seed + k, loaded slice k's
    10000 noise_seed + 5000 + k. pixel_size_mm and field_of_view_mm make the slices' matrix (coarser for quick
    tests); n_truth_elements: the truth meshes' size."""
    folder = Path(folder)
    truth_folder = Path(truth_folder) if truth_folder is not None else folder.with_name(folder.name + ".truth")
    for target in (folder, truth_folder):
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} already exists; choose another folder or pass overwrite=True")
    heights = np.asarray(heights_mm, float)
    if len(heights) < 2 or not np.allclose(np.diff(heights), heights[1] - heights[0]) or heights[1] <= heights[0]:
        raise ValueError(f"the volume's heights must be at least two, increasing and evenly spaced: {list(heights)}")
    studied = [float(h) for h in (heights[1:-1] if studied is None else studied)]
    if not studied or any(not np.isclose(heights, h).any() for h in studied):
        raise ValueError(f"the studied heights {studied} must be some of the volume's heights {list(heights)}")

    leg = PhantomLeg(profile, contrast or T1Contrast(), pixel_size_mm, field_of_view_mm)
    spacing = float(heights[1] - heights[0])
    affine = volume_affine(leg.pixel_size_mm, spacing, (0.0, 0.0, float(heights[0])))
    fe_heights = solved_heights(heights, leg.image_shape, affine, motion)
    phantoms = [leg.slice_phantom(h) for h in fe_heights]
    _check_leg_in_view(phantoms, fe_heights, affine, motion)
    solutions = [solve_slice(p, truth.at(h), tension.at(h), n_truth_elements) for p, h in zip(phantoms, fe_heights)]
    fields = np.stack([field_mm for field_mm, _ in solutions])

    first = int(np.argmin(np.abs(fe_heights - heights[0])))   # volume slice k is solved height first + k
    seeds = {"unloaded": [10000 * noise_seed + k for k in range(len(heights))],
             "loaded": [10000 * noise_seed + 5000 + k for k in range(len(heights))]}
    unloaded = np.stack([render_unloaded(phantoms[first + k], seed) for k, seed in enumerate(seeds["unloaded"])], axis=2)
    session = LoadedSession(phantoms, fe_heights, fields, affine, motion, leg=leg)
    loaded = np.stack([session.render(k, seed) for k, seed in enumerate(seeds["loaded"])], axis=2)

    slices = []
    for index, (height, phantom, (field_mm, mesh)) in enumerate(zip(fe_heights, phantoms, solutions)):
        k = index - first                                     # its volume slice, if it is one
        entry = {"height_mm": float(height), "in_volume": 0 <= k < len(heights),
                 "studied": any(np.isclose(height, h) for h in studied),
                 "parameters_kPa": dict(zip(LEG_PARAMETERS, truth.at(height))),
                 "tension_N_per_mm": tension.at(height), "shape": dataclasses.asdict(phantom.geometry.shape),
                 "landmarks": phantom.geometry.landmarks(),
                 "engine_mesh": {"elements": len(mesh.elements), "type": mesh.element_type},
                 "max_displacement_mm": float(np.abs(field_mm).max())}
        if entry["in_volume"]:
            entry["noise_seeds"] = {role: seeds[role][k] for role in ("unloaded", "loaded")}
        if entry["studied"]:
            entry["displacement_file"] = f"displacement_{height_tag(height)}mm.npy"
            entry["labels_file"] = f"labels_{height_tag(height)}mm.png"
        slices.append(entry)
    record = {"case_folder": str(folder), "heights_mm": heights.tolist(), "studied_heights_mm": studied,
              "solved_heights_mm": fe_heights.tolist(), "parameters": list(LEG_PARAMETERS),
              "truth_profile_kPa": truth.as_dict(), "tension_profile_N_per_mm": tension.as_dict(),
              "motion": motion.as_dict(), "noise_seed": noise_seed, "image_shape": list(leg.image_shape),
              "pixel_size_mm": list(leg.pixel_size_mm), "slice_spacing_mm": spacing, "affine": affine.tolist(),
              "profile": dataclasses.asdict(leg.profile), "contrast": dataclasses.asdict(leg.contrast),
              "supersampling": leg.supersampling, "slices": slices}
    case_toml = _case_toml(name, leg.pixel_size_mm, tension, tension_rel_uncertainty, studied,
                           compression_heights(leg.profile, studied),
                           [(float(h), phantoms[first + k].geometry.landmarks()) for k, h in enumerate(heights)])

    with staged_folders(truth_folder, folder) as (truth_staging, case_staging):
        (truth_staging / "truth.json").write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        for entry, phantom, field_mm in zip(slices, phantoms, fields):
            if entry["studied"]:
                np.save(truth_staging / entry["displacement_file"], field_mm)
                write_png16(truth_staging / entry["labels_file"], phantom.labels().astype(np.uint8))
        write_nifti_volume(case_staging / "unloaded.nii.gz", unloaded, affine)
        write_nifti_volume(case_staging / "loaded.nii.gz", loaded, affine)
        (case_staging / "case.toml").write_text(case_toml, encoding="utf-8")
    return folder, truth_folder


def _check_leg_in_view(phantoms: Sequence[CalfPhantom], heights: np.ndarray, affine: np.ndarray,
                       motion: RigidMotion3D) -> None:
    """ValueError if the skin of a slice comes within LEG_MARGIN_MM of the field of view's edge, unloaded or moved
    by the motion (the garment only shrinks the leg, so the unloaded skin bounds the loaded one)."""
    dy, dx = phantoms[0].pixel_size_mm
    rows, cols = phantoms[0].image_shape
    low, high = np.array([LEG_MARGIN_MM, LEG_MARGIN_MM]), np.array([cols * dx, rows * dy]) - LEG_MARGIN_MM
    to_patient = np.array([-0.5 * dx, -0.5 * dy])   # slice frame -> patient x, y (module text)
    for phantom, height in zip(phantoms, heights):
        skin = phantom.geometry.skin.polygon(360)
        patient = np.vstack([(skin + to_patient).T, np.full(len(skin), height)])
        moved = motion.apply(patient)[:2].T - to_patient
        for points, session in ((skin, "unloaded"), (moved, "loaded")):
            if np.any(points < low) or np.any(points > high):
                raise ValueError(f"the leg at {height:g} mm comes within {LEG_MARGIN_MM} mm of the field of view's "
                                 f"edge in the {session} session; enlarge field_of_view_mm or recentre the profile")


def _case_toml(name: str, pixel_size_mm, tension: HeightProfile, rel: float, studied: Sequence[float],
               named_heights: dict[str, float], landmarks: list[tuple[float, dict]]) -> str:
    def numbers(values) -> str:
        return "[" + ", ".join(repr(round(float(v), 4)) for v in values) + "]"

    lines = ["[case]", f"name = {json.dumps(name)}", f"pixel_size_mm = {numbers(pixel_size_mm)}  # row, column", "",
             "[garment]",
             f"tension_N_per_mm = {{ heights_mm = {numbers(tension.heights_mm)}, values = {numbers(tension.values)} }}",
             f"tension_rel_uncertainty = {float(rel)!r}", "",
             "[study]", f"heights_mm = {numbers(studied)}  # slice positions of the unloaded volume",
             "compression_heights_mm = { " + ", ".join(f"{key} = {float(named_heights[key])!r}"
                                                       for key in COMPRESSION_POINTS) + " }", "",
             "[landmarks]  # polylines along the leg: [x, y, z] mm, x y in the slice frame, z the height"]
    for landmark in LANDMARK_NAMES:
        points = ", ".join(numbers((*marks[landmark], height)) for height, marks in landmarks)
        lines.append(f"{landmark} = [{points}]")
    return "\n".join(lines) + "\n"
