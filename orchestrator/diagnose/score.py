"""The score of a missing effect: how much of the fitted model's residual its columns could take; the thresholds the
diagnosis judges by and the information criteria of a fit.

Residual. r = P C^-1/2 (u_model - u_measured) at the measured points or DIC windows (Bouten and Drapier
eq. 2 weighted by the measurements' covariance C, both components, n = 2N values; P removes the k nuisance
directions, the residual rigid motion of the bones for DIC; `objectives.DisplacementResidualObjective`), at
the identified parameters theta of p fitted parameters. The misfit is F = s^2 r.r / n (mm^2, the
identification's cost, s^2 the mean variance of one component); for a correct model its expectation is the
noise floor F_0 = s^2 (n - p - k) / n, and r.r is chi^2 with n - p - k degrees of freedom.

Which effect is missing (docs/method/diagnosis.md). For every catalog effect not in the model, G = dr/dphi at phi = 0
(n x q, its q parameters), from the engine's sensitivities when it gives them (one run), otherwise by
forward differences of step `scale`. Its part that the fitted parameters cannot absorb is
G_perp = G - J (J^T J)^-1 J^T G (J = dr/dx, x the optimizer's variables). Linearized, refitting with
the effect lowers chi^2 = r.r by U^T M^-1 U with U = G_perp^T r and M = G_perp^T G_perp (the predicted
reduction; for q = 1 it is (g_perp^T r)^2 / g_perp^T g_perp), and the score statistic
S = U^T M^-1 U / (sigma^2 D) is chi^2 with q degrees of freedom when the effect is absent (r is
normalized: sigma = 1). D >= 1 is the design effect of residuals correlated in space: with rho the
correlation of each point's residual with its nearest neighbour's, D = (1 + rho) / (1 - rho) (the AR(1)
variance inflation, i.e. an effective sample size n / D); independent noise has rho ~ 0 and D = 1, a
smooth misfit pattern a large D, which keeps a smooth model error from passing for many independent
pieces of evidence. |g_perp| / |g| tells how much of the effect the fitted parameters would mimic
(0: all of it). Effects are ranked by S; one is significant when its p-value is below alpha / m
(Bonferroni over the m effects tried), whether or not the misfit as a whole is above the noise floor (the chi^2
lack-of-fit test, which a faint effect of few parameters passes: `diagnosis.diagnose`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..engine.results import OK

ALPHA = 0.01

EXPLAINED_FACTOR = 1.5       # predicted misfit within 1.5 x the noise floor: the effect explains the residual

# the error model agrees with the measured errors to a chi^2/n of 0.8-1.25 (benchmarks/imaging.py: every band, pooled
# over the cases of both renderers and of another program): an explaining refit above 1.25 x has not reached the
# floor, and the verdict says so
FLOOR_AGREEMENT = 1.25

MAX_DESIGN_EFFECT = 100.0

ORTHOGONAL_ROUNDOFF = 1e-8   # |g_perp| / |g| below this: the fitted parameters absorb the effect entirely



@dataclass
class EffectScore:
    effect: str
    parameters: list[str]
    statistic: float
    dof: int
    p_value: float
    predicted_reduction: float        # of the misfit F, mm^2
    predicted_misfit: float           # F - reduction, mm^2
    orthogonal_fraction: list[float]  # |g_perp| / |g| per parameter
    predicted_values: list[float]     # the linearized refit's parameter values
    significant: bool = False
    tied_with: list[str] = field(default_factory=list)   # effects the score cannot tell from this one



def neighbour_correlation(positions_mm: np.ndarray, residual: np.ndarray,
                          levels: Sequence[slice] | None = None) -> float:
    """Correlation of each point's residual vector with that of its nearest neighbour in the same garment level
    (`levels`: each level's rows; the levels' windows are the same windows of I0, each its own twin otherwise)."""
    vectors = np.asarray(residual, float).reshape(-1, 2)
    positions_mm = np.asarray(positions_mm, float)
    products = squares = 0.0
    for rows in levels or [slice(0, len(vectors))]:
        own, places = vectors[rows], positions_mm[rows]
        if len(own) < 3:
            continue
        _, nearest = cKDTree(places).query(places, k=2)
        products += float(np.sum(own * own[nearest[:, 1]]))
        squares += float(np.sum(own * own))
    return products / max(squares, 1e-300) if squares else 0.0



def design_effect(rho: float) -> float:
    rho = min(max(rho, 0.0), 0.999)
    return float(min((1.0 + rho) / (1.0 - rho), MAX_DESIGN_EFFECT))



def score_effect(r: np.ndarray, J: np.ndarray, G: np.ndarray, chi2_to_misfit: float, deff: float) -> dict:
    """Score statistic, predicted reduction and orthogonal fractions of one effect (module text)."""
    Q, _ = np.linalg.qr(J)
    G_perp = G - Q @ (Q.T @ G)
    r_perp = r - Q @ (Q.T @ r)
    norms = np.linalg.norm(G, axis=0)
    fraction = np.linalg.norm(G_perp, axis=0) / np.where(norms > 0, norms, 1.0)
    # in units of |g|, so that a direction the fitted parameters absorb (round-off left) counts as zero
    unit = G_perp / np.where(norms > 0, norms, 1.0)
    unit[:, fraction < ORTHOGONAL_ROUNDOFF] = 0.0
    U = unit.T @ r_perp
    solution, *_ = np.linalg.lstsq(unit.T @ unit, U, rcond=ORTHOGONAL_ROUNDOFF)
    reduction = float(max(U @ solution, 0.0))
    return {"statistic": reduction / deff, "reduction_chi2": reduction,
            "predicted_reduction": reduction * chi2_to_misfit, "orthogonal_fraction": fraction.tolist(),
            "step": (-solution / np.where(norms > 0, norms, 1.0)).tolist()}



def information_criteria(chi2: float, k: int, n: int) -> dict:
    return {"chi2": chi2, "k": k, "aic": chi2 + 2 * k, "bic": chi2 + k * np.log(n)}



def residuals_of(record: dict) -> np.ndarray:
    if record["status"] != OK:
        raise RuntimeError(f"the engine failed at the diagnosis point: {record['message']}")
    return np.asarray(record["outputs"]["residuals"], float)
