"""The forward model: parameters -> deck -> calfit-fe -> nodal displacement -> displacement anywhere.

A model (`LegModel`, `DiskModel`) turns a parameter vector theta into the text of a deck
(`orchestrator.engine.decks`) for its mesh. The engine gives the nodal displacement u_a; the
displacement at any point x of the reference configuration is the finite-element
interpolation u(x) = sum_a N_a(x) u_a on the triangle that holds x (barycentric coordinates
L1, L2, L3; T3: N_a = L_a; T6 with straight sides: N_a = L_a (2 L_a - 1) at the corners and
4 L_a L_b at the mid-side nodes). `MeshInterpolator` assembles these weights once into a
sparse matrix W, so that u at all the pixels of an image is one product W u: this is the
u(x) of the warping I(x) = I1(x + u(x)) (Avril et al. sec. 2.1.2) and of the displacement
residual at DIC points (Bouten and Drapier eq. 2). Points outside the mesh (background,
bone holes) take the displacement of the nearest point of the nearest element (the bones'
boundary is clamped, so bone pixels get u = 0).

Parameters of the leg model: the constants of each tissue's law (`orchestrator.core.materials`), by constant then
by tissue, in kPa (decks are in MPa); with the first paper's law in fat and muscle, Avril et al.'s Table 1
order: C10 of fat, C10 of muscle, Kv of fat, Kv of muscle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from ..core.errors import MaterialError
from ..core.materials import (
    AVRIL,
    AVRIL_START_KPA,
    CONSTANT_ORDER,
    GARMENTS,
    HIGHER_ORDER_SCALE_KPA,
    LINEAR_CONSTANTS,
    TissueLaw,
    deck_material,
    default_bounds,
    default_start,
    engine_constant,
    sum_only_pairs,
    tissue_set,
)
from ..core.tissues import parameter_tissue
from ..core.units import KPA_PER_MPA
from ..engine.decks import disk_deck, leg_garment_deck, leg_laplace_deck, text_sha256
from ..meshing import Mesh
from ..meshing.mesh import muscle_sets
from .heterogeneity import group_elsets_text, groups_for

LEG_PARAMETERS = ("C10_fat", "C10_muscle", "Kv_fat", "Kv_muscle")   # the first paper's law in fat and muscle
BAND_PROFILE = "band_profile"   # the band's own effect: its prestretch varying around the leg (`effects`)
# Avril et al. Table 2, central values (kPa), in LEG_PARAMETERS order: the phantom's default truth and the fits' usual
# start (`materials.AVRIL_START_KPA`).
TABLE2_CENTRAL_KPA = tuple(AVRIL_START_KPA[name.split("_")[1]][name.split("_")[0]] for name in LEG_PARAMETERS)
CANDIDATE_ELEMENTS = 8   # nearest element centroids searched for the triangle holding a point
INSIDE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class ParameterSpace:
    """Named parameters with the box where Monte-Carlo draws are made (same units as theta).

    Material constants are positive and the optimizers move them in ln(theta) (relative steps); effect
    parameters (`linear`) are zero when the effect is off and may be negative, so they move in
    theta / scale. `to_x` / `from_x` are that change of variables, one place for every optimizer."""

    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    units: str = "kPa"
    linear: tuple[bool, ...] = ()
    scale: tuple[float, ...] = ()
    unit_of: tuple[str, ...] = ()

    def __post_init__(self):
        n = len(self.names)
        if not (n == len(self.lower) == len(self.upper)):
            raise ValueError("a parameter space needs one lower and one upper bound per parameter")
        object.__setattr__(self, "linear", tuple(self.linear) or (False,) * n)
        object.__setattr__(self, "scale", tuple(self.scale) or (1.0,) * n)
        object.__setattr__(self, "unit_of", tuple(self.unit_of) or (self.units,) * n)
        if not (len(self.linear) == len(self.scale) == len(self.unit_of) == n):
            raise ValueError("linear, scale and unit_of need one entry per parameter")
        for name, lo, hi, linear in zip(self.names, self.lower, self.upper, self.linear):
            if not (lo < hi and (linear or lo > 0)):
                raise ValueError(f"bounds of {name} must satisfy {'' if linear else '0 < '}lower < upper, got ({lo}, {hi})")

    @property
    def size(self) -> int:
        return len(self.names)

    def to_x(self, theta) -> np.ndarray:
        theta = np.asarray(theta, float)
        linear, scale = np.array(self.linear), np.array(self.scale)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(linear, theta / scale, np.log(np.where(linear, 1.0, theta)))

    def from_x(self, x) -> np.ndarray:
        x = np.asarray(x, float)
        linear, scale = np.array(self.linear), np.array(self.scale)
        return np.where(linear, x * scale, np.exp(np.where(linear, 0.0, x)))

    def clip(self, theta) -> np.ndarray:
        """theta inside the box: a fit that runs away (a constant to 1e-8 kPa) stops at the edge, where the
        report shows it, instead of producing decks far outside any tissue."""
        return np.clip(np.asarray(theta, float), np.array(self.lower), np.array(self.upper))

    def draw(self, count: int, rng: np.random.Generator, lower=None, upper=None) -> np.ndarray:
        """count uniform draws in the box (or in [lower, upper])."""
        lo = np.asarray(self.lower if lower is None else lower, float)
        hi = np.asarray(self.upper if upper is None else upper, float)
        return lo + (hi - lo) * rng.random((count, self.size))

    def as_dict(self, theta) -> dict[str, float]:
        return {name: float(value) for name, value in zip(self.names, theta)}

    def join(self, other: "ParameterSpace") -> "ParameterSpace":
        return ParameterSpace(self.names + other.names, self.lower + other.lower, self.upper + other.upper, self.units,
                              self.linear + other.linear, self.scale + other.scale, self.unit_of + other.unit_of)


# --- interpolation of a nodal field --------------------------------------------------------------

def _barycentric(nodes: np.ndarray, corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 3) barycentric coordinates of points (..., 2) in triangles with corner indices (..., 3)."""
    p1, p2, p3 = nodes[corners[..., 0]], nodes[corners[..., 1]], nodes[corners[..., 2]]
    v1, v2, w = p2 - p1, p3 - p1, points - p1
    det = v1[..., 0] * v2[..., 1] - v1[..., 1] * v2[..., 0]
    l2 = (w[..., 0] * v2[..., 1] - w[..., 1] * v2[..., 0]) / det
    l3 = (v1[..., 0] * w[..., 1] - v1[..., 1] * w[..., 0]) / det
    return np.stack([1.0 - l2 - l3, l2, l3], axis=-1)


def shape_functions(bary: np.ndarray, order: int) -> np.ndarray:
    """(n, 3) or (n, 6) shape function values of T3 / straight-sided T6 at barycentric coordinates."""
    if order == 1:
        return bary
    l1, l2, l3 = bary[:, 0], bary[:, 1], bary[:, 2]
    return np.stack([l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), l3 * (2 * l3 - 1), 4 * l1 * l2, 4 * l2 * l3, 4 * l3 * l1], axis=1)


class MeshInterpolator:
    """Finite-element interpolation of nodal fields of one mesh at fixed points: values = W @ nodal."""

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        self._corners = mesh.elements[:, :3]
        self._tree = cKDTree(mesh.nodes[self._corners].mean(axis=1))

    def weights(self, points: np.ndarray) -> sparse.csr_matrix:
        """Sparse (n_points, n_nodes) interpolation matrix at points (n, 2) in mm."""
        points = np.asarray(points, float).reshape(-1, 2)
        k = min(CANDIDATE_ELEMENTS, len(self._corners))
        _, candidates = self._tree.query(points, k=k)
        candidates = candidates.reshape(len(points), k)
        bary = _barycentric(self.mesh.nodes, self._corners[candidates], points[:, None, :])   # (n, k, 3)
        worst = bary.min(axis=2)
        inside = worst >= -INSIDE_TOLERANCE
        choice = np.where(inside.any(axis=1), inside.argmax(axis=1), worst.argmax(axis=1))
        rows = np.arange(len(points))
        element = candidates[rows, choice]
        chosen = np.clip(bary[rows, choice], 0.0, None)   # outside: the nearest point of the element
        chosen /= chosen.sum(axis=1, keepdims=True)
        values = shape_functions(chosen, self.mesh.order)
        columns = self.mesh.elements[element]
        n_per_row = columns.shape[1]
        return sparse.csr_matrix((values.ravel(), columns.ravel(), np.arange(0, values.size + 1, n_per_row)),
                                 shape=(len(points), len(self.mesh.nodes)))

    def pixel_weights(self, shape: tuple[int, int], pixel_size_mm: Sequence[float]) -> sparse.csr_matrix:
        """Interpolation matrix at the pixel centres ((j + 0.5) dx, (i + 0.5) dy) of an image, row-major."""
        dy, dx = (float(v) for v in pixel_size_mm)
        rows, cols = np.indices(shape, dtype=float)
        return self.weights(np.column_stack([((cols + 0.5) * dx).ravel(), ((rows + 0.5) * dy).ravel()]))


def field_on_pixels(weights: sparse.csr_matrix, nodal: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(2, H, W) displacement on the pixel grid (component 0 along x) from a nodal (n, 2) field."""
    values = weights @ np.asarray(nodal, float)
    return np.ascontiguousarray(values.T.reshape(2, *shape))


# --- models ----------------------------------------------------------------------------------------

def _effect_space(names: Sequence[str], element_sets: Sequence[str], node_sets: Sequence[str],
                  garment: str = "laplace") -> ParameterSpace:
    from .effects import effect

    parameters = [p for name in names for p in effect(name).parameters(element_sets, node_sets, garment)]
    return ParameterSpace(tuple(p.name for p in parameters), tuple(p.lower for p in parameters),
                          tuple(p.upper for p in parameters), "", (True,) * len(parameters),
                          tuple(p.scale for p in parameters), tuple(p.unit for p in parameters))


@dataclass
class LegModel:
    """The leg slice of Avril et al.: two tissues with the AVRIL law, clamped bones, Laplace garment;
    optionally with effects of the catalog (`orchestrator.model.effects`).

    garment: "laplace" (Avril et al. eq. 1, the default) or "explicit": the second paper's band
    (`orchestrator.meshing.garment_band`, carrying tension_N_per_mm at its design stretch) put on by
    templates/leg_garment.inp.j2 with penalty contact and Coulomb friction `friction_mu`. The band's nodes follow
    the leg's in the deck, and the objectives read the leg's rows only. The engine's sensitivities pass through
    frictionless contact; with friction the engine carries them along the loading path for what acts on the elements
    alone (solver_cpp/README.md, Sensitivities): the deck then asks for the constants' (the tissues' laws,
    heterogeneity, compartments, stiffening), the drainage's and the out-of-plane stretch's, and the fits difference
    runs for the other parameters (a bone's motion, the band's prestretch profile, the friction coefficient:
    `engine_differentiates`).
    The explicit band's deck carries the catalog's effects on the tissues and bones, and friction
    (`effects.Effect.garments`).

    tissues: the law of each tissue (`materials.TissueLaw` by tissue name: fat, muscle, compartment<label>; the
    first paper's AVRIL law where none is given); a compartment without its own law shares the muscle's.

    theta = the free constants of the tissues' laws in kPa (`materials.CONSTANT_ORDER`, then tissue order:
    (C10_fat, C10_muscle, Kv_fat, Kv_muscle) for the first paper's law), then the parameters of `effects` in catalog
    order; `fixed_effects` are switched on at given values and not fitted (how a case with a hidden effect
    is made); with `engine_sensitivities` the deck asks calfit-fe for du/dtheta of every parameter of theta
    (`*SENSITIVITY`), which the objectives turn into the Jacobian of their residuals. All muscle element sets
    (MUSCLE, or COMPARTMENTk when the labels have compartments) share the muscle constants unless the
    `compartments` effect separates them."""

    mesh: Mesh
    tension_N_per_mm: float
    tension_profile: Sequence[tuple[float, float]] | None = None
    effects: tuple[str, ...] = ()
    fixed_effects: dict = field(default_factory=dict)
    engine_sensitivities: bool = False
    garment: str = "laplace"
    friction_mu: float = 0.0
    hybrid: bool = False   # the leg's elements as u/p (CPE6H, CPE3H): nearly or fully incompressible tissues
    tissues: dict | None = None

    def __post_init__(self):
        self._check_garment_options()
        sets = self.mesh.element_sets()
        self._set_laws(list(sets))
        self.effects = tuple(self.effects)
        conflict = self.garment_conflict(BAND_PROFILE) if BAND_PROFILE in self._all_effects else None
        if conflict:
            raise ValueError(f"effect {BAND_PROFILE!r} is not available on this model: {conflict}")
        overlap = set(self.effects) & set(self.fixed_effects)
        if overlap:
            raise ValueError(f"effects {sorted(overlap)} are both fitted and fixed")
        self.groups = groups_for(self.mesh, self.effects + tuple(self.fixed_effects))
        element_sets = list(sets) + [group.name for group in self.groups]
        self.space = self._law_space().join(_effect_space(self.effects, element_sets, list(self.mesh.node_sets),
                                                          self.garment))
        _effect_space(list(self.fixed_effects), element_sets, list(self.mesh.node_sets), self.garment)  # they fit?
        self.mesh_text = self._mesh_include_text()
        self.mesh_sha = text_sha256(self.mesh_text)

    def _check_garment_options(self) -> None:
        """The garment's options agree with each other: a known garment, friction only on the explicit band and
        given once, a tabulated tension profile only with Laplace's law."""
        if self.garment not in GARMENTS:
            raise ValueError(f"garment must be one of {GARMENTS}, got {self.garment!r}")
        if self.friction_mu < 0.0 or (self.friction_mu > 0.0 and self.garment != "explicit"):
            raise ValueError(f"a friction coefficient ({self.friction_mu}) needs garment = 'explicit' and must be >= 0")
        if self.garment == "explicit" and self.tension_profile:
            raise ValueError("a tabulated tension profile belongs to Laplace's law (p = T / r), and this model fits the "
                             "explicit garment ([model] garment = \"explicit\" in case.toml): leave the profile out, "
                             "or fit Laplace's law")
        if "friction" in self.effects and self.friction_mu > 0.0:
            raise ValueError("the friction coefficient is both fixed (friction_mu, [model] friction) and fitted "
                             "(the friction effect): give one")

    def _mesh_include_text(self) -> str:
        """The deck's mesh include: the leg (its elements u/p when hybrid), the explicit band and its sectors when
        there is one, and the effects' element sets. Sets self.band and self.band_sectors."""
        from ..meshing import garment_band

        self.band = garment_band(self.mesh, self.tension_N_per_mm) if self.garment == "explicit" else None
        mesh_text = self.band.include_text(self.mesh) if self.band else self.mesh.include_text()
        # the band's sectors, once: every deck of a model with band_profile writes their volume changes
        self.band_sectors = (self.band.sector_sets() if self.band is not None and BAND_PROFILE in self._all_effects
                             else {})
        if self.band_sectors:
            mesh_text += self.band.sector_elsets_text(self.mesh)
        if self.hybrid:   # the leg's element block only: the band stays a compressible displacement element
            leg_block = f"*ELEMENT, TYPE={self.mesh.element_type}, ELSET=EALL"
            mesh_text = mesh_text.replace(leg_block, f"*ELEMENT, TYPE={self.mesh.element_type}H, ELSET=EALL", 1)
        return mesh_text + group_elsets_text(self.groups)

    @property
    def _all_effects(self) -> tuple[str, ...]:
        return tuple(self.effects) + tuple(self.fixed_effects)

    def garment_conflict(self, effect_name: str) -> str | None:
        """Why an effect of the band cannot act on this model's garment (None when it can)."""
        if effect_name == BAND_PROFILE and self.garment == "explicit" and not (self.friction_mu > 0.0
                                                                               or "friction" in self.effects):
            return ("a frictionless band slides over the skin until its hoop force is the same all round, whatever "
                    "its prestretch: the prestretch's profile needs friction ([model] friction, or the friction "
                    "effect)")
        return None

    @property
    def has_friction(self) -> bool:
        """The band with friction, fixed ([model] friction) or fitted (the friction effect)."""
        return self.garment == "explicit" and (self.friction_mu > 0.0 or "friction" in self.effects)

    def engine_differentiates(self, line: str) -> bool:
        """Whether calfit-fe gives du/dtheta of a `*SENSITIVITY` line on this model: every line through
        frictionless contact; with friction, what acts on the elements alone from the band's last step on (the
        constants, the tissues' volume changes, the axial stretch) and the skin's shape and its offset as the band
        feels it (`SHAPE`, `GAP PROFILE`), not a rigid motion or the band's own prestretch, set in its second step
        (solver_cpp/README.md, Sensitivities)."""
        if (not self.has_friction or line.startswith(("MATERIAL,", "GAP PROFILE,", "SHAPE,"))
                or line == "AXIAL STRETCH"):
            return True
        return line.startswith("VOLUME CHANGE,") and line.split(", ")[1] not in self.band_sectors

    def _set_laws(self, element_sets: list[str]) -> None:
        """The tissues' laws, the element sets each governs and the checks that they fit the mesh and elements."""
        given = dict(self.tissues or {})
        laws = {"fat": given.pop("fat", AVRIL), "muscle": given.pop("muscle", AVRIL)}
        for tissue in sorted(given):
            if tissue_set(tissue) not in element_sets:
                raise MaterialError(f"the leg mesh has no {tissue_set(tissue)} elements for the law of {tissue}: label "
                                    f"that compartment {tissue[len('compartment'):]} in labels.png")
            laws[tissue] = given[tissue]
        self.tissue_laws: dict[str, TissueLaw] = laws
        own = {tissue_set(t) for t in laws if t not in ("fat", "muscle")}
        self.muscle_sets = [name for name in muscle_sets(element_sets) if name not in own]
        if "FAT" not in element_sets or not self.muscle_sets:
            missing = ", ".join(n for n, ok in (("FAT", "FAT" in element_sets), ("MUSCLE", bool(self.muscle_sets)))
                                if not ok)
            raise ValueError(f"the leg mesh has no {missing} elements; check the segmentation labels")
        # element set -> tissue, in the mesh's order (the deck's materials keep the first paper's order)
        self.set_tissue = {name: ("fat" if name == "FAT" else parameter_tissue(name) if name in own else "muscle")
                           for name in ["FAT"] + muscle_sets(element_sets)}
        for tissue, law in laws.items():
            if law.incompressible and not self.hybrid:
                raise MaterialError(f"{tissue} is incompressible (D1 = 0), which displacement elements lock on: "
                                    "fit with u/p elements (element = \"CPE6H\" in case.toml's [model])")
        for name in set(self.effects) | set(self.fixed_effects):
            conflict = self.law_conflict(name)
            if conflict:
                raise MaterialError(conflict)

    def law_conflict(self, effect_name: str) -> str | None:
        """Why a catalog effect cannot join the tissues' laws (None when it can)."""
        if effect_name == "stiffening":
            having = [f"{law.law} law of {tissue}" for tissue, law in self.tissue_laws.items() if law.has_c20()]
            if having:
                return (f"the {', '.join(having)} has C20 already: the stiffening effect would add it twice (leave it "
                        "out, or fix or free C20 in the law)")
        own = sorted(tissue for tissue in self.tissue_laws if tissue not in ("fat", "muscle"))
        if effect_name == "compartments" and own:
            return (f"the compartments effect scales the muscle's C10 in each compartment, and {', '.join(own)} have "
                    "laws of their own: use one or the other")
        return None

    def _law_space(self) -> ParameterSpace:
        """The free constants of the tissues' laws: by constant (materials.CONSTANT_ORDER), then by tissue."""
        names, lower, upper, linear, scale = [], [], [], [], []
        for constant in CONSTANT_ORDER:
            for tissue, law in self.tissue_laws.items():
                if constant in law.free:
                    low, high = default_bounds(tissue, law, constant)
                    names.append(f"{constant}_{tissue}")
                    lower.append(low)
                    upper.append(high)
                    linear.append(constant in LINEAR_CONSTANTS)
                    scale.append(HIGHER_ORDER_SCALE_KPA if constant in LINEAR_CONSTANTS else 1.0)
        return ParameterSpace(tuple(names), tuple(lower), tuple(upper), "kPa", tuple(linear), tuple(scale))

    @property
    def law_parameters(self) -> tuple[str, ...]:
        """The names of theta's first values: the free constants of the laws."""
        return self.space.names[:self.law_size]

    @property
    def law_size(self) -> int:
        return sum(len(law.free) for law in self.tissue_laws.values())

    @property
    def sum_only(self) -> list[tuple[str, str]]:
        """Pairs of theta's parameters that act only through their sum (`materials.sum_only_pairs`)."""
        return sum_only_pairs(self.tissue_laws)

    @property
    def base_start(self) -> list[float]:
        """The laws' start (kPa): case.toml's, else Avril et al. Table 2 (`materials.default_start`)."""
        constants_and_tissues = (name.split("_", 1) for name in self.law_parameters)
        return [default_start(tissue, self.tissue_laws[tissue], constant) for constant, tissue in constants_and_tissues]

    def start(self, base_kPa: Sequence[float] | None = None) -> list[float]:
        """A start point: the laws' constants (`base_start` when not given), every effect parameter at zero (off)."""
        base = self.base_start if base_kPa is None else [float(v) for v in base_kPa]
        if len(base) != self.law_size:
            raise ValueError(f"a start of the laws needs {self.law_size} values ({', '.join(self.law_parameters)}), "
                             f"got {len(base)}")
        return base + [0.0] * (self.space.size - self.law_size)

    def deck_state(self, theta: Sequence[float]):
        """The materials and step keywords of theta, with the *SENSITIVITY lines of every parameter."""
        from .effects import LegDeckState, effect, split_into_groups

        theta = [float(v) for v in theta]
        if len(theta) != self.space.size:
            raise ValueError(f"theta has {len(theta)} values; this model has {self.space.size}: {self.space.names}")
        law_values = dict(zip(self.law_parameters, theta))
        per_tissue = {tissue: {constant: (law_values[f"{constant}_{tissue}"] if constant in law.free
                                          else float(law.fixed[constant])) / KPA_PER_MPA
                               for constant in law.constants}
                      for tissue, law in self.tissue_laws.items()}
        state = LegDeckState({elset: dict(per_tissue[tissue]) for elset, tissue in self.set_tissue.items()},
                             laws={elset: self.tissue_laws[tissue] for elset, tissue in self.set_tissue.items()},
                             groups=self.groups)
        state.band_sectors = {name: angle for name, (_, angle) in self.band_sectors.items()}
        for name in self.law_parameters:
            constant, tissue = name.split("_", 1)
            state.sensitivity[name] = []
            for elset in (e for e, t in self.set_tissue.items() if t == tissue):
                engine_name, factor = engine_constant(self.tissue_laws[tissue], constant, per_tissue[tissue])
                state.sensitivity[name].append((f"MATERIAL, {elset}, {engine_name}", factor))
        values = dict(zip(self.space.names[self.law_size:], theta[self.law_size:]))
        element_sets = list(state.constants) + [group.name for group in self.groups]
        for name in self.effects:
            item = effect(name)
            if item.apply is not None:   # the garment's effects (friction) are the explicit deck's, not the state's
                item.apply(state, {p.name: values[p.name]
                                   for p in item.parameters(element_sets, list(self.mesh.node_sets), self.garment)})
        for name, fixed in self.fixed_effects.items():
            effect(name).apply(state, dict(fixed))
        # the compartments effect scales C10 of a compartment by (1 + c): du/dC10_muscle gets that factor
        for name in self.law_parameters:
            state.sensitivity[name] = [(line, f * state.c10_factor.get(line, 1.0)) for line, f in state.sensitivity[name]]
        if self.groups:
            split_into_groups(state)
        return state

    def deck(self, theta: Sequence[float], tension_N_per_mm: float | None = None,
             extra_sensitivities: Sequence[str] = (), sensitivities: bool = True, own_sensitivities: bool = True,
             release_static: Sequence[float] | None = None) -> str:
        """The deck of theta; extra_sensitivities: more `*SENSITIVITY` lines (a `PROFILE` line defines the garment's
        Fourier profile, at zero, when the model has none; a `GAP PROFILE` line the band's `*GAP PROFILE` of the
        skin, at zero); sensitivities=False: none at all (a finite-difference probe needs the displacements alone);
        own_sensitivities=False: the extra lines alone, not theta's; release_static: the band's release increments
        (`decks.leg_garment_deck`; default: the fit's, RELEASE_STATIC or FRICTION_RELEASE_STATIC)."""
        from ..engine.decks import StepEffects

        state = self.deck_state(theta)
        tension = self.tension_N_per_mm if tension_N_per_mm is None else tension_N_per_mm
        # each parameter of theta is one engine parameter, its lines weighted (`sensitivity_map`)
        own = (tuple((name, tuple(terms)) for name, terms in self._engine_terms(state).items() if terms)
               if self.engine_sensitivities and own_sensitivities and sensitivities else ())
        lines = (list(dict.fromkeys(line for line in extra_sensitivities if self.engine_differentiates(line)))
                 if sensitivities else [])
        if any(line.startswith("PROFILE") for line in extra_sensitivities) and not self.tension_profile:
            state.fourier_profile.setdefault(1, (0.0, 0.0))
        effects = StepEffects(tuple(state.volume_changes.items()), state.axial_stretch,
                              tuple((n, *m) for n, m in state.rigid_motions.items()),
                              tuple((k, a, b) for k, (a, b) in sorted(state.fourier_profile.items())),
                              tuple(lines), own, state.reference_share, tuple(state.band_volume_changes.items()))
        stiffening = "stiffening" in self._all_effects   # C20 written, even at 0
        materials = {elset: deck_material(state.laws[elset], c, stiffening) for elset, c in state.constants.items()}
        if self.band is not None:
            band = self.band if tension == self.tension_N_per_mm else self.band.at_tension(tension)
            mu = self.friction_at(theta)
            gap = () if any(line.startswith("GAP PROFILE") for line in extra_sensitivities) else None
            return leg_garment_deck(materials, band, self.mesh, friction_mu=mu, effects=effects, gap_profile=gap,
                                    release_static=release_static,
                                    description=f"theta = {list(map(float, theta))}, T = {tension:.6g} N/mm, "
                                                f"mu = {mu:g}")
        return leg_laplace_deck(materials, tension, tension_profile=self.tension_profile, effects=effects,
                                description=f"theta = {list(map(float, theta))}, T = {tension:.6g} N/mm")

    def friction_at(self, theta: Sequence[float]) -> float:
        """The band's friction coefficient at theta: fitted (the friction effect's mu) or fixed."""
        return float(theta[self.space.names.index("mu")]) if "friction" in self.effects else self.friction_mu

    def _engine_terms(self, state) -> dict[str, list[tuple[str, float]] | None]:
        """Parameter name -> its `*SENSITIVITY` lines and their weights (du/dtheta_j = sum weight x du/d(line)), or
        None where the engine does not differentiate every line on this model (the parameter is differenced)."""
        out = {}
        for name in self.space.names:
            terms = state.sensitivity.get(name)
            out[name] = (None if terms is None or not all(self.engine_differentiates(line) for line, _ in terms)
                         else list(terms))
        return out

    def sensitivity_map(self, theta: Sequence[float]) -> dict[str, list[tuple[str, float]] | None]:
        """Parameter name -> (engine sensitivity name, factor) pairs: du/dtheta_j = sum factor * du/d(name); None
        for a parameter whose sensitivity the engine does not give on this model (differenced instead). The deck
        asks for each parameter as one `*SENSITIVITY, NAME=<parameter>` block of its weighted lines (`deck`)."""
        return {name: None if terms is None else [(name, 1.0)] if terms else []
                for name, terms in self._engine_terms(self.deck_state(theta)).items()}


def annulus_mesh(inner_radius_mm: float = 10.0, outer_radius_mm: float = 40.0, rings: int = 6,
                 sectors: int = 36) -> Mesh:
    """A structured T3 mesh of an annulus centred at the origin; node set BONES = the inner circle,
    `skin_faces` (surface SKIN) = the outer circle. Elements are counter-clockwise in (x, y)."""
    radii = np.linspace(inner_radius_mm, outer_radius_mm, rings + 1)
    angles = np.linspace(0.0, 2 * np.pi, sectors, endpoint=False)
    nodes = np.array([(r * np.cos(a), r * np.sin(a)) for r in radii for a in angles])
    index = lambda ring, sector: ring * sectors + sector % sectors  # noqa: E731
    elements, outer = [], []
    for ring in range(rings):
        for sector in range(sectors):
            a, b = index(ring, sector), index(ring, sector + 1)
            c, d = index(ring + 1, sector + 1), index(ring + 1, sector)
            elements.append((a, d, c))
            if ring == rings - 1:
                outer.append((len(elements) - 1, 2))   # face 2 of (a, d, c) joins d to c: the outer circle
            elements.append((a, c, b))
    elements = np.array(elements, dtype=np.int64)
    inner = np.arange(sectors)
    return Mesh(nodes, elements, np.full(len(elements), 2), {"BONES": inner},
                np.array(outer, dtype=np.int64), np.arange(rings * sectors, (rings + 1) * sectors))


@dataclass
class DiskModel:
    """The disk under radial load of Bouten and Drapier (sec. 3.4): law ELASTIC (theta = E in kPa,
    nu fixed) or MOONEY-RIVLIN (theta = C10, C01 in kPa, D1 fixed), outer pressure in kPa."""

    law: str
    pressure_kPa: float | None = None   # default: 3 kPa (ELASTIC, strains ~2 %, far from the St Venant-Kirchhoff
                                        # limit point in compression) or 8 kPa (MOONEY-RIVLIN, finite strains ~10 %)
    poisson: float = 0.3
    d1_per_MPa: float = 20.0
    mesh: Mesh = field(default_factory=annulus_mesh)

    def __post_init__(self):
        if self.law not in ("ELASTIC", "MOONEY-RIVLIN"):
            raise ValueError(f"disk law must be ELASTIC or MOONEY-RIVLIN, not {self.law!r}")
        if self.pressure_kPa is None:
            self.pressure_kPa = 3.0 if self.law == "ELASTIC" else 8.0
        names = ("E",) if self.law == "ELASTIC" else ("C10", "C01")
        lower, upper = ((5.0,), (500.0,)) if self.law == "ELASTIC" else ((1.0, 1.0), (100.0, 100.0))
        self.space = ParameterSpace(names, lower, upper)
        self.mesh_text = self.mesh.include_text()
        self.mesh_sha = text_sha256(self.mesh_text)

    def deck(self, theta: Sequence[float]) -> str:
        values = [float(v) / KPA_PER_MPA for v in theta]
        constants = (values[0], self.poisson) if self.law == "ELASTIC" else (values[0], values[1], self.d1_per_MPa)
        faces = [(int(e) + 1, int(k)) for e, k in self.mesh.skin_faces]
        return disk_deck(self.law, constants, self.pressure_kPa / KPA_PER_MPA, faces,
                         description=f"theta (kPa) = {list(map(float, theta))}")


