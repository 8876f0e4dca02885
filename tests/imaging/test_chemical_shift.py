"""The fat's chemical shift read across the fat/muscle interface (`imaging.chemical_shift`), and the mesh that moves
the interface back by it (`meshing.labels.with_fat_moved_back`).

The scene is an MR image made as a scanner makes it: a leg-like ellipse of water (muscle 0.4, with a dark fascia
0.3 mm wide at its edge, and a bone: fatty marrow in a dark cortex) inside a ring of fat (1.0) and a skin of water (0.5), the fat's signal shifted along the
readout by a known number of pixels on a fine grid, the sum band-limited to the acquired k-space matrix, complex
noise of 2.5 % of the fat, the magnitude taken. The estimate must find the shift within 0.25 pixel (0.1 mm) and its sign,
find none where there is none, and the meshed interface must come back to within 0.3 mm of
where it lies on the same scene without a chemical shift (it is 0.5-0.7 mm off it before)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from orchestrator.imaging.chemical_shift import fat_shift
from orchestrator.imaging.segment import segment_t1
from orchestrator.meshing import fat_muscle_normals, tissue_curves, with_fat_moved_back
from orchestrator.meshing.labels import is_fat_muscle

SHAPE = (256, 256)
PIXEL_MM = 0.4
OVERSAMPLING = 4
CENTRE = np.array([51.2, 51.2])
MUSCLE_AXES = (34.0, 28.0)      # the water's (muscle's) edge, mm
FAT_AXES = (42.0, 37.0)         # the fat's outer edge: the skin's inner one
SKIN_MM = 1.5
FASCIA_MM = 0.3
BONE_CENTRE = (45.0, 42.0)      # a tibia: fatty marrow within a dark cortex, mm
BONE_RADII = (6.0, 8.5)         # the marrow's and the cortex's outer radius


def _inside(x, y, axes, grow=0.0):
    return ((x - CENTRE[0]) / (axes[0] + grow)) ** 2 + ((y - CENTRE[1]) / (axes[1] + grow)) ** 2 <= 1.0


def scanner_image(shift_px: tuple[float, float], seed: int = 0, to_material=None, noise: float = 0.025) -> np.ndarray:
    """The scene of the module text, the fat's signal moved by shift_px (x, y) pixels; to_material(x, y) -> (X, Y):
    the material point each scanner point shows (a loaded session), identity by default."""
    n = OVERSAMPLING
    rows, cols = np.indices((SHAPE[0] * n, SHAPE[1] * n), dtype=float)
    x, y = (cols + 0.5) * PIXEL_MM / n, (rows + 0.5) * PIXEL_MM / n
    dx, dy = (s * PIXEL_MM for s in shift_px)
    fat_x, fat_y = x - dx, y - dy        # the fat's signal shown at x is the fat's at x - shift
    if to_material is not None:
        x, y = to_material(x, y)
        fat_x, fat_y = to_material(fat_x, fat_y)
    bone = np.hypot(x - BONE_CENTRE[0], y - BONE_CENTRE[1])
    water = np.where(_inside(x, y, MUSCLE_AXES) & (bone > BONE_RADII[1]), 0.4, 0.0)
    water += np.where(_inside(x, y, FAT_AXES, SKIN_MM) & ~_inside(x, y, FAT_AXES), 0.5, 0.0)
    # a texture of the fat (thin dark septa) and of the muscle (weak), fixed to the material
    water *= 1.0 + 0.08 * np.sin(1.3 * x + 0.7 * y) * np.sin(0.9 * x - 1.1 * y)
    fat = np.where(_inside(fat_x, fat_y, FAT_AXES) & ~_inside(fat_x, fat_y, MUSCLE_AXES, FASCIA_MM), 1.0, 0.0)
    fat += np.where(np.hypot(fat_x - BONE_CENTRE[0], fat_y - BONE_CENTRE[1]) < BONE_RADII[0], 0.8, 0.0)   # marrow
    fat *= 1.0 - 0.7 * (np.abs(np.sin(0.8 * fat_x + 0.3 * np.cos(0.5 * fat_y)) * np.sin(0.6 * fat_y)) > 0.97)
    spectrum = np.fft.fftshift(np.fft.fft2(water + fat))
    h, w = SHAPE
    top, left = (spectrum.shape[0] - h) // 2, (spectrum.shape[1] - w) // 2
    acquired = np.fft.ifftshift(spectrum[top:top + h, left:left + w])
    # the fine grid's samples sit (n - 1) / 2 fine pixels before the acquired pixels' centres: a phase ramp undoes it
    ky, kx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]
    centring = np.exp(-2j * np.pi * (ky + kx) * (n - 1) / (2 * n))
    image = np.fft.ifft2(acquired * centring) / n ** 2
    rng = np.random.default_rng(seed)
    return np.abs(image + noise * (rng.standard_normal(SHAPE) + 1j * rng.standard_normal(SHAPE)))


@pytest.mark.parametrize("shift_px", [(1.4, 0.0), (-1.8, 0.0), (0.0, 1.2), (0.0, -1.5)])
def test_the_fat_shift_is_found_along_the_readout_and_the_interface_moved_back(shift_px):
    image = scanner_image(shift_px)
    pixel = (PIXEL_MM, PIXEL_MM)
    curves = tissue_curves(segment_t1(image, pixel), pixel, image=image)
    found = fat_shift(image, *fat_muscle_normals(curves), pixel)
    assert found is not None and found.significant
    assert np.allclose(found.in_pixels(pixel), shift_px, atol=0.25), found
    assert np.all(np.asarray(found.standard_error_mm) < 0.1 * PIXEL_MM), found

    # where the interface is placed on the same scene without a chemical shift
    unshifted = scanner_image((0.0, 0.0))
    reference = np.vstack([k.points for k in tissue_curves(segment_t1(unshifted, pixel), pixel, image=unshifted).curves
                           if is_fat_muscle(k.sides)])

    def off_the_reference(tissue):
        points = np.vstack([k.points for k in tissue.curves if is_fat_muscle(k.sides)])
        return cKDTree(reference).query(points)[0]

    before, after = off_the_reference(curves), off_the_reference(with_fat_moved_back(curves, found.shift_mm))
    # the fat's edge on the image lies the shift's projection off where it lies without one (up to the whole shift)
    assert np.percentile(before, 95) > 0.6 * np.hypot(*shift_px) * PIXEL_MM
    # what is left: the estimate's error (up to 0.2 px here) and the placement's own change with the bands
    assert np.percentile(after, 95) < 0.3
    assert np.percentile(after, 95) < 0.5 * np.percentile(before, 95)


def test_no_fat_shift_is_found_where_there_is_none():
    image = scanner_image((0.0, 0.0), seed=1)
    pixel = (PIXEL_MM, PIXEL_MM)
    curves = tissue_curves(segment_t1(image, pixel), pixel, image=image)
    found = fat_shift(image, *fat_muscle_normals(curves), pixel)
    assert found is not None and not found.significant, found
    assert np.all(np.abs(found.in_pixels(pixel)) < 0.15), found
    assert "none found" in found.sentence(pixel)


def test_windows_see_the_fat_where_its_signal_lies_and_its_offset_between_the_sessions():
    """The leg turned by 2 degrees about the bone and compressed by 1 % about it between the sessions, the fat shown
    1.5 px along x in both: against what the windows see of the true field, the windows that see the fat (in this
    scene almost all: its muscle is nearly flat) are off by about (R^T - I) delta (0.021 mm along y) unless they see
    the chemical shift (`imaging.windows`); seen so, that error goes."""
    from orchestrator.core.frame import RigidMotion
    from orchestrator.measure.measurements import measure_dic

    pixel = (PIXEL_MM, PIXEL_MM)
    shift = (1.5, 0.0)
    motion = RigidMotion(2.0, (0.3, -0.2), BONE_CENTRE)
    strain = -0.01

    def to_material(x, y):   # y = M(X + u(X)), u = strain (X - bone centre): X = c + (M^-1(y) - c) / (1 + strain)
        back_x, back_y = motion.inverse().apply(x, y)
        return (BONE_CENTRE[0] + (back_x - BONE_CENTRE[0]) / (1.0 + strain),
                BONE_CENTRE[1] + (back_y - BONE_CENTRE[1]) / (1.0 + strain))

    unloaded = scanner_image(shift, seed=2, noise=0.005)
    loaded = scanner_image(shift, seed=3, to_material=to_material, noise=0.005)
    labels = segment_t1(unloaded, pixel)
    rows, cols = np.indices(SHAPE, dtype=float)
    x, y = (cols + 0.5) * PIXEL_MM, (rows + 0.5) * PIXEL_MM
    field = np.stack([strain * (x - BONE_CENTRE[0]), strain * (y - BONE_CENTRE[1])])
    fat_shift = tuple(v * PIXEL_MM for v in shift)
    along_y = {}
    for name, given in (("without", None), ("with", fat_shift)):
        measured, _, _ = measure_dic(unloaded, loaded, labels, pixel, motion, fat_shift_mm=given)
        errors = (measured.displacement_mm.ravel() - measured.sees(field).ravel()).reshape(-1, 2)
        # the windows' typical error along y, where (R^T - I) delta lies (a median: a window or two that matched
        # badly do not count)
        along_y[name] = float(np.median(np.abs(errors[:, 1])))
    turn = np.deg2rad(motion.angle_deg)
    expected = np.sin(turn) * fat_shift[0]      # |(R^T - I) delta| along y, 0.021 mm
    assert along_y["without"] > 0.6 * expected, along_y
    assert along_y["with"] < 0.4 * along_y["without"], along_y


def _header(size_px: float, readout: str | None):
    """What a DICOM header of this scene would say: 1.5 T, the bandwidth that makes size_px of shift."""
    from orchestrator.case.acquisition import FAT_WATER_PPM, LARMOR_MHZ_PER_T, Acquisition

    frequency = 1.5 * LARMOR_MHZ_PER_T
    phase = {"x": "COL", "y": "ROW"}.get(readout)
    return Acquisition(frequency, FAT_WATER_PPM * frequency / size_px, phase, (PIXEL_MM, PIXEL_MM))


@pytest.mark.parametrize("shift_px, readout", [((-1.8, 0.0), "x"), ((0.0, 1.2), None)])
def test_the_headers_size_is_taken_and_the_image_gives_its_sign_and_axis(shift_px, readout):
    image = scanner_image(shift_px)
    pixel = (PIXEL_MM, PIXEL_MM)
    curves = tissue_curves(segment_t1(image, pixel), pixel, image=image)
    alone = fat_shift(image, *fat_muscle_normals(curves), pixel)
    found = fat_shift(image, *fat_muscle_normals(curves), pixel, _header(float(np.hypot(*shift_px)), readout))
    assert found.source == "header" and found.significant
    # the header's size exactly, along the readout (the image's larger component where the header does not say)
    assert np.allclose(found.in_pixels(pixel), shift_px, atol=1e-9), found
    assert found.image_shift_mm == alone.shift_mm
    sentence = found.sentence(pixel)
    assert "from the DICOM header (a pixel bandwidth of" in sentence and "its sign from" in sentence


def test_a_header_shift_whose_sign_the_image_does_not_show_is_not_taken():
    """The header says 1.4 px, the image shows none (a sign cannot be read from nothing): the profiles' own reading
    stands, and the sentence says that the header's size was left for want of a sign."""
    image = scanner_image((0.0, 0.0), seed=1)
    pixel = (PIXEL_MM, PIXEL_MM)
    curves = tissue_curves(segment_t1(image, pixel), pixel, image=image)
    found = fat_shift(image, *fat_muscle_normals(curves), pixel, _header(1.4, "x"))
    assert found.source == "image" and not found.significant, found
    assert "is not taken: the profiles do not tell its sign" in found.sentence(pixel)
