"""The 3D phantom leg of volume studies: its profile along the leg, the texture's coherence, the loaded session's
frames, and a small volume case written with the engine (4 slices at 0.72 mm: case.toml, the NIfTI volumes, the
bones moved by the motion, the leg shrunk by the true field, the truth folder)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tomllib
from scipy import ndimage
from skimage import io

from orchestrator.case.volume import RigidMotion3D, Volume, volume_affine
from orchestrator.core.frame import pixel_centres_mm
from orchestrator.imaging.segment import segment_t1
from orchestrator.model.forward import TABLE2_CENTRAL_KPA
from orchestrator.phantom import LANDMARK_NAMES, as_displacement_fn
from orchestrator.phantom.appearance import bias_field
from orchestrator.phantom.volume import (
    DEFAULT_HEIGHTS_MM,
    DEFAULT_MOTION,
    DEFAULT_TENSION,
    DEFAULT_TRUTH,
    HeightProfile,
    LegProfile,
    LoadedSession,
    PhantomLeg,
    write_volume_case,
)

SMALL_HEIGHTS_MM = (236.0, 244.0, 252.0, 260.0)
COARSE_PIXELS_MM = (0.72, 0.72)


@pytest.fixture(scope="module")
def small_case(tmp_path_factory):
    """(case folder, truth folder) of a 4-slice volume at 0.72 mm pixels, the default truth, tension and motion."""
    folder = tmp_path_factory.mktemp("volume") / "leg"
    return write_volume_case(folder, heights_mm=SMALL_HEIGHTS_MM, pixel_size_mm=COARSE_PIXELS_MM)


@pytest.fixture(scope="module")
def small_volumes(small_case):
    import nibabel

    images = {role: nibabel.load(small_case[0] / f"{role}.nii.gz") for role in ("unloaded", "loaded")}
    return {role: Volume(np.asarray(image.get_fdata()), image.affine) for role, image in images.items()}


@pytest.fixture(scope="module")
def small_truth(small_case):
    return json.loads((small_case[1] / "truth.json").read_text(encoding="utf-8"))


def _polygon_area(points: np.ndarray) -> float:
    x, y = points.T
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _bone_centroids(image: np.ndarray, pixel_size_mm) -> list[np.ndarray]:
    """(row, column) centroids of the two largest bones of a segmented slice: tibia, then fibula."""
    bones, count = ndimage.label(segment_t1(image, pixel_size_mm) == 3)
    assert count >= 2
    areas = ndimage.sum_labels(np.ones_like(bones), bones, range(1, count + 1))
    largest = np.argsort(areas)[::-1][:2] + 1
    return [np.asarray(ndimage.center_of_mass(bones == label)) for label in largest]


def _patient(volume: Volume, row_column: np.ndarray, slice_index: float) -> np.ndarray:
    return volume.affine[:3, :3] @ np.array([*row_column, slice_index]) + volume.affine[:3, 3]


# -- the leg along its height (no engine) ----------------------------------------------------------------

def test_the_leg_narrows_towards_the_ankle_and_its_bones_are_not_prisms():
    profile = LegProfile()
    widest, low = profile.geometry_at(profile.widest_height_mm), profile.geometry_at(profile.narrowest_height_mm)
    width = {name: np.ptp(g.skin.polygon(720)[:, 0]) for name, g in (("widest", widest), ("low", low))}
    assert 110.0 < width["widest"] < 120.0
    assert width["low"] / width["widest"] == pytest.approx(0.85, abs=0.005)
    back = {z: profile.geometry_at(z).fat_thickness(np.pi / 2) for z in (DEFAULT_HEIGHTS_MM[0], DEFAULT_HEIGHTS_MM[-1])}
    assert back[DEFAULT_HEIGHTS_MM[-1]] > back[DEFAULT_HEIGHTS_MM[0]] + 2.0   # thicker fat at the back higher up
    geometries = [profile.geometry_at(z) for z in DEFAULT_HEIGHTS_MM]      # every slice's parts nest (no ValueError)
    for bone in ("tibia", "fibula"):
        centres = np.array([getattr(g, bone).centre for g in geometries])
        radii = [getattr(g, bone).radius(0.0) for g in geometries]
        assert np.ptp(centres, axis=0).max() > 1.5 and np.ptp(radii) > 0.3
        # smooth: no jump of the bone's centre between neighbouring slices
        assert np.max(np.linalg.norm(np.diff(centres, axis=0), axis=1)) < 1.5


def test_the_texture_runs_along_the_leg():
    leg = PhantomLeg(pixel_size_mm=COARSE_PIXELS_MM)
    x, y = np.meshgrid(np.linspace(20.0, 110.0, 300), np.linspace(20.0, 110.0, 300))
    base = leg.profile.widest_height_mm

    def texture(height):
        return leg.slice_phantom(height).texture(x, y).ravel()

    here = texture(base)
    assert np.std(here) == pytest.approx(1.0, abs=0.1) and np.std(texture(base - 50.0)) == pytest.approx(1.0, abs=0.1)
    assert np.corrcoef(here, texture(base - 8.0))[0, 1] > 0.98          # neighbouring slices: the same structure
    assert np.corrcoef(here, texture(base - 4.0))[0, 1] > np.corrcoef(here, texture(base - 8.0))[0, 1]
    assert abs(np.corrcoef(here, texture(base - leg.profile.texture_turn_mm))[0, 1]) < 0.1   # a quarter turn away


def test_height_profiles_interpolate_linearly_and_hold_beyond_their_knots():
    assert DEFAULT_TENSION.at(196.0) == pytest.approx(0.20) and DEFAULT_TENSION.at(248.0) == pytest.approx(0.17)
    assert DEFAULT_TENSION.at(150.0) == pytest.approx(0.20) and DEFAULT_TENSION.at(400.0) == pytest.approx(0.14)
    assert DEFAULT_TRUTH.at(248.0) == pytest.approx((5.5, 13.2, 88.0, 80.5))
    with pytest.raises(ValueError):
        HeightProfile((300.0, 196.0), (0.1, 0.2))


def test_the_default_truth_is_not_the_default_start_and_varies_with_height():
    truths = np.array([DEFAULT_TRUTH.at(z) for z in DEFAULT_HEIGHTS_MM])
    assert np.all(np.abs(truths / np.asarray(TABLE2_CENTRAL_KPA) - 1.0) > 0.09)
    assert np.all(np.abs(truths[-1] / truths[0] - 1.0) > 0.05)
    tensions = [DEFAULT_TENSION.at(z) for z in DEFAULT_HEIGHTS_MM]
    assert np.all(np.diff(tensions) < 0)           # graduated: highest at the ankle end


# -- the loaded session's frames (no engine) --------------------------------------------------------------

def _session_without_load(leg: PhantomLeg, heights, motion: RigidMotion3D) -> LoadedSession:
    phantoms = [leg.slice_phantom(z) for z in heights]
    fields = np.zeros((len(heights), 2, *leg.image_shape))
    affine = volume_affine(leg.pixel_size_mm, heights[1] - heights[0], (0.0, 0.0, heights[0]))
    return LoadedSession(phantoms, np.asarray(heights), fields, affine, motion)


def test_the_loaded_session_maps_voxels_as_the_volume_affine_does():
    leg = PhantomLeg(pixel_size_mm=COARSE_PIXELS_MM)
    session = _session_without_load(leg, SMALL_HEIGHTS_MM, DEFAULT_MOTION)
    volume = Volume(np.zeros((*leg.image_shape, len(SMALL_HEIGHTS_MM))), session.affine)
    patient = DEFAULT_MOTION.inverse().apply(volume.slice_points_mm(2))
    rows, columns, slices = volume.index_of_points(patient)
    x, y = (np.indices(leg.image_shape)[::-1] + 0.5) * np.reshape(leg.pixel_size_mm[::-1], (2, 1, 1))
    X, Y, height_index = session.unloaded_points(x, y, 2)
    np.testing.assert_allclose(X, (columns + 0.5) * leg.pixel_size_mm[1], atol=1e-9)
    np.testing.assert_allclose(Y, (rows + 0.5) * leg.pixel_size_mm[0], atol=1e-9)
    np.testing.assert_allclose(height_index, slices, atol=1e-9)
    assert np.ptp(height_index) > 0.2        # the tilt: one loaded slice spans heights of the unloaded session


def test_a_leg_slid_by_one_slice_and_whole_pixels_is_the_next_unloaded_slice_shifted():
    """No garment, a motion of (2, -3) pixels and one slice down: the loaded slice k is the unloaded slice k + 1
    moved by those pixels (the scanner's bias, fixed in the scanner, divided out), to rounding."""
    leg = PhantomLeg(pixel_size_mm=COARSE_PIXELS_MM)
    dy, dx = leg.pixel_size_mm
    spacing = SMALL_HEIGHTS_MM[1] - SMALL_HEIGHTS_MM[0]
    motion = RigidMotion3D(translation_mm=(2 * dx, -3 * dy, -spacing))
    session = _session_without_load(leg, SMALL_HEIGHTS_MM, motion)
    upper = session.phantoms[2]
    bias = bias_field(*pixel_centres_mm(upper.image_shape, upper.pixel_size_mm), upper.extent_mm,
                      upper.contrast.bias_amplitude)
    loaded = session.render(1, noise_seed=None) / bias
    unloaded = upper.render(lambda x, y: (x, y), None) / bias
    np.testing.assert_allclose(loaded, np.roll(unloaded, (-3, 2), axis=(0, 1)), atol=1e-6)
    assert np.abs(loaded - session.phantoms[1].render(lambda x, y: (x, y), None) / bias).max() > 0.3


# -- a small volume case made with the engine -------------------------------------------------------------

def test_case_toml_holds_the_study(small_case):
    with open(small_case[0] / "case.toml", "rb") as handle:
        case = tomllib.load(handle)
    assert case["case"] == {"name": "phantom-leg", "pixel_size_mm": list(COARSE_PIXELS_MM)}
    assert case["garment"]["tension_N_per_mm"] == {"heights_mm": [196.0, 300.0], "values": [0.2, 0.14]}
    assert case["garment"]["tension_rel_uncertainty"] == 0.1
    assert case["study"]["heights_mm"] == list(SMALL_HEIGHTS_MM[1:-1])
    named = case["study"]["compression_heights_mm"]
    assert set(named) == {"B", "B1", "C", "D"} and set(named.values()) <= set(SMALL_HEIGHTS_MM[1:-1])
    assert named["B"] <= named["B1"] <= named["C"] <= named["D"]
    assert set(case["landmarks"]) == set(LANDMARK_NAMES)
    profile = LegProfile()
    for name, polyline in case["landmarks"].items():
        assert [point[2] for point in polyline] == list(SMALL_HEIGHTS_MM)
        for x, y, z in polyline:
            assert (x, y) == pytest.approx(profile.geometry_at(z).landmarks()[name], abs=1e-3)


def test_the_volumes_slice_positions_are_the_heights(small_volumes, small_truth):
    for volume in small_volumes.values():
        assert volume.shape == (190, 190, len(SMALL_HEIGHTS_MM))
        np.testing.assert_allclose(volume.slice_positions_mm, SMALL_HEIGHTS_MM, atol=1e-4)
        np.testing.assert_allclose(volume.pixel_size_mm, COARSE_PIXELS_MM, atol=1e-6)
        np.testing.assert_allclose(volume.normal, (0.0, 0.0, 1.0))
    assert small_truth["heights_mm"] == list(SMALL_HEIGHTS_MM)
    # the default motion slides the leg 6 mm: the loaded slices see above the last height, which was solved too
    assert small_truth["solved_heights_mm"] == [*SMALL_HEIGHTS_MM, 268.0]


def test_the_loaded_bones_are_where_the_motion_puts_them(small_volumes, small_truth):
    """The bones are clamped, so the loaded volume's bones are the unloaded ones moved by the motion: each loaded
    slice's bone centroids against the unloaded bone axes (centroids per slice, linear between them) moved by the
    motion and cut by the loaded slice's plane."""
    unloaded, loaded = small_volumes["unloaded"], small_volumes["loaded"]
    motion = RigidMotion3D.from_dict(small_truth["motion"])
    axes = [[_patient(unloaded, c, k) for c in _bone_centroids(unloaded.slice_image(k), unloaded.pixel_size_mm)]
            for k in range(unloaded.shape[2])]
    compared = 0
    for k, height in enumerate(loaded.slice_positions_mm):
        measured = [_patient(loaded, c, k)[:2] for c in _bone_centroids(loaded.slice_image(k), loaded.pixel_size_mm)]
        for bone in range(2):
            moved = motion.apply(np.array([axis[bone] for axis in axes]).T)
            if not moved[2].min() <= height <= moved[2].max():
                continue            # this slice sees the bone beyond the unloaded volume
            expected = np.array([np.interp(height, moved[2], moved[i]) for i in (0, 1)])
            unmoved = np.array([np.interp(height, unloaded.slice_positions_mm, np.array(axes)[:, bone, i]) for i in (0, 1)])
            assert np.linalg.norm(expected - unmoved) > 1.5    # the motion is large enough to be seen
            assert np.linalg.norm(measured[bone] - expected) < 0.5
            compared += 1
    assert compared >= 4


def test_the_loaded_leg_is_shrunk_by_the_true_skin_displacement(small_case, small_volumes, small_truth):
    """Equivalent radius sqrt(area / pi) of the segmented leg, unloaded (linear between slices) at the height the
    loaded slice sees, less the loaded slice's: the truth's (skin polygon moved by the true field at the two
    studied heights around it, linear between them), to a fraction of a pixel."""
    unloaded, loaded = small_volumes["unloaded"], small_volumes["loaded"]
    pixel_size = unloaded.pixel_size_mm
    motion, profile = RigidMotion3D.from_dict(small_truth["motion"]), LegProfile()
    studied = np.asarray(small_truth["studied_heights_mm"])

    def radius(area):
        return np.sqrt(np.asarray(area) / np.pi)

    def leg_radius(volume, k):
        return radius(np.count_nonzero(segment_t1(volume.slice_image(k), pixel_size)) * pixel_size[0] * pixel_size[1])

    true_unloaded, true_loaded = [], []
    for height in studied:
        skin = profile.geometry_at(height).skin.polygon(720)
        field_mm = np.load(small_case[1] / f"displacement_{height:g}mm.npy")
        ux, uy = as_displacement_fn(field_mm, pixel_size)(skin[:, 0], skin[:, 1])
        true_unloaded.append(_polygon_area(skin))
        true_loaded.append(_polygon_area(skin + np.stack([ux, uy], axis=1)))
    unloaded_radii = [leg_radius(unloaded, k) for k in range(unloaded.shape[2])]
    compared = 0
    for k, height in enumerate(loaded.slice_positions_mm):
        leg = segment_t1(loaded.slice_image(k), pixel_size) > 0
        seen = motion.inverse().apply(_patient(loaded, ndimage.center_of_mass(leg), k))[2]   # the leg's axis here
        if not studied[0] <= seen <= studied[-1]:
            continue
        true_shrink = radius(np.interp(seen, studied, true_unloaded)) - radius(np.interp(seen, studied, true_loaded))
        shrink = np.interp(seen, unloaded.slice_positions_mm, unloaded_radii) - leg_radius(loaded, k)
        assert true_shrink > 0.3
        assert shrink == pytest.approx(true_shrink, abs=0.15)      # the pixel is 0.72 mm
        compared += 1
    assert compared >= 1


def test_the_truth_folder_holds_each_studied_slice(small_case, small_truth, small_volumes):
    truth_folder = small_case[1]
    studied = [entry for entry in small_truth["slices"] if entry["studied"]]
    assert [entry["height_mm"] for entry in studied] == list(SMALL_HEIGHTS_MM[1:-1])
    assert small_truth["motion"] == DEFAULT_MOTION.as_dict()
    for entry in small_truth["slices"]:
        assert list(entry["parameters_kPa"].values()) == pytest.approx(DEFAULT_TRUTH.at(entry["height_mm"]))
        assert entry["tension_N_per_mm"] == pytest.approx(DEFAULT_TENSION.at(entry["height_mm"]))
        assert entry["shape"]["half_width_mm"] == pytest.approx(LegProfile().shape_at(entry["height_mm"]).half_width_mm)
    seeds = [entry["noise_seeds"]["unloaded"] for entry in small_truth["slices"] if entry["in_volume"]]
    assert len(set(seeds)) == len(SMALL_HEIGHTS_MM)
    for entry in studied:
        field_mm = np.load(truth_folder / entry["displacement_file"])
        labels = io.imread(truth_folder / entry["labels_file"])
        assert field_mm.shape == (2, 190, 190) and labels.shape == (190, 190)
        assert set(np.unique(labels)) == {0, 1, 2, 3}
        magnitude = np.hypot(*field_mm)
        assert magnitude[labels == 1].max() > 0.8 and magnitude[labels == 3].max() < 0.05   # skin moves, bones clamped
        assert entry["max_displacement_mm"] == pytest.approx(np.abs(field_mm).max())
        # the true labels are the unloaded slice's anatomy: the segmentation of the unloaded volume agrees
        k = SMALL_HEIGHTS_MM.index(entry["height_mm"])
        segmented = segment_t1(small_volumes["unloaded"].slice_image(k), COARSE_PIXELS_MM)
        assert np.mean(segmented == labels) > 0.97


def test_an_existing_case_is_not_overwritten(small_case):
    with pytest.raises(FileExistsError):
        write_volume_case(small_case[0], heights_mm=SMALL_HEIGHTS_MM, pixel_size_mm=COARSE_PIXELS_MM)


@pytest.mark.slow
def test_the_default_volume_case(tmp_path):
    """The default: 14 slices of 380 x 380 pixels of 0.36 mm every 8 mm from 196 to 300 mm, 12 studied."""
    import nibabel

    case, truth = write_volume_case(tmp_path / "leg")
    with open(case / "case.toml", "rb") as handle:
        assert tomllib.load(handle)["study"]["heights_mm"] == list(DEFAULT_HEIGHTS_MM[1:-1])
    images = {role: nibabel.load(case / f"{role}.nii.gz") for role in ("unloaded", "loaded")}
    volumes = {role: Volume(np.asarray(image.get_fdata()), image.affine) for role, image in images.items()}
    for volume in volumes.values():
        assert volume.shape == (380, 380, 14)
        np.testing.assert_allclose(volume.slice_positions_mm, DEFAULT_HEIGHTS_MM, atol=1e-4)
    assert len(list(truth.glob("displacement_*mm.npy"))) == 12
    unloaded, loaded = volumes["unloaded"], volumes["loaded"]
    motion = DEFAULT_MOTION
    axes = np.array([[_patient(unloaded, c, k) for c in _bone_centroids(unloaded.slice_image(k), unloaded.pixel_size_mm)]
                     for k in range(unloaded.shape[2])])
    for k in (3, 8):
        height = loaded.slice_positions_mm[k]
        measured = [_patient(loaded, c, k)[:2] for c in _bone_centroids(loaded.slice_image(k), loaded.pixel_size_mm)]
        for bone in range(2):
            moved = motion.apply(axes[:, bone].T)
            expected = np.array([np.interp(height, moved[2], moved[i]) for i in (0, 1)])
            assert np.linalg.norm(measured[bone] - expected) < 0.5
