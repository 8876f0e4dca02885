"""Input decks for calfit-fe, rendered from the jinja2 templates in `templates/` (StrictUndefined:
a variable the caller forgets is an error, never an empty string in a deck).

Three templates are in use: `leg_laplace.inp.j2`, the leg slice of the first paper (Avril et al.):
clamped bones (sec. 2.2.2), the compressible neo-Hookean law W = C10 (I1bar - 3) + Kv [(J^2 - 1)/2
- ln J] per tissue (eq. 2, keyword `*HYPERELASTIC, AVRIL`) and the garment pressure p = T / r of
the Laplace law on the skin (eq. 1, `*LAPLACE PRESSURE`), with the `tension_profile` effect as a
template variable; `disk.inp.j2`, the disk under radial load of the second paper (Bouten and
Drapier, sec. 3.4), an annulus clamped inside and pressed outside, linear elastic (`*ELASTIC`)
or Mooney-Rivlin; and `leg_garment.inp.j2`, the leg slice under the explicit garment band of the
second paper (Fig. 2), put on in four steps (`leg_garment_deck`). The mesh is not in the deck: it
is `*INCLUDE`d from `mesh.inp` beside it, so that one mesh serves thousands of decks. A deck's identity (cache key) is the SHA-256 of its
text and of the mesh it includes (`deck_key`).
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import jinja2

from ..core.errors import DeckError

TEMPLATE_DIR_ENV = "CALFIT_TEMPLATES"
MESH_INCLUDE_NAME = "mesh.inp"
ONE_INCREMENT = (1.0, 1.0, 1e-4, 1.0)  # initial dt, period, min dt, max dt: cut back only when needed


def template_dir() -> Path:
    """The folder of the *.inp.j2 templates: $CALFIT_TEMPLATES, else `templates/` of the
    checkout (editable installs), else the copy CMake installs in the package (wheels)."""
    override = os.environ.get(TEMPLATE_DIR_ENV)
    if override:
        candidates = [Path(override)]
    else:
        package = Path(__file__).resolve().parents[1]   # orchestrator/
        candidates = [package.parent / "templates", package / "templates"]
    for folder in candidates:
        if folder.is_dir():
            return folder
    raise DeckError(
        f"deck templates not found in {candidates[0]}; set {TEMPLATE_DIR_ENV} to the calfit templates/ folder"
    )


def _environment() -> jinja2.Environment:
    return _environment_for(template_dir())


@functools.lru_cache(maxsize=4)
def _environment_for(folder: Path) -> jinja2.Environment:
    """One environment per template folder: jinja2 then compiles each template once."""
    return jinja2.Environment(loader=jinja2.FileSystemLoader(str(folder)), undefined=jinja2.StrictUndefined,
                              keep_trailing_newline=True, autoescape=False)


def render(template_name: str, **variables) -> str:
    """Render one template; an undefined variable raises DeckError naming the template."""
    try:
        return _environment().get_template(template_name).render(**variables)
    except jinja2.UndefinedError as error:
        raise DeckError(f"template {template_name}: {error}; pass it to decks.render") from None
    except jinja2.TemplateNotFound:
        raise DeckError(f"template {template_name} is not in {template_dir()}") from None


def numbers(values: Iterable[float]) -> str:
    """A data line of numbers with 10 significant digits."""
    return ", ".join(f"{float(v):.10g}" for v in values)


def _positive(name: str, values: Sequence[float]) -> None:
    for value in values:
        if not float(value) > 0.0:
            raise DeckError(f"{name} must be positive, got {value!r}")


def _material_rows(materials: Mapping[str, tuple[str, Sequence[float]]]) -> list[dict]:
    """The template rows of the tissues' materials, checked where a law's sign is known: the leading constant
    (C10) positive, AVRIL's Kv positive and its C20 >= 0 (solver_cpp/README.md); other constants as the engine
    checks them (a Mooney-Rivlin C20 may be negative, D1 = 0 is incompressible)."""
    rows = []
    for elset, (law, constants) in materials.items():
        _positive(f"C10 of {elset}", constants[:1])
        if law == "AVRIL":
            _positive(f"Kv of {elset}", constants[1:2])
            if any(float(c) < 0.0 for c in constants[2:]):
                raise DeckError(f"the higher-order constants of {elset} must be >= 0, got {list(constants[2:])}")
        rows.append({"name": elset, "elset": elset, "law": law, "constants": numbers(constants)})
    return rows


@dataclass(frozen=True)
class StepEffects:
    """The effect catalog's step keywords of a leg deck (solver_cpp/README.md, project keywords); the
    defaults leave the baseline model of Avril et al. unchanged.

    volume_changes: (element set, relative volume change dv of its stress-free state) pairs, `*VOLUME CHANGE`;
    axial_stretch: lambda_z of generalized plane strain, `*AXIAL STRETCH` (None: plane strain, lambda_z = 1);
    rigid_motions: (node set, u_x mm, u_y mm, angle degrees), `*RIGID MOTION` of a bone;
    fourier_profile: (k, a_k, b_k) of the garment tension factor 1 + sum a_k cos k theta + b_k sin k theta
    (`*TENSION PROFILE, TYPE=FOURIER`);
    sensitivities: data lines of `*SENSITIVITY` (du/dtheta of the converged state, engine-computed);
    combined_sensitivities: (name, ((data line, weight), ...)) of `*SENSITIVITY, NAME=name` blocks, each one parameter
    t moving every line's parameter by weight x t (a fitted constant shared by several material groups: one column
    of the engine's, not one per group; through friction each column is carried along the put-on);
    reference_share: alpha, the share of the garment's pressure taken from the curvature of the unloaded contour
    (`*LAPLACE PRESSURE, REFERENCE=alpha`; 0 is Laplace's law on the deformed contour);
    band_volume_changes: (band sector set, dv) pairs of the explicit band's natural state, `*VOLUME CHANGE` ramped in
    its second step, the band free and round under its pressure (a prestretch varying around the leg: the sector's
    natural length times (1 + dv)^(1/3)).
    """

    volume_changes: tuple[tuple[str, float], ...] = ()
    axial_stretch: float | None = None
    rigid_motions: tuple[tuple[str, float, float, float], ...] = ()
    fourier_profile: tuple[tuple[int, float, float], ...] = ()
    sensitivities: tuple[str, ...] = ()
    combined_sensitivities: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = ()
    reference_share: float = 0.0
    band_volume_changes: tuple[tuple[str, float], ...] = ()


def leg_laplace_deck(materials: Mapping[str, tuple[str, Sequence[float]]], tension_N_per_mm: float, *,
                     tension_profile: Sequence[tuple[float, float]] | None = None, effects: StepEffects = StepEffects(),
                     static: Sequence[float] = ONE_INCREMENT, max_increments: int = 50, description: str = "") -> str:
    """The leg slice under the Laplace-law garment (Avril et al. eqs. 1-2).

    materials: element set -> (*HYPERELASTIC option, constants in MPa), e.g. {"FAT": ("AVRIL", (C10, Kv))}
    (`materials.deck_material`); a third AVRIL constant is C20 (>= 0, the `stiffening` effect).
    tension_profile: (angle in degrees, factor) pairs of a tabulated tension; None = constant T.
    effects: the step keywords of the effect catalog (`orchestrator.model.effects`).
    """
    _positive("the garment tension", [tension_N_per_mm])
    if tension_profile and effects.fourier_profile:
        raise DeckError("give the garment tension profile either as a table or as Fourier coefficients, not both")
    rows = _material_rows(materials)
    _check_tissue_effects(effects)
    if not 0.0 <= float(effects.reference_share) <= 1.0:
        raise DeckError(f"the share of the pressure from the unloaded contour must lie in [0, 1], got "
                        f"{effects.reference_share!r}")
    profile = [(f"{a:.10g}", f"{f:.10g}") for a, f in tension_profile] if tension_profile else []
    return render("leg_laplace.inp.j2", description=description, mesh_include=MESH_INCLUDE_NAME, materials=rows,
                  tension=f"{tension_N_per_mm:.10g}", tension_profile=profile,
                  fourier_profile=[(int(k), numbers((a, b))) for k, a, b in effects.fourier_profile],
                  **_tissue_effect_lines(effects), static=numbers(static), max_increments=max_increments,
                  reference_share=f"{float(effects.reference_share):.10g}" if effects.reference_share else None)


def _check_tissue_effects(effects: StepEffects) -> None:
    if effects.axial_stretch is not None:
        _positive("the axial stretch", [effects.axial_stretch])
    _check_volume_changes(effects.volume_changes)


def _check_volume_changes(volume_changes) -> None:
    for elset, dv in volume_changes:
        if not float(dv) > -1.0:
            raise DeckError(f"the volume change of {elset} must be > -1 (a relative change), got {dv!r}")


def _tissue_effect_lines(effects: StepEffects) -> dict:
    """The template variables of the step keywords that act on the tissues and bones, and of *SENSITIVITY."""
    return dict(volume_changes=[(elset, f"{float(dv):.10g}") for elset, dv in effects.volume_changes],
                axial_stretch=None if effects.axial_stretch is None else f"{float(effects.axial_stretch):.10g}",
                rigid_motions=[(nset, numbers((ux, uy, angle))) for nset, ux, uy, angle in effects.rigid_motions],
                sensitivities=list(effects.sensitivities),
                combined_sensitivities=[(name, [(line, f"{float(weight):.17g}") for line, weight in lines])
                                        for name, lines in effects.combined_sensitivities])


def disk_deck(law: str, constants: Sequence[float], pressure_MPa: float, outer_faces: Sequence[tuple[int, int]], *,
              static: Sequence[float] = (0.5, 1.0, 1e-4, 0.5), max_increments: int = 50, description: str = "") -> str:
    """The disk under radial load (Bouten and Drapier sec. 3.4). law: "ELASTIC" (constants E, nu) or a
    *HYPERELASTIC option such as "MOONEY-RIVLIN" (C10, C01, D1); outer_faces: 1-based (element, face)."""
    if law == "ELASTIC":
        _positive("Young's modulus", constants[:1])
    else:
        _positive(f"the {law} constants", [c for c in constants if c != 0.0])
    return render("disk.inp.j2", description=description, mesh_include=MESH_INCLUDE_NAME,
                  material={"law": law, "constants": numbers(constants)}, pressure=f"{pressure_MPa:.10g}",
                  outer_faces=list(outer_faces), static=numbers(static), max_increments=max_increments)


# The band closes onto the skin in increments of a fifth of the release, which a free stretch may grow; a
# tenth took 37 Newton iterations on the 5k-DOF leg against 32 (leg of benchmarks/engine.py --only garment).
RELEASE_STATIC = (0.2, 1.0, 1e-5, 1.0)
# With friction the put-on depends on its path, and the release's increments are part of the model: on the second
# paper's model (2,000 CPE6H, mu = 0.3) a release in fifths put the leg 15 um RMS (92 um at most) from one in
# fortieths, a release in twentieths 2.9 um (20 um); and where a fifth failed and was cut back to twentieths
# (C10 of muscle 0.885 kPa against 0.88), the state jumped by 90 um and the misfit by 20 %, a step in the fit's
# landscape where Levenberg-Marquardt stalled. A fixed grid of twentieths takes every theta along the same
# increments (no cut-back on that model) at 1.5 times the run time.
FRICTION_RELEASE_STATIC = (0.05, 1.0, 1e-5, 0.05)
INFLATE_STATIC = ONE_INCREMENT  # every band node prescribed: nothing to increment
LET_GO_STATIC = ONE_INCREMENT  # a released *BOUNDARY is not ramped; the band is near equilibrium already
SETTLE_STATIC = ONE_INCREMENT  # likewise: the released pins carried a few % of the band tension
GARMENT_STEPS = {"inflated": 2, "released": 4}  # step numbers of leg_garment.inp.j2's states (Fig. 2 b, c)
# Penalty K: p / K = 0.027 mm overclosure at 20 mmHg, 2-3 times the tissue's stiffness per mm (E / h, E = 6 C10 of
# 30-70 kPa, h = 1 mm). Measured on the 5k-DOF leg of benchmarks/engine.py (frictionless release): K = 1, 0.3, 0.1,
# 0.03 MPa/mm took 126, 54, 44, 40 Newton iterations in all, and moved the tissue by 0, 0.19, 0.68, 2.0 % of its
# largest displacement (1.2 mm) from K = 1: the error falls as 1/K (about 0.075 % at K = 1), and 0.68 % (8 um) is
# a tenth of an MRI pixel's noise. The stick slope follows K (tangential and normal penalties alike: with 1.0,
# friction took 154 iterations against 51).
GARMENT_PENALTY_MPA_PER_MM = 0.1
GARMENT_STICK_SLOPE_MPA_PER_MM = 0.1


def leg_garment_deck(materials: Mapping[str, tuple[str, Sequence[float]]], band, leg, *, friction_mu: float = 0.0,
                     penalty: float = GARMENT_PENALTY_MPA_PER_MM, stick_slope: float = GARMENT_STICK_SLOPE_MPA_PER_MM,
                     inflate_static: Sequence[float] = INFLATE_STATIC, let_go_static: Sequence[float] = LET_GO_STATIC,
                     release_static: Sequence[float] | None = None, max_increments: int = 200,
                     effects: StepEffects = StepEffects(), gap_profile: Sequence[tuple[int, float, float]] | None = None,
                     description: str = "") -> str:
    """The leg slice under the explicit garment band of the second paper (Bouten and Drapier sec. 2.5,
    Fig. 2), `orchestrator.meshing.garment_band(leg)`, put on in four steps (module docstring of
    orchestrator.meshing.garment): 1, every band node drawn onto the inflated circle, the holding
    pressure ramped up; 2, the band let go, held round by the pressure and three pins; 3, the
    skin/band contact added (penalty `penalty`, Coulomb friction `friction_mu` with stick slope
    `stick_slope`, 0 = frictionless) and the pressure released; 4, the two pins that the wrapped band
    makes statically indeterminate released (step 3 in increments of release_static: RELEASE_STATIC, or
    FRICTION_RELEASE_STATIC with friction). GARMENT_STEPS names the steps of the inflated and the
    released states. materials: tissue element set -> (law, constants in MPa), as leg_laplace_deck.
    effects: the effect catalog's keywords on the tissues and bones (volume changes, axial stretch, rigid motions)
    act in step 4, once the band is on (`orchestrator.model.effects`), and its *SENSITIVITY lines; a tension profile or
    the unloaded curvature belong to Laplace's law and are refused. gap_profile: (k, a_k, b_k) of the skin's offset
    as the band feels it (`*GAP PROFILE`, mm; () writes the keyword at zero, for its `GAP PROFILE` sensitivities).
    The mesh include (mesh.inp) is `band.include_text(leg)`."""
    _positive("the penalty slope and stick slope", [penalty, stick_slope])
    if friction_mu < 0.0:
        raise DeckError(f"the friction coefficient must be >= 0, got {friction_mu!r}")
    if effects.fourier_profile or effects.reference_share:
        raise DeckError("a garment tension profile and the unloaded curvature are Laplace's law's (p = T / r): the "
                        "explicit band carries neither")
    _check_tissue_effects(effects)
    _check_volume_changes(effects.band_volume_changes)
    rows = _material_rows(materials)
    if release_static is None:
        release_static = FRICTION_RELEASE_STATIC if friction_mu > 0.0 else RELEASE_STATIC
    return render("leg_garment.inp.j2", description=description, mesh_include=MESH_INCLUDE_NAME, materials=rows,
                  band_constants=numbers((band.C10, band.D1)), penalty=f"{penalty:.10g}",
                  friction_mu=float(friction_mu), stick_slope=f"{stick_slope:.10g}",
                  inflation_pressure=f"{band.inflation_pressure_MPa:.10g}", inflate_faces=band.deck_inner_faces(leg),
                  inflate_displacements=band.deck_inflation_displacements(leg), pins=band.deck_pins(leg),
                  sliding_pins=band.deck_pins(leg, ("GARMENT_PIN_Y",)), inflate_static=numbers(inflate_static),
                  let_go_static=numbers(let_go_static), settle_static=numbers(SETTLE_STATIC),
                  release_static=numbers(release_static), max_increments=max_increments,
                  band_volume_changes=[(elset, f"{float(dv):.10g}") for elset, dv in effects.band_volume_changes],
                  gap_profile=None if gap_profile is None else [(int(k), float(a), float(b)) for k, a, b in gap_profile],
                  **_tissue_effect_lines(effects))


def sensitivity_blocks(deck_text: str) -> list[tuple[str | None, list[str]]]:
    """The `*SENSITIVITY` blocks of a deck, in order: the NAME= of a combined block (None for a plain one) and its
    data lines as written (a combined block's with their weights), comment and blank lines left out."""
    blocks: list[tuple[str | None, list[str]]] = []
    lines = None   # the data lines of the block being read, None outside *SENSITIVITY
    for line in deck_text.splitlines():
        if line.startswith("**") or not line.strip():
            continue
        if not line.startswith("*"):
            if lines is not None:
                lines.append(line.strip())
            continue
        keyword, *options = (part.strip() for part in line.split(","))
        lines = None
        if keyword.upper() == "*SENSITIVITY":
            name = next((option.split("=", 1)[1].strip() for option in options
                         if option.upper().startswith("NAME=")), None)
            lines = []
            blocks.append((name, lines))
    return blocks


def text_sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def deck_key(deck_text: str, mesh_sha: str, outputs_fingerprint: str = "") -> str:
    """Cache key of an evaluation: the deck, the mesh it includes and what is extracted from the results."""
    return text_sha256("\n".join((deck_text, mesh_sha, outputs_fingerprint)))[:32]
