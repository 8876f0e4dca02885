"""Locate. When the misfit is above the floor, every place a local stiffness change may take is scored the same way,
as a one-parameter effect: the material groups of `heterogeneity` (15-degree sectors, depth bands), contiguous in
one tissue kind over 1 to 6 sectors (up to 90 degrees) and a run of bands, its column the sum of its groups' dr/dln
E (E every modulus of the group, the `local` probe, one engine run). The best places that share no group are
reported (tissue, sector, depth, area; Bonferroni over the N places tried), and the best is refitted (`patch:...`).
Its BIC counts the choice of the place among N, 2 ln N on top of its parameter's ln n (a prior 1/N on each place).
It explains when it reaches EXPLAINED_FACTOR x the floor with a BIC below the baseline's; when a catalog effect
explained the residual too, the lower BIC wins, and a local change that wins takes "explained" away from the
catalog (`weigh_local`).

A compartment whose septum the images do not show is no patch of groups: its boundary is a line across the sectors
and bands. `locate_cuts` scores every straight cut of the muscle the same way (`heterogeneity.Cut`: CUT_NORMALS
directions of its normal, offsets every CUT_STEP_MM where the part beyond holds CUT_AREA of the muscle, the smaller part), each
column the groups' dr/dln E weighted by the share of each group's area beyond the line (the probe's groups are
coarser than the line; the refit cuts the elements themselves). The stepwise diagnosis refits the best cut beside
the catalog's candidates, the choice of its place counted as a patch's is."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

from ..model.forward import LegModel
from ..model.heterogeneity import (
    SECTOR_DEG,
    Cut,
    Group,
    cut_name,
    element_geometry,
    groups_for,
    leg_centre_mm,
    patch_candidates,
    patch_groups,
    patch_name,
)
from ..model.regions import LegFrame
from .score import ALPHA, ORTHOGONAL_ROUNDOFF

PATCHES_KEPT = 3             # candidate places for a local stiffness change reported, best first
CUT_NORMALS = 48             # the cuts' normals every 7.5 degrees...
CUT_STEP_MM = 2.5            # ...their lines every 2.5 mm...
CUT_AREA = (0.05, 0.5)       # ...where the part beyond holds 5-50 % of the muscle: the changed part is the smaller,
                             # so that the tissue's constants stay those of most of it (the other side of a line is
                             # the same field, its ratio inverted, with the tissue's constants moved by the ratio)



@dataclass
class PatchScore:
    """A candidate place for a local stiffness change: contiguous material groups of one tissue (module text)."""

    effect: str                       # patch:<groups>, the effect that refits it
    tissue: str                       # fat or muscle
    sector_deg: list[float]           # [start, end], display angles counter-clockwise
    centre_deg: float
    depth_mm: list[float]             # [min, max] distance to the skin of its elements' centroids
    area_cm2: float
    place: str                        # "muscle, posterior sector 240-330 deg, 12-35 mm under the skin"
    statistic: float
    p_value: float                    # Bonferroni over the candidates tried
    predicted_misfit: float
    predicted_ratio: float            # stiffness in the patch / stiffness of the tissue, linearized
    significant: bool = False
    places_tried: int = 1             # candidates scored: the choice of this one costs 2 ln N on BIC



def locate(r: np.ndarray, J: np.ndarray, local: np.ndarray, groups: Sequence[Group], frame: LegFrame,
           chi2_to_misfit: float, deff: float, misfit: float, alpha: float = ALPHA,
           keep: int = PATCHES_KEPT) -> list[PatchScore]:
    """Score every candidate patch (`heterogeneity.patch_candidates`) as a one-parameter effect whose column is
    the sum of its groups' dr/dlnE (module text); the best `keep` places that share no group, best first."""
    Q, _ = np.linalg.qr(J)
    r_perp = r - Q @ (Q.T @ r)
    local_perp = local - Q @ (Q.T @ local)
    candidates = patch_candidates(list(groups))
    scored = []
    for members, start, width in candidates:
        g = local[:, members].sum(axis=1)
        g_perp = local_perp[:, members].sum(axis=1)
        norm2 = float(g_perp @ g_perp)
        if norm2 <= (ORTHOGONAL_ROUNDOFF * np.linalg.norm(g)) ** 2:
            continue
        projection = float(g_perp @ r_perp)
        scored.append((projection ** 2 / norm2, -projection / norm2, members, start, width))
    scored.sort(key=lambda item: -item[0])
    chosen, used = [], set()
    for reduction, step, members, start, width in scored:
        if used & set(members):
            continue
        used |= set(members)
        statistic = reduction / deff
        p_value = float(min(1.0, stats.chi2.sf(statistic, 1) * len(candidates)))
        chosen.append(_patch_score([groups[k] for k in members], start, width, frame, statistic, p_value,
                                   misfit - reduction * chi2_to_misfit, float(np.exp(step)), p_value < alpha,
                                   len(candidates)))
        if len(chosen) == keep:
            break
    return chosen



def cut_candidates(mesh, groups: Sequence[Group], kind: str = "muscle") -> list[tuple[Cut, np.ndarray, float]]:
    """The straight cuts of one tissue scored (module text): (cut, each group's share of its area beyond the line,
    the area beyond in mm^2). Groups of other tissues have share 0."""
    centroid, _, _, area = element_geometry(mesh)
    centre = leg_centre_mm(mesh)
    members = [k for k, g in enumerate(groups) if g.kind == kind]
    if not members:
        return []
    elements = np.concatenate([np.asarray(groups[k].elements) for k in members])
    owner = np.concatenate([np.full(len(groups[k].elements), j) for j, k in enumerate(members)])
    weights, total = area[elements], float(area[elements].sum())
    group_area = np.bincount(owner, weights=weights, minlength=len(members))
    found = []
    for normal_deg in np.arange(CUT_NORMALS) * 360.0 / CUT_NORMALS:
        angle = np.radians(normal_deg)
        t = (centroid[elements] - centre) @ np.array([np.cos(angle), -np.sin(angle)])
        for offset in np.arange(np.floor(t.min() / CUT_STEP_MM), np.ceil(t.max() / CUT_STEP_MM)) * CUT_STEP_MM:
            beyond = t > offset
            held = float(weights[beyond].sum())
            if not CUT_AREA[0] <= held / total <= CUT_AREA[1]:
                continue
            share = np.zeros(len(groups))
            share[members] = np.bincount(owner[beyond], weights=weights[beyond], minlength=len(members)) / group_area
            found.append((Cut(kind, float(normal_deg), float(offset)), share, held))
    return found


def locate_cuts(r: np.ndarray, J: np.ndarray, local: np.ndarray, groups: Sequence[Group], mesh, frame: LegFrame,
                chi2_to_misfit: float, deff: float, misfit: float, alpha: float = ALPHA) -> list[PatchScore]:
    """The best straight cut of the muscle (module text) as a one-parameter effect, [] when no cut can be scored;
    its p-value Bonferroni over the cuts tried."""
    candidates = cut_candidates(mesh, groups)
    Q, _ = np.linalg.qr(J)
    r_perp = r - Q @ (Q.T @ r)
    best = None
    for cut, share, held in candidates:
        g = local @ share
        g_perp = g - Q @ (Q.T @ g)
        norm2 = float(g_perp @ g_perp)
        if norm2 <= (ORTHOGONAL_ROUNDOFF * np.linalg.norm(g)) ** 2:
            continue
        projection = float(g_perp @ r_perp)
        if best is None or projection ** 2 / norm2 > best[0]:
            best = (projection ** 2 / norm2, -projection / norm2, cut, held)
    if best is None:
        return []
    reduction, step, cut, held = best
    statistic = reduction / deff
    p_value = float(min(1.0, stats.chi2.sf(statistic, 1) * len(candidates)))
    place = (f"{cut.kind}, {frame.direction(cut.normal_deg)} side beyond a straight line {cut.offset_mm:+.1f} mm from "
             f"the leg's centre (its normal at {cut.normal_deg:.1f} deg)")
    return [PatchScore(cut_name(cut.kind, cut.normal_deg, cut.offset_mm), cut.kind, [cut.normal_deg, cut.normal_deg],
                       cut.normal_deg, [0.0, 0.0], held / 100.0, place, statistic, p_value,
                       misfit - reduction * chi2_to_misfit, float(np.exp(step)), p_value < alpha, len(candidates))]


def _patch_score(members: Sequence[Group], start: int, width: int, frame: LegFrame, statistic: float,
                 p_value: float, predicted_misfit: float, ratio: float, significant: bool,
                 places_tried: int) -> PatchScore:
    low, high = start * SECTOR_DEG, (start + width) * SECTOR_DEG
    centre = ((low + high) / 2.0) % 360.0
    depth = [min(g.depth_range_mm[0] for g in members), max(g.depth_range_mm[1] for g in members)]
    tissue = members[0].kind
    place = (f"{tissue}, {frame.direction(centre)} sector {low % 360:.0f}-{high % 360 or 360:.0f} deg, "
             f"{depth[0]:.0f}-{depth[1]:.0f} mm under the skin")
    return PatchScore(patch_name([g.name for g in members]), tissue, [low % 360.0, high % 360.0 or 360.0], centre, depth,
                      sum(g.area_mm2 for g in members) / 100.0, place, statistic, p_value, predicted_misfit, ratio,
                      significant, places_tried)



def patch_elements(model: LegModel, patch_effect: str) -> np.ndarray:
    """0-based elements of the model's mesh in a patch (to draw it)."""
    members = set(patch_groups(patch_effect))
    groups = groups_for(model.mesh, [patch_effect])
    return np.concatenate([g.elements for g in groups if g.name in members] or [np.zeros(0, int)])
