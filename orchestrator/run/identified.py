"""What an identification left in the run folder, read by the stages after it: which data it fitted, how the floor's
error model was calibrated on the case's images, each garment level's image and the skin's columns under its
tension."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.files import read_json
from ..fit.geometry_uncertainty import COLUMN_RUNS, geometry_columns
from .setup import RunSetup
from .timings import declare_runs


def floor_calibration(run_dir: Path) -> dict:
    """How the DIC's error model, on which the floor rests, was calibrated on the case's own images (measure):
    each image's noise, the edges' error of position found in the windows' residuals, how far those residuals agree
    with what the model predicts of them (1 where it holds), and the windows kept or rejected by reason."""
    summary = read_json(Path(run_dir) / "measurements.json", "calfit measure")
    return {"prefilter_px": summary.get("prefilter_px", 0.0), "image_noise_sigma": summary["noise_sigma"],
            "image_noise_sigma_estimated": summary.get("noise_sigma_estimated", summary["noise_sigma"]),
            "edge_position_sigma_px": float(np.sqrt(summary.get("edge_variance_px2", 0.0))),
            "residual_over_predicted": summary.get("noise_scale"), "windows": summary["windows"],
            "kept": summary["kept"], "status": summary["status"], "point_sampling": summary.get("point_sampling"),
            "fat_shift_mm": summary.get("fat_shift_mm"), "texture_coherence": summary.get("texture_coherence"),
            "through_plane_warning": summary.get("through_plane_warning")}


def level_images(setup: RunSetup) -> list[str]:
    """The loaded image of every garment level, the case's own first."""
    return [setup.case.files["loaded"].name] + [level.path.name for level in setup.case.levels]


def identified_data(identification: dict) -> str:
    """The data source an identification used ("points" or "dic"), for the stages after it."""
    source = identification.get("data", {}).get("source", "points")
    return "points" if source in ("points", "points.csv") else source


def level_skin_columns(setup, theta, measured, level: int, options: dict, workers: int = 1):
    """`geometry_columns` of garment level `level`'s measurements, under that level's tension."""
    tension = None if level == 1 else setup.case.tensions[level - 1]
    found = geometry_columns(setup, theta, measured, tension_N_per_mm=tension, workers=workers, **options)
    declare_runs(COLUMN_RUNS)   # solves of their own, not in the run's log
    return found
