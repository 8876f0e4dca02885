"""Several garment levels of one slice, fitted jointly (the second paper's socks of 20 and 40 mmHg).

One loaded image says how the leg answers one garment pressure, and in-plane displacements under one pressure
tell the bulk moduli Kv apart from the shear constants only weakly (the first paper identified Kv poorly). A
second image of the same slice under another tension loads the nonlinear tissues differently, so fitting both at
once narrows the intervals (`benchmarks/levels.py`). Bouten and Drapier imaged the same calf with 20 and 40 mmHg
socks.

- `LevelsModel(base, tensions)`: the leg model under each tension (Laplace's law, `forward.LegModel.deck` with
  `tension_N_per_mm`); one evaluation is one deck per level (`decks`), which `runner.execute_task` runs in the
  sub-folders level-1, level-2, ... of the job. The parameters, the start, the mesh and the map from the
  model's parameters to the engine's sensitivities are the base model's: every level is the same tissue.
- `JointDisplacementObjective(parts, between)`: every level's data whitened together. Each level's
  `objectives.DisplacementResidualObjective` gives its differences O u_s - u_e (its own measurements and residual
  rigid motion of the bones: each image was aligned on its own); they are stacked and whitened with the symmetric
  inverse square root of the full covariance

      C = blockdiag(C_meas,k) + B + G W G^T,   G = [G_1; G_2; ...],

  B the measurement errors' covariance between levels (`between`: the noise of I0, whose windows every level's DIC
  shares, `measure.reference_noise_covariance`; half of each window's variance) and G_k W G_l^T the model's
  geometry uncertainty between levels k and l: the same skin modes and interface shifts with the same variances W,
  seen at each level's tension (`geometry_uncertainty`). One segmented skin makes every level's geometry error, so
  the levels' errors are not independent, and whitened level by level (as before) a second level halved the
  intervals while the errors stayed: 9 of 12 benchmark truths inside their two-level 95 % intervals, 12 of 12
  with one level (`benchmarks/levels.py`, seeds 1-3). Each level's rigid motion is then projected out of the
  jointly whitened vector (the nuisance basis is block-diagonal before whitening). The misfit stays Bouten and
  Drapier's eq. 2 over all the levels' points, F = s^2 r.r / n, s^2 the mean variance of one component over all
  of them, its floor s^2 (n - p - k) / n with k the nuisance parameters of every level; `residual_mm` colours back
  with C^1/2 (u_model - u_measured, each level's fitted rigid motion removed) and `level_misfits` are each level's
  own F, its part of that residual weighed by its own covariance: what that level alone would show at the same
  parameters. Without geometry columns nor measurement covariance between levels (points, whose errors are
  independent, before the skin's uncertainty is estimated) the levels' own residuals are concatenated.
- `AtTension(base, tension)`: the base model whose decks default to another tension (a level's pressures).

With the explicit garment (`[model] garment = "explicit"`), each level's band is the case's band made of a fabric
that carries that level's tension at the same size (`GarmentBand.at_tension`): the socks differ in how hard their
fabric pulls, the mesh and every level's deck stay one model's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.linalg import symmetric_roots
from ..model.forward import LegModel
from .objectives import _array_sha


class LevelsModel:
    """The base leg model under each garment tension of `tensions` (the first is the case's [garment] tension,
    the others those of its [[garment.levels]]), one deck per level for one theta."""

    def __init__(self, base: LegModel, tensions: Sequence[float]):
        self.tensions = tuple(float(t) for t in tensions)
        if len(self.tensions) < 2:
            raise ValueError(f"a joint fit needs at least two garment levels, got {len(self.tensions)}: fit the "
                             "model of one level directly")
        if not all(np.isfinite(t) and t > 0 for t in self.tensions):
            raise ValueError(f"garment tensions must be positive, got {list(self.tensions)} N/mm")
        self.base = base
        self.space = base.space
        self.mesh = base.mesh
        self.mesh_text = base.mesh_text
        self.mesh_sha = base.mesh_sha

    @property
    def effects(self) -> tuple[str, ...]:
        return self.base.effects

    @property
    def garment(self) -> str:
        return self.base.garment

    @property
    def engine_sensitivities(self) -> bool:
        return self.base.engine_sensitivities

    def start(self, *args, **kwargs) -> list[float]:
        return self.base.start(*args, **kwargs)

    # what the diagnosis asks of a model (`diagnose`) is the base model's: every level is the same leg

    @property
    def fixed_effects(self):
        return self.base.fixed_effects

    @property
    def tension_profile(self):
        return self.base.tension_profile

    @property
    def friction_mu(self) -> float:
        return self.base.friction_mu

    @property
    def groups(self):
        return self.base.groups

    def law_conflict(self, name: str) -> str | None:
        return self.base.law_conflict(name)

    def garment_conflict(self, name: str) -> str | None:
        return self.base.garment_conflict(name)

    def replace(self, **changes) -> "LevelsModel":
        """The same levels of the base model with these fields changed (`dataclasses.replace` of a LegModel):
        effects added, the garment switched to the band."""
        return LevelsModel(dataclasses.replace(self.base, **changes), self.tensions)

    def deck_state(self, theta: Sequence[float]):
        """The base model's: the materials are the same under every tension (`heterogeneity.stiffness_field_kpa`)."""
        return self.base.deck_state(theta)

    def sensitivity_map(self, theta: Sequence[float]) -> dict[str, list[tuple[str, float]] | None]:
        """The base model's: the tension is not a parameter, so every level has the same engine sensitivities."""
        return self.base.sensitivity_map(theta)

    def decks(self, theta: Sequence[float], **options) -> tuple[str, ...]:
        """The deck of theta under each tension, in the order of `tensions`."""
        if "tension_N_per_mm" in options:
            raise ValueError("a model of several garment levels has its tensions (LevelsModel.tensions); solve "
                             "one level with another tension through its base model (AtTension)")
        return tuple(self.base.deck(theta, tension_N_per_mm=tension, **options) for tension in self.tensions)


@dataclass
class AtTension:
    """The base model with its decks under another garment tension by default (a level's landmark pressures and
    their Table 4 sensitivity to the tension, `identify.pressure_uncertainty`)."""

    base: LegModel
    tension_N_per_mm: float

    def __post_init__(self):
        self.space = self.base.space
        self.mesh = self.base.mesh
        self.mesh_text = self.base.mesh_text
        self.mesh_sha = self.base.mesh_sha

    def deck(self, theta: Sequence[float], tension_N_per_mm: float | None = None, **options) -> str:
        tension = self.tension_N_per_mm if tension_N_per_mm is None else tension_N_per_mm
        return self.base.deck(theta, tension_N_per_mm=tension, **options)


class JointDisplacementObjective:
    """The displacement residuals of every garment level, whitened together (module text). It offers what
    `identify`, `pipeline` and `diagnose` use of a `DisplacementResidualObjective`, with `level_outputs` in place
    of `outputs`: the runner hands it every level's (nodal displacement, output folder) of one evaluation."""

    name = "displacement_residual_levels"
    needs_vtu = False

    def __init__(self, parts: Sequence, between: dict | None = None):
        """parts: each level's `DisplacementResidualObjective`; between: {(k, l): (n_k, n_l) covariance (mm^2)} of the
        measurement errors of levels k < l (0-based), e.g. the noise of I0 that every level's DIC shares
        (`measure.reference_noise_covariance`)."""
        self.parts = tuple(parts)
        if len(self.parts) < 2:
            raise ValueError(f"a joint objective needs at least two garment levels, got {len(self.parts)}")
        bounds = np.cumsum([0] + [part.n_residuals for part in self.parts])
        self.slices = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        self.positions_mm = np.vstack([part.positions_mm for part in self.parts])
        self.nuisance_dof = sum(part.nuisance_dof for part in self.parts)
        # eq. 2 over all the levels' points: the mean variance of one component over every level
        self.reference_variance_mm2 = float(sum(part.reference_variance_mm2 * part.n_residuals for part in self.parts)
                                            / bounds[-1])
        self.source = self.parts[0].source
        self.fingerprint = "levels[" + "|".join(part.fingerprint for part in self.parts) + "]"
        self.geometry_columns = self.geometry_weights = None   # G (the levels' columns stacked) and w, when known
        self._whiten = self._colour = self._nuisance = None
        kinds = [getattr(part, "geometry", "none") for part in self.parts]
        if "covariance" in kinds:
            raise ValueError(
                f"garment level {kinds.index('covariance') + 1}'s skin uncertainty was stored without its columns "
                "(a run folder made before the levels' common skin error was kept), so the covariance between the "
                "levels cannot be formed: rerun `calfit identify CASE_DIR --out RUN_DIR` to estimate it again")
        self.between = {(int(k), int(l)): np.asarray(block, float) for (k, l), block in (between or {}).items()
                        if block is not None and np.any(block)}
        for (k, l), block in self.between.items():
            if not 0 <= k < l < len(self.parts) or block.shape != (self.parts[k].n_residuals, self.parts[l].n_residuals):
                raise ValueError(f"the covariance between garment levels {k + 1} and {l + 1} is {block.shape}")
        if "columns" in kinds or self.between:
            self._whiten_together()

    def _whiten_together(self) -> None:
        """C = blockdiag(C_meas,k) + the measurement covariance between levels + G diag(w) G^T with G the levels'
        geometry columns stacked (a level without them adds zero rows), its symmetric inverse square root and
        square root, and the projection that removes each level's own residual rigid motion after the joint
        whitening."""
        weights = [part.geometry_weights for part in self.parts if part.geometry == "columns"]
        if any(w.shape != weights[0].shape or not np.allclose(w, weights[0], rtol=1e-9, atol=0) for w in weights):
            raise ValueError("the garment levels' skin uncertainties were made with other mode variances (another "
                             "skin uncertainty or mesh): estimate them again together (`calfit identify`)")
        weights = weights[0] if weights else np.zeros(0)
        n = self.n_residuals
        columns = np.zeros((n, len(weights)))
        covariance = np.zeros((n, n))
        for (k, l), block in self.between.items():
            covariance[self.slices[k], self.slices[l]] = block
            covariance[self.slices[l], self.slices[k]] = block.T
        rigid = np.zeros((n, self.nuisance_dof))
        column = 0
        for part, rows in zip(self.parts, self.slices):
            if part.geometry == "columns":
                columns[rows] = part.geometry_columns
                covariance[rows, rows] = part.measurement_covariance
            else:
                covariance[rows, rows] = part._colour @ part._colour   # C_k = C_k^1/2 C_k^1/2
            rigid[rows, column:column + part.nuisance_dof] = part.rigid_columns
            column += part.nuisance_dof
        covariance += (columns * weights) @ columns.T
        self._whiten, self._colour = symmetric_roots(covariance, "the joint covariance of the garment levels")
        self._nuisance, _ = np.linalg.qr(self._whiten @ rigid)
        self.geometry_columns, self.geometry_weights = (columns, weights) if len(weights) else (None, None)
        self.fingerprint += f":together:{_array_sha(columns, weights, *(self.between[key] for key in sorted(self.between)))}"

    @property
    def together(self) -> bool:
        """Whether the levels' data are whitened together (their geometry columns or the measurement covariance
        between them known), not each on its own."""
        return self._whiten is not None

    @property
    def covariance_mm2(self) -> np.ndarray:
        """The covariance every level's data are whitened with: C (together), or blockdiag(C_k) (each alone)."""
        if self.together:
            return self._colour @ self._colour
        n = self.n_residuals
        covariance = np.zeros((n, n))
        for part, rows in zip(self.parts, self.slices):
            covariance[rows, rows] = part._colour @ part._colour
        return covariance

    @property
    def n_residuals(self) -> int:
        return self.slices[-1].stop

    def split(self, residuals: np.ndarray) -> list[np.ndarray]:
        """A joint residual vector cut into its levels' parts."""
        residuals = np.asarray(residuals, float)
        return [residuals[part] for part in self.slices]

    def weigh(self, values_mm: np.ndarray) -> np.ndarray:
        """P C^-1/2 of every level's values (mm) stacked: jointly, or each level by its own part."""
        values_mm = np.asarray(values_mm, float)
        if not self.together:
            return np.concatenate([part.weigh(values_mm[rows]) for part, rows in zip(self.parts, self.slices)])
        whitened = self._whiten @ values_mm
        return whitened - self._nuisance @ (self._nuisance.T @ whitened)

    def residuals(self, nodal_per_level: Sequence[np.ndarray]) -> np.ndarray:
        if len(nodal_per_level) != len(self.parts):
            raise ValueError(f"{len(nodal_per_level)} nodal fields for {len(self.parts)} garment levels")
        if not self.together:
            return np.concatenate([part.residuals(u) for part, u in zip(self.parts, nodal_per_level)])
        return self.weigh(np.concatenate([part.difference(u) for part, u in zip(self.parts, nodal_per_level)]))

    def cost_of(self, residuals: np.ndarray) -> float:
        """F (mm^2) of a joint residual vector."""
        residuals = np.asarray(residuals, float)
        return float(self.reference_variance_mm2 * (residuals @ residuals) / len(residuals))

    def noise_floor(self, n_parameters: int) -> float:
        """Expected F of a correct model with n_parameters fitted to every level's measurements."""
        n = self.n_residuals
        return float(self.reference_variance_mm2 * (n - n_parameters - self.nuisance_dof) / n)

    def residual_mm(self, residuals: np.ndarray) -> np.ndarray:
        """(N, 2) u_model - u_measured in mm (each level's fitted residual rigid motion removed), the levels one
        after the other (as `positions_mm`)."""
        if not self.together:
            return np.vstack([part.residual_mm(r) for part, r in zip(self.parts, self.split(residuals))])
        return (self._colour @ np.asarray(residuals, float)).reshape(-1, 2)

    def level_misfits(self, residuals: np.ndarray) -> list[float]:
        """Each level's own F (its points, its s^2, its own covariance): the misfit that level alone would have
        at the same parameters."""
        if not self.together:
            return [part.cost_of(r) for part, r in zip(self.parts, self.split(residuals))]
        # each level's part of the residual in mm less a rigid motion of that level, which its own projection removes
        values = self.residual_mm(residuals).ravel()
        return [part.cost_of(part.weigh(values[rows])) for part, rows in zip(self.parts, self.slices)]

    def outputs(self, nodal_per_level: Sequence[np.ndarray], outdirs: Sequence[Path]) -> dict:
        """`level_outputs` with the levels' nodal fields and output folders in two sequences (a one-level
        objective's `outputs(nodal_u, outdir)`, each argument holding one entry per level)."""
        return self.level_outputs(list(zip(nodal_per_level, outdirs)))

    def level_outputs(self, levels: Sequence[tuple[np.ndarray, Path]]) -> dict:
        """Cost, residuals, each level's misfit and, when the decks asked for them, dr/d(engine parameter) of
        every level (concatenated per engine parameter name, or whitened together)."""
        if len(levels) != len(self.parts):
            raise ValueError(f"{len(levels)} engine results for {len(self.parts)} garment levels")
        if not self.together:
            outputs = [part.outputs(nodal, Path(outdir)) for part, (nodal, outdir) in zip(self.parts, levels)]
            residuals = np.concatenate([np.asarray(out["residuals"], float) for out in outputs])
            joined = {"cost": self.cost_of(residuals), "residuals": residuals.tolist(),
                      "level_misfits": [float(out["cost"]) for out in outputs]}
            sensitivities = [out.get("sensitivity") or {} for out in outputs]
            if all(sensitivities):
                names = [name for name in sensitivities[0] if all(name in s for s in sensitivities[1:])]
                joined["sensitivity"] = {name: [v for s in sensitivities for v in s[name]] for name in names}
            return joined
        residuals = self.residuals([nodal for nodal, _ in levels])
        joined = {"cost": self.cost_of(residuals), "residuals": residuals.tolist(),
                  "level_misfits": self.level_misfits(residuals)}
        observed = [part.observed_sensitivities(Path(outdir)) for part, (_, outdir) in zip(self.parts, levels)]
        if all(observed):
            names = [name for name in observed[0] if all(name in s for s in observed[1:])]
            joined["sensitivity"] = {name: self.weigh(np.concatenate([s[name] for s in observed])).tolist()
                                     for name in names}
        return joined
