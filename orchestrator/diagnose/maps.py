"""The residual where it is: per tissue, per sector around the leg and in the named region (tissue, sector, depth
band) that holds the largest share of its squares (`regions.LegFrame`); with several garment levels, each level's
own misfit over its own floor and its own maps."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model.regions import SECTORS, LegFrame, depth_band

MIN_REGION_POINTS = 3        # a named region holds at least this many measurements



@dataclass
class ResidualMaps:
    """The residual where it is: vectors at the points, RMS per tissue and per angular sector."""

    positions_mm: list[list[float]]
    residual_mm: list[list[float]]          # u_model - u_measured at each point
    per_region_rms_mm: dict[str, float]     # per tissue
    sector_centre_deg: list[float]          # display angles, counter-clockwise from the image's +x axis
    sector_rms_mm: list[float]
    sector_radial_mm: list[float]           # mean radial component (+ outwards: the model is too far out)
    sector_count: list[int]
    centre_mm: list[float]
    worst_sector_deg: float
    sector_names: list[str] = field(default_factory=list)   # "posterior sector 240-270 deg"
    worst_region: str = ""                  # "fat, posterior sector 240-270 deg, 0-5 mm under the skin"
    worst_region_rms_mm: float = 0.0
    worst_region_share: float = 0.0         # its share of the sum of squared residuals



def level_points(objective) -> list[slice]:
    """The rows of each garment level's points in the objective's stacked positions (one slice for one level)."""
    slices = getattr(objective, "slices", None)
    if not slices:
        return [slice(0, len(objective.positions_mm))]
    return [slice(rows.start // 2, rows.stop // 2) for rows in slices]



def level_misfits(objective, r: np.ndarray, n_parameters: int) -> list[dict]:
    """Each garment level's own misfit and noise floor at the joint residual r (`levels.JointDisplacementObjective.
    level_misfits`): which level the model fails at. Empty for one level."""
    parts = getattr(objective, "parts", None)
    if not parts:
        return []
    # each level's floor counts its share of the fitted parameters, p n_k / n (as identification.json's levels)
    floors = [part.noise_floor(n_parameters * part.n_residuals / objective.n_residuals) for part in parts]
    return [{"level": k, "misfit": float(misfit), "noise_floor": floor, "misfit_over_floor": float(misfit) / floor}
            for k, (floor, misfit) in enumerate(zip(floors, objective.level_misfits(r)), 1)]



def level_maps(objective, residual_mm: np.ndarray, frame: LegFrame) -> list[ResidualMaps]:
    """The residual maps of each garment level's points (`residual_maps`); empty for one level."""
    if not getattr(objective, "parts", None):
        return []
    residual_mm = np.asarray(residual_mm, float).reshape(-1, 2)
    return [residual_maps(objective.positions_mm[rows], residual_mm[rows], frame) for rows in level_points(objective)]



def residual_maps(positions_mm: np.ndarray, residual_mm: np.ndarray, frame: LegFrame) -> ResidualMaps:
    """The residual per tissue and per sector, and the named region (tissue, sector, depth band) that holds
    the largest share of its squares."""
    positions_mm = np.asarray(positions_mm, float)
    residual_mm = np.asarray(residual_mm, float).reshape(-1, 2)
    squared = np.sum(residual_mm ** 2, axis=1)
    tissues = np.array(frame.tissues(positions_mm))
    per_region = {str(name): float(np.sqrt(np.mean(squared[tissues == name]))) for name in np.unique(tissues)}
    offset = positions_mm - frame.centre_mm
    radial = np.sum(residual_mm * offset, axis=1) / np.maximum(np.linalg.norm(offset, axis=1), 1e-12)
    sector = frame.sectors(positions_mm)
    centres = ((np.arange(SECTORS) + 0.5) * 360.0 / SECTORS).tolist()
    rms, mean_radial, count = [], [], []
    for k in range(SECTORS):
        inside = sector == k
        count.append(int(inside.sum()))
        rms.append(float(np.sqrt(np.mean(squared[inside]))) if inside.any() else 0.0)
        mean_radial.append(float(np.mean(radial[inside])) if inside.any() else 0.0)
    bands = np.array([depth_band(d) for d in frame.depth_mm(positions_mm)])
    worst, worst_sum, worst_rms = "", -1.0, 0.0
    for key in {(t, k, b) for t, k, b in zip(tissues, sector, bands)}:
        inside = (tissues == key[0]) & (sector == key[1]) & (bands == key[2])
        if inside.sum() >= MIN_REGION_POINTS and squared[inside].sum() > worst_sum:
            worst_sum, worst_rms = float(squared[inside].sum()), float(np.sqrt(np.mean(squared[inside])))
            worst = f"{key[0]}, {frame.sector_label(int(key[1]))}, {key[2]}"
    return ResidualMaps(positions_mm.tolist(), residual_mm.tolist(), per_region, centres, rms, mean_radial, count,
                        frame.centre_mm.tolist(), float(centres[int(np.argmax(rms))]),
                        [frame.sector_label(k) for k in range(SECTORS)], worst, worst_rms,
                        worst_sum / max(float(squared.sum()), 1e-300))
