"""Write a phantom case folder, with its ground truth kept apart.

The case folder is what a user would bring (docs/design.md, "The case folder"):
case.toml with the five landmarks of the first paper, unloaded.png and
loaded.png (16-bit), labels.png (by default the segmentation of the unloaded
image, as a user would make it, not the phantom's exact labels) and
optionally points.csv (the true displacement at grid points in the tissue,
plus Gaussian measurement noise of sigma_mm).

The truth goes to a separate folder (default: a sibling `<case>.truth`):
truth.json (the phantom's `description()`, rigid motion, noise seeds, description of the
displacement), displacement_mm.npy ((2, H, W) on the pixels of the unloaded
image, mm), and the exact label maps of both images. Both folders are staged
in temporary siblings and renamed into place only when complete.

More garment levels (`levels`: (tension, displacement) pairs) are rendered as the loaded image is, with the
same scanner motion and a noise seed of their own, and written as loaded-level-<k>.png (k = 2, 3, ...) with
their [[garment.levels]] tables; their true fields and loaded labels go to the truth folder as
displacement_level_<k>_mm.npy and labels_loaded_level_<k>.png.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..case._formats import write_png16
from ..case.folder import DisplacementPoints, GarmentLevel, write_case_folder
from ..core.files import staged_folders
from ..core.frame import RigidMotion, displacement_on_grid, pixel_centres_mm
from ..imaging.segment import segment_t1
from .render import (
    CalfPhantom,
    Phantom,
    as_displacement_fn,
    bone_clamped_compression,
    loaded_labels,
    make_loaded_image,
    render_unloaded,
)


def write_case(folder, phantom: Phantom | None = None, displacement=None, *, rigid: RigidMotion | None = None,
               truth_folder=None, name: str = "phantom-calf", tension_N_per_mm: float = 0.16,
               tension_rel_uncertainty: float = 0.10, labels: str | None = "segmented", points_spacing_mm: float | None = None,
               points_sigma_mm: float = 0.05, noise_seeds: tuple[int, int] = (0, 1), description: str = "",
               levels=(), overwrite: bool = False) -> tuple[Path, Path]:
    """Render the phantom unloaded and loaded (displacement in mm, callable or (2, H, W); default a bone-clamped
    radial compression) and write the case folder and the truth folder. Returns (case folder, truth folder).
    phantom: a `CalfPhantom` (default) or any `render.Phantom`, e.g. `mri.MRIPhantom`.

    labels: "segmented" (segment_t1 of the unloaded image), "truth" (exact phantom labels), "compartments" (exact
    labels with the muscle compartments as labels 4, 5, ..., a user's hand segmentation) or None (no labels.png).
    points_spacing_mm: if given, write points.csv on a grid of that spacing inside the leg.
    levels: (tension N/mm, displacement) of more garment levels (module text); level k's image noise has the seed
    `level_noise_seed(noise_seeds, k)`.
    """
    folder = Path(folder)
    truth_folder = Path(truth_folder) if truth_folder is not None else folder.with_name(folder.name + ".truth")
    for target in (folder, truth_folder):
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} already exists; choose another folder or pass overwrite=True")
    if labels not in ("segmented", "truth", "compartments", None):
        raise ValueError("labels must be 'segmented', 'truth', 'compartments' or None")
    phantom = phantom or CalfPhantom()
    if displacement is None:
        displacement = bone_clamped_compression(phantom.geometry)
        description = description or "bone_clamped_compression(strain=0.025, ramp_mm=8)"
    displacement_fn = as_displacement_fn(displacement, phantom.pixel_size_mm)

    unloaded = render_unloaded(phantom, noise_seed=noise_seeds[0])
    loaded = make_loaded_image(phantom, displacement_fn, rigid, noise_seed=noise_seeds[1])
    true_labels = phantom.labels()
    case_labels = {"segmented": lambda: segment_t1(unloaded, phantom.pixel_size_mm), "truth": lambda: true_labels,
                   "compartments": lambda: phantom.labels(compartments=True), None: lambda: None}[labels]()
    field = displacement_on_grid(displacement_fn, phantom.image_shape, phantom.pixel_size_mm)
    points = (_grid_points(phantom, true_labels, displacement_fn, points_spacing_mm, points_sigma_mm, noise_seeds[1])
              if points_spacing_mm else None)
    extra = []   # (number, tension, displacement function, seed, GarmentLevel to write)
    for number, (tension, level_displacement) in enumerate(levels, start=2):
        level_fn = as_displacement_fn(level_displacement, phantom.pixel_size_mm)
        seed = level_noise_seed(noise_seeds, number)
        level_points = (_grid_points(phantom, true_labels, level_fn, points_spacing_mm, points_sigma_mm, seed)
                        if points_spacing_mm else None)
        extra.append((number, float(tension), level_fn, seed, GarmentLevel(
            number, make_loaded_image(phantom, level_fn, rigid, noise_seed=seed), float(tension),
            Path(f"loaded-level-{number}.png"), level_points,
            Path(f"points-level-{number}.csv") if level_points is not None else None)))

    with staged_folders(truth_folder) as (staging,):
        truth = {"case_folder": str(folder), "description": description, **phantom.description(),
                 "image_shape": list(phantom.image_shape), "pixel_size_mm": list(phantom.pixel_size_mm),
                 "noise_seeds": list(noise_seeds),
                 "rigid_motion": dataclasses.asdict(rigid) if rigid is not None else None,
                 "landmarks": phantom.geometry.landmarks(), "displacement_file": "displacement_mm.npy",
                 "labels_in_case": labels}
        if extra:
            truth["levels"] = [{"level": number, "tension_N_per_mm": tension, "image": level.path.name,
                                "noise_seed": seed, "displacement_file": f"displacement_level_{number}_mm.npy"}
                               for number, tension, _, seed, level in extra]
        (staging / "truth.json").write_text(json.dumps(truth, indent=2) + "\n", encoding="utf-8")
        np.save(staging / "displacement_mm.npy", field)
        write_png16(staging / "labels_unloaded.png", true_labels.astype(np.uint8))
        write_png16(staging / "labels_loaded.png", loaded_labels(phantom, displacement_fn, rigid).astype(np.uint8))
        for number, _, level_fn, _, _ in extra:
            np.save(staging / f"displacement_level_{number}_mm.npy",
                    displacement_on_grid(level_fn, phantom.image_shape, phantom.pixel_size_mm))
            write_png16(staging / f"labels_loaded_level_{number}.png",
                        loaded_labels(phantom, level_fn, rigid).astype(np.uint8))
        write_case_folder(folder, name=name, unloaded=unloaded, loaded=loaded, pixel_size_mm=phantom.pixel_size_mm,
                          tension_N_per_mm=tension_N_per_mm, tension_rel_uncertainty=tension_rel_uncertainty,
                          labels=case_labels, points=points, landmarks=phantom.geometry.landmarks(),
                          levels=tuple(level for *_, level in extra), overwrite=overwrite)
    return folder, truth_folder


def level_noise_seed(noise_seeds: tuple[int, int], number: int) -> int:
    """The image noise seed of garment level `number` (2, 3, ...): its own, apart from the first level's."""
    return int(noise_seeds[1]) + 100 * (number - 1)


def _grid_points(phantom, labels, displacement_fn, spacing_mm, sigma_mm, seed) -> DisplacementPoints:
    """True displacements at grid points in fat and muscle, plus Gaussian noise of sigma_mm."""
    x, y = pixel_centres_mm(phantom.image_shape, phantom.pixel_size_mm)
    step = max(1, int(round(spacing_mm / phantom.pixel_size_mm[0])))
    grid = np.zeros(labels.shape, bool)
    grid[::step, ::step] = True
    keep = grid & ((labels == 1) | (labels == 2))
    px, py = x[keep], y[keep]
    ux, uy = displacement_fn(px, py)
    noise = np.random.default_rng(seed + 1000).normal(0.0, sigma_mm, (px.size, 2))
    return DisplacementPoints(np.stack([px, py], axis=1), np.stack([ux, uy], axis=1) + noise, np.full(px.size, sigma_mm))
