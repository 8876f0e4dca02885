"""The effect catalog (docs/design.md, "The effect catalog"): named, switchable pieces of physics, off in the
baseline model of Avril et al., each with its parameters, its physical reading, its realization in the
deck (`decks.StepEffects` and the materials) and the `*SENSITIVITY` lines that give the engine's
du/d(parameter) at the current point (at zero when the effect is off: what the score test needs).

An effect's parameters are additive (`linear`): zero is "effect off", negative values may be physical
(a shrink, a displacement), so the optimizers move them by steps of `scale` rather than in ln theta.

| effect          | parameters                      | engine keyword                      |
|-----------------|---------------------------------|-------------------------------------|
| compartments    | dC10 of each compartment but 1st| one *MATERIAL per COMPARTMENTk      |
| drainage        | dv_muscle                       | *VOLUME CHANGE, ELSET=<muscle>      |
| friction        | mu                              | explicit garment (*FRICTION)        |
| bridging        | (switch)                        | explicit garment (*CONTACT PAIR)    |
| tension_profile | a1, b1, a2, b2                  | *TENSION PROFILE, TYPE=FOURIER      |
| bone_motion     | ux_BONE2, uy_BONE2              | *RIGID MOTION, NSET=BONE2           |
| stiffening      | C20_fat, C20_muscle             | *HYPERELASTIC, AVRIL third constant |
| out_of_plane    | eps_z                           | *AXIAL STRETCH                      |
| heterogeneity   | h_<mode>_<fat, muscle>          | one *MATERIAL per group             |
| unloaded_curvature | alpha_unloaded               | *LAPLACE PRESSURE, REFERENCE=alpha  |
| band_profile    | band_a1, band_b1                | *VOLUME CHANGE of the band's sectors|

Beyond the catalog, four effects act on the material groups of `orchestrator.model.heterogeneity` (every tissue cut
by sector and depth, one material each): `patch:<groups>` (dlnE_patch: every modulus of the law, C10 and
Kv alike, times exp(dlnE_patch) in those groups, the local stiffness change the diagnosis proposes where the
catalog explains nothing), `cut:<fat|muscle>:<normal deg>:<offset mm>` (dlnE_cut: the same beyond a straight line,
the groups it crosses split on their elements' centroids: a compartment whose septum the images do not show),
`region:<fat|muscle>:<start deg>:<end deg>` (dlnE: the same in an angular sector, cut on any mesh: how a phantom
with a stiff patch is made) and `local` (dlnE_<group> of every group: the diagnosis' probe of where a stiffness
change would reduce the residual).

Which garment model carries an effect (`Effect.garments`). `friction` and `bridging` are not in the Laplace-law
deck: they need the explicit garment band (`templates/leg_garment.inp.j2`, penalty contact, friction). The
diagnosis of a Laplace-law model ranks them with the band's runs (`diagnose.garment_model`). The
explicit band's deck carries every effect of the tissues and bones (compartments, drainage, bone_motion,
stiffening, out_of_plane, heterogeneity, and the group effects), written into its last step, once the band is on
the leg: the fluid leaves, the fibula moves and the slice lengthens under the garment, as they do in a real calf.
It carries `friction` (its coefficient mu) too. `tension_profile` and `unloaded_curvature` change Laplace's law
itself, and `bridging` is what the band does: none of the three has a meaning on the band. `band_profile` is the
band's own: a prestretch that varies around the leg, the band's natural length per 15-degree sector changed in its
second step (free and round, before it closes on the leg); with friction it makes the hoop force vary around the leg
(a frictionless band slides until its force is the same all round, so there it is refused).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..core.errors import EffectError
from ..core.materials import engine_constant
from ..core.units import KPA_PER_MPA
from ..meshing.mesh import compartment_sets, muscle_sets
from .heterogeneity import (
    CUT_PREFIX,
    FAT_MODES,
    KINDS,
    MODES,
    PATCH_PREFIX,
    REGION_PREFIX,
    is_group,
    parse_cut,
    parse_region,
    patch_groups,
)

SECOND_BONE = "BONE2"
PROFILE_NAME = "GARMENT"
SKIN_SURFACE = "SKIN"


@dataclass(frozen=True)
class EffectParameter:
    """One additive parameter of an effect; 0 is the effect switched off."""

    name: str
    unit: str
    lower: float
    upper: float
    scale: float   # a typical size: the optimizers' unit step and the finite-difference scale
    meaning: str


@dataclass
class LegDeckState:
    """What the parameters of a leg model set in its deck: material constants (MPa) per element set and the
    step keywords of `decks.StepEffects`; effects edit it in turn. `sensitivity` maps each parameter name to
    the engine's *SENSITIVITY lines and the factor of each, d(engine value)/d(parameter), whose weighted sum
    is du/d(parameter)."""

    constants: dict[str, dict[str, float]]   # element set -> its law's constants in MPa ("C10", "Kv", "C20", ...)
    laws: dict = field(default_factory=dict)  # element set -> materials.TissueLaw
    volume_changes: dict[str, float] = field(default_factory=dict)
    axial_stretch: float | None = None
    rigid_motions: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    fourier_profile: dict[int, tuple[float, float]] = field(default_factory=dict)
    reference_share: float = 0.0   # the share of the garment's pressure taken from the unloaded contour
    band_sectors: dict[str, float] = field(default_factory=dict)         # band sector set -> its middle angle (rad)
    band_volume_changes: dict[str, float] = field(default_factory=dict)  # band sector set -> dv of its natural state
    sensitivity: dict[str, list[tuple[str, float]]] = field(default_factory=dict)
    c10_factor: dict[str, float] = field(default_factory=dict)   # sensitivity line -> C10 / C10_muscle (compartments)
    groups: list = field(default_factory=list)                   # heterogeneity.Group of the model, [] if none
    stiffness_log_factor: dict[str, float] = field(default_factory=dict)   # group -> ln(modulus_group / modulus_tissue)
    group_sensitivity: dict[str, list[tuple[str, float]]] = field(default_factory=dict)  # parameter -> (group, dln(factor)/dp)


@dataclass(frozen=True)
class Effect:
    name: str
    adds: str          # what it adds, one line (docs/method/diagnosis.md table)
    physics: str       # why it may be missing in a real calf, and what it does to the residual
    parameter_list: Callable[[Sequence[str], Sequence[str]], tuple[EffectParameter, ...]]
    apply: Callable[[LegDeckState, dict[str, float]], None] | None
    garments: tuple[str, ...] = ("laplace", "explicit")   # the garment models whose deck carries it (module text)
    requirement: Callable[[Sequence[str], Sequence[str]], str | None] = lambda element_sets, node_sets: None

    def parameters(self, element_sets: Sequence[str], node_sets: Sequence[str],
                   garment: str = "laplace") -> tuple[EffectParameter, ...]:
        """The effect's parameters on a mesh with these sets under this garment model; EffectError when the model
        cannot carry it."""
        reason = self.unavailable(element_sets, node_sets, garment)
        if reason:
            raise EffectError(f"effect {self.name!r} is not available on this model: {reason}")
        return self.parameter_list(element_sets, node_sets)

    def unavailable(self, element_sets: Sequence[str], node_sets: Sequence[str], garment: str = "laplace") -> str | None:
        if garment not in self.garments:
            if garment == "laplace":
                return "it needs the explicit garment band (templates/leg_garment.inp.j2), not the Laplace-law model"
            if self.name == "bridging":
                return "the explicit band bridges the skin's concave parts already"
            return "it changes Laplace's law (p = T / r), which the explicit band does not use"
        return self.requirement(element_sets, node_sets)


# --- the realizations -------------------------------------------------------------------------------

def _add_sensitivity(state: LegDeckState, parameter: str, line: str, factor: float) -> None:
    state.sensitivity.setdefault(parameter, []).append((line, factor))


def _compartment_parameters(element_sets, node_sets):
    """One relative change per compartment but the first, whose C10 stays the muscle's C10_muscle (a change in
    every compartment would duplicate C10_muscle and leave the fit without a unique optimum)."""
    return tuple(EffectParameter(f"dC10_{name}", "1", -0.8, 4.0, 0.5,
                                 f"relative change of the muscle C10 in {name}") for name in compartment_sets(element_sets)[1:])


def _apply_compartments(state: LegDeckState, values: dict[str, float]) -> None:
    for name, change in values.items():
        elset = name[len("dC10_"):]
        base = state.constants[elset]["C10"]
        state.constants[elset]["C10"] = base * (1.0 + change)
        _add_sensitivity(state, name, f"MATERIAL, {elset}, C10", base)
        state.c10_factor[f"MATERIAL, {elset}, C10"] = 1.0 + change


def _apply_drainage(state: LegDeckState, values: dict[str, float]) -> None:
    for elset in muscle_sets(list(state.constants)):
        state.volume_changes[elset] = values["dv_muscle"]
        _add_sensitivity(state, "dv_muscle", f"VOLUME CHANGE, {elset}", 1.0)


TENSION_HARMONICS = (1, 2)


def _apply_tension_profile(state: LegDeckState, values: dict[str, float]) -> None:
    # a harmonic a phantom's hidden profile leaves out is at zero
    for k in TENSION_HARMONICS:
        state.fourier_profile[k] = (values.get(f"a{k}", 0.0), values.get(f"b{k}", 0.0))
        for name in (f"a{k}", f"b{k}"):
            _add_sensitivity(state, name, f"PROFILE, {PROFILE_NAME}, {name.upper()}", 1.0)


def _apply_band_profile(state: LegDeckState, values: dict[str, float]) -> None:
    # the band's natural length in a sector at angle phi times 1 + e(phi), e = a1 cos phi + b1 sin phi: an isotropic
    # volume change dv = (1 + e)^3 - 1 of its natural state (the engine's growth g = (1 + dv)^(1/3) = 1 + e)
    a1, b1 = values["band_a1"], values["band_b1"]
    for sector, phi in state.band_sectors.items():
        stretch = 1.0 + a1 * np.cos(phi) + b1 * np.sin(phi)
        state.band_volume_changes[sector] = stretch ** 3 - 1.0
        _add_sensitivity(state, "band_a1", f"VOLUME CHANGE, {sector}", 3.0 * stretch ** 2 * np.cos(phi))
        _add_sensitivity(state, "band_b1", f"VOLUME CHANGE, {sector}", 3.0 * stretch ** 2 * np.sin(phi))


def _apply_unloaded_curvature(state: LegDeckState, values: dict[str, float]) -> None:
    state.reference_share = values["alpha_unloaded"]
    _add_sensitivity(state, "alpha_unloaded", f"REFERENCE, {SKIN_SURFACE}", 1.0)


def _apply_bone_motion(state: LegDeckState, values: dict[str, float]) -> None:
    state.rigid_motions[SECOND_BONE] = (values["ux_BONE2"], values["uy_BONE2"], 0.0)
    _add_sensitivity(state, "ux_BONE2", f"RIGID MOTION, {SECOND_BONE}, UX", 1.0)
    _add_sensitivity(state, "uy_BONE2", f"RIGID MOTION, {SECOND_BONE}, UY", 1.0)


def _apply_stiffening(state: LegDeckState, values: dict[str, float]) -> None:
    for elset, constants in state.constants.items():
        name = "C20_fat" if elset == "FAT" else "C20_muscle"
        constants["C20"] = values[name] / KPA_PER_MPA
        _add_sensitivity(state, name, f"MATERIAL, {elset}, C20", 1.0 / KPA_PER_MPA)


def _apply_out_of_plane(state: LegDeckState, values: dict[str, float]) -> None:
    state.axial_stretch = 1.0 + values["eps_z"]
    _add_sensitivity(state, "eps_z", "AXIAL STRETCH", 1.0)


HETEROGENEITY_BOUND = 1.5   # |c_m| <= 1.5: stiffness within a factor e^1.5 = 4.5 of the tissue's across the leg


def _heterogeneity_parameters(element_sets, node_sets):
    return tuple(EffectParameter(f"h_{mode}_{kind}", "1", -HETEROGENEITY_BOUND, HETEROGENEITY_BOUND, 0.25,
                                 f"{mode} mode of the ln stiffness in the {kind}")
                 for kind in KINDS for mode in (FAT_MODES if kind == "fat" else MODES))


def _add_log_factor(state: LegDeckState, parameter: str, group: str, weight: float, value: float) -> None:
    state.stiffness_log_factor[group] = state.stiffness_log_factor.get(group, 0.0) + weight * value
    state.group_sensitivity.setdefault(parameter, []).append((group, weight))


def _apply_heterogeneity(state: LegDeckState, values: dict[str, float]) -> None:
    for name, value in values.items():
        _, mode, kind = name.split("_")
        for group in state.groups:
            if group.kind == kind:
                _add_log_factor(state, name, group.name, group.mode(mode), value)


def _needs_groups(element_sets, node_sets):
    return None if any(is_group(name) for name in element_sets) else "the model has no material groups"


def _apply_local(state: LegDeckState, values: dict[str, float]) -> None:
    for name, value in values.items():
        _add_log_factor(state, name, name[len("dlnE_"):], 1.0, value)


def patch_effect(name: str) -> Effect:
    """Every modulus times exp(dlnE_patch) in the groups of `name` (patch:G1+G2+...)."""
    members = set(patch_groups(name))

    def apply(state: LegDeckState, values: dict[str, float]) -> None:
        for group in state.groups:   # a group that a cut split is in the patch with both of its parts
            if group.mesh_group in members:
                _add_log_factor(state, "dlnE_patch", group.name, 1.0, values["dlnE_patch"])

    def requirement(element_sets, node_sets):
        missing = sorted(m for m in members if not any(s == m or s.startswith(m + "C") for s in element_sets))
        return f"the model has no material group {', '.join(missing)}" if missing else None

    return Effect(name, "stiffness change in a patch of material groups",
                  "A region of one tissue stiffer or softer than the rest (scar, oedema, a muscle unlike its neighbours).",
                  _fixed(EffectParameter("dlnE_patch", "1", -2.5, 2.5, 0.25, "ln of the patch's stiffness ratio")),
                  apply, requirement=requirement)


def region_effect(name: str) -> Effect:
    """Every modulus times exp(dlnE) in an angular sector of one tissue (`heterogeneity.region_groups`)."""
    try:
        parse_region(name)
    except ValueError as error:
        raise EffectError(str(error)) from None

    def apply(state: LegDeckState, values: dict[str, float]) -> None:
        for group in state.groups:
            if group.region == name:
                _add_log_factor(state, "dlnE", group.name, 1.0, values["dlnE"])

    return Effect(name, "stiffness change in an angular sector of one tissue",
                  "A stiff or soft patch of tissue, wherever the mesh's elements lie (phantoms with physics outside the catalog).",
                  _fixed(EffectParameter("dlnE", "1", -2.5, 2.5, 0.25, "ln of the region's stiffness ratio")), apply,
                  requirement=_needs_groups)


CUT_PARAMETER = "dlnE_cut"   # one cut per model (`heterogeneity.groups_for`)


def cut_effect(name: str) -> Effect:
    """Every modulus times exp(dlnE_cut) in the part of a tissue beyond a straight line (`heterogeneity.Cut`):
    the groups the line crosses are split on their elements' centroids (`heterogeneity.mesh_groups`)."""
    try:
        parse_cut(name)
    except ValueError as error:
        raise EffectError(str(error)) from None

    def apply(state: LegDeckState, values: dict[str, float]) -> None:
        for group in state.groups:
            if name in group.cuts:
                _add_log_factor(state, CUT_PARAMETER, group.name, 1.0, values[CUT_PARAMETER])

    return Effect(name, "stiffness change beyond a straight boundary in one tissue",
                  "A compartment bounded by a septum the images do not show (the interosseous membrane, an "
                  "intermuscular septum thinner than the slice): a stiffness step along a line.",
                  _fixed(EffectParameter(CUT_PARAMETER, "1", -2.5, 2.5, 0.25, "ln of the stiffness ratio beyond the line")),
                  apply, requirement=_needs_groups)

def _modulus_lines(group: str, law, constants_MPa: dict[str, float], dln_factor: float) -> list[tuple[str, float]]:
    """The *SENSITIVITY lines of a group's moduli for a parameter p that multiplies all of them by exp(p): each
    modulus k moves by dk/dp = k dln_factor (kPa), through the deck's constant `materials.engine_constant` names."""
    lines = []
    for constant, value in constants_MPa.items():
        if value != 0.0:
            name, per_kPa = engine_constant(law, constant, constants_MPa)
            lines.append((f"MATERIAL, {group}, {name}", per_kPa * value * KPA_PER_MPA * dln_factor))
    return lines


def split_into_groups(state: LegDeckState) -> None:
    """Give every group its tissue's constants times exp(its log factor), and rewrite the sensitivity lines of a
    tissue's constants into the lines of its groups (dk_group/dk_tissue = the group's factor for every modulus k).

    The factor scales the whole strain energy, C10 and Kv alike, so that a stiffer or softer region keeps its
    tissue's Poisson ratio, nu = (3 Kv - 2 C10) / (6 Kv + 2 C10) at small strain (bulk modulus 2 Kv, shear 2 C10).
    A factor on C10 alone would make a region three times stiffer more compressible (the muscle's nu from 0.42 to
    0.29 at C10 x3 with Table 2's constants) and one over 9 auxetic: not tissue."""
    members: dict[str, list] = {}
    for group in state.groups:
        members.setdefault(group.tissue_set, []).append(group)
    group_tissue = {g.name: g.tissue_set for g in state.groups}
    factor = {g.name: float(np.exp(state.stiffness_log_factor.get(g.name, 0.0))) for g in state.groups}
    # every modulus (C10, C01, C20, C30 and Kv) times the factor: the strain energy scales, Poisson's ratio stays
    constants = {g.name: {k: v * factor[g.name] for k, v in state.constants[g.tissue_set].items()} for g in state.groups}
    material_line = re.compile(r"MATERIAL, (\S+), (\S+)$")
    for parameter, lines in state.sensitivity.items():
        rewritten = []
        for line, weight in lines:
            match = material_line.match(line)
            if match and match.group(1) in members:
                # the deck's D1 = 1 / Kv scales by 1 / factor, every modulus by factor
                rewritten += [(f"MATERIAL, {g.name}, {match.group(2)}",
                               weight * (1.0 / factor[g.name] if match.group(2) == "D1" else factor[g.name]))
                              for g in members[match.group(1)]]
            else:
                rewritten.append((line, weight))
        state.sensitivity[parameter] = rewritten
    for parameter, entries in state.group_sensitivity.items():
        # du/dp = sum_g sum_k dk_g/dp du/dk_g, dk_g/dp = k_g dln(factor_g)/dp for every modulus k (-D1_g for D1)
        state.sensitivity[parameter] = [line for group, weight in entries if weight != 0.0
                                        for line in _modulus_lines(group, state.laws[group_tissue[group]],
                                                                   constants[group], weight)]
    state.laws = {g.name: state.laws[g.tissue_set] for g in state.groups}
    state.constants = constants


def _fixed(*parameters: EffectParameter):
    return lambda element_sets, node_sets: parameters


def _needs_compartments(element_sets, node_sets):
    found = compartment_sets(element_sets)
    return None if len(found) >= 2 else (f"the mesh has {len(found)} muscle compartment set(s); label the "
                                         "compartments 4, 5, ... in labels.png")


def _needs_second_bone(element_sets, node_sets):
    return None if SECOND_BONE in node_sets else "the mesh has a single bone (no node set BONE2)"


CATALOG: dict[str, Effect] = {effect.name: effect for effect in (
    Effect("compartments", "separate C10 for each muscle compartment",
           "The anterior, lateral, deep and superficial posterior compartments hold different muscles with different "
           "tone; one muscle material then leaves a residual that jumps at the fasciae between compartments.",
           _compartment_parameters, _apply_compartments, requirement=_needs_compartments),
    Effect("drainage", "volumetric shrink of muscle (fluid loss under compression)",
           "Muscle is a biphasic 'wet sponge': under sustained compression interstitial fluid leaves, the tissue "
           "loses volume (dv < 0) and moves inwards everywhere, beyond what the compressible law gives: a radial, "
           "roughly uniform inward residual.",
           _fixed(EffectParameter("dv_muscle", "1", -0.3, 0.3, 0.01, "relative volume change of the muscle")),
           _apply_drainage),
    Effect("friction", "garment-skin Coulomb friction (explicit garment contact)",
           "A garment pulled on holds the skin by friction, so the tangential traction shears the fat; Laplace's law "
           "has no tangential traction at all.",
           _fixed(EffectParameter("mu", "1", 0.0, 1.0, 0.05, "Coulomb friction coefficient")), None,
           garments=("explicit",)),
    Effect("bridging", "explicit garment that bridges concave parts of the skin",
           "Over concave skin (between the tibia's crest and the calf) a real garment lifts off; Laplace's law pulls "
           "there (p = T/r < 0 is clipped, not bridged).",
           _fixed(), None, garments=()),
    Effect("tension_profile", "garment tension varying around the leg (first two harmonics)",
           "Seams, a knit that is stretched unevenly or friction make the tension T vary around the leg: "
           "T(theta) = T (1 + a1 cos theta + b1 sin theta + a2 cos 2theta + b2 sin 2theta), theta about the skin's "
           "centroid; the leg is pushed towards the side of low tension. The second harmonic is there because "
           "nothing fixes the centre of a real profile: a first harmonic of amplitude a about a point d from the "
           "centroid is, seen from the centroid, the same harmonic plus a second of amplitude a d / (2 r) (and a "
           "change of the mean tension as large, inside the tension's own uncertainty).",
           _fixed(EffectParameter("a1", "1", -0.6, 0.6, 0.05, "cos theta amplitude of the tension factor"),
                  EffectParameter("b1", "1", -0.6, 0.6, 0.05, "sin theta amplitude of the tension factor"),
                  EffectParameter("a2", "1", -0.6, 0.6, 0.05, "cos 2theta amplitude of the tension factor"),
                  EffectParameter("b2", "1", -0.6, 0.6, 0.05, "sin 2theta amplitude of the tension factor")),
           _apply_tension_profile, garments=("laplace",)),
    Effect("unloaded_curvature", "the garment's pressure from the curvature of the unloaded leg, T kappa0",
           "Laplace's law presses with the curvature of the deformed skin (Avril et al. eq. 1); a garment designer "
           "computes the pressure from the unloaded leg instead (p = T kappa0, the pressure a pressure sensor "
           "calibrated on the bare leg reads), and so may the model behind the data. Where the garment flattens the "
           "leg the two differ: a residual that follows the change of the skin's curvature.",
           _fixed(EffectParameter("alpha_unloaded", "1", 0.0, 1.0, 0.1,
                                  "share of the pressure taken from the unloaded contour's curvature")),
           _apply_unloaded_curvature, garments=("laplace",)),
    Effect("band_profile", "the garment band's prestretch varying around the leg (explicit band with friction)",
           "A knit stretched unevenly, a seam or a band pulled on askew: the band's natural length varies around the "
           "leg, e(phi) = a1 cos phi + b1 sin phi (phi counter-clockwise on the image from its +x axis, about the "
           "band's centre). Held by friction, the band keeps a hoop force that varies with it, and presses harder "
           "where it is shorter; frictionless it would slide until its force is the same all round.",
           _fixed(EffectParameter("band_a1", "1", -0.15, 0.15, 0.02, "cos phi amplitude of the band's natural length"),
                  EffectParameter("band_b1", "1", -0.15, 0.15, 0.02, "sin phi amplitude of the band's natural length")),
           _apply_band_profile, garments=("explicit",)),
    Effect("bone_motion", "rigid motion of the fibula relative to the tibia instead of clamping",
           "The bones are not welded together: the interosseous membrane lets the fibula move under load, which "
           "drags the deep tissue with it: a residual that is largest around the second bone.",
           _fixed(EffectParameter("ux_BONE2", "mm", -3.0, 3.0, 0.1, "x translation of the second bone"),
                  EffectParameter("uy_BONE2", "mm", -3.0, 3.0, 0.1, "y translation of the second bone")),
           _apply_bone_motion, requirement=_needs_second_bone),
    Effect("stiffening", "higher-order strain-energy term C20 (I1bar - 3)^2",
           "Soft tissue stiffens with strain (collagen recruitment); the neo-Hookean law cannot: regions of large "
           "strain (under the skin, near the bones) move less than the model says.",
           _fixed(EffectParameter("C20_fat", "kPa", 0.0, 5000.0, 500.0, "C20 of fat"),
                  EffectParameter("C20_muscle", "kPa", 0.0, 5000.0, 500.0, "C20 of muscle")),
           _apply_stiffening),
    Effect("out_of_plane", "generalized plane strain: uniform axial stretch",
           "A calf squeezed by a garment lengthens along the leg (or the slice is not where the two scans cut it): "
           "a uniform axial strain eps_z changes the in-plane area at no cost, a dilatation everywhere.",
           _fixed(EffectParameter("eps_z", "1", -0.2, 0.2, 0.01, "axial strain lambda_z - 1")),
           _apply_out_of_plane),
    Effect("heterogeneity", "stiffness varying smoothly around the leg and with depth, in fat and in muscle",
           "Muscle groups differ in stiffness (the compartments), and fat is thicker and looser at the back; a "
           "segmentation into fat and muscle holds none of it: every modulus (C10, Kv) of a tissue times "
           "exp(sum_m c_m phi_m) with the modes "
           "cos, sin of the angle and of twice it, and depth through the muscle, on material groups cut by sector and "
           "depth. Needs no compartment labels.",
           _heterogeneity_parameters, _apply_heterogeneity),
)}
LOCAL_PROBE = Effect("local", "a separate stiffness factor in every material group (diagnosis probe, not fitted)",
                     "Where a local stiffness change would reduce the residual.",
                     lambda element_sets, node_sets: tuple(
                         EffectParameter(f"dlnE_{name}", "1", -2.5, 2.5, 0.25, f"ln stiffness factor of {name}")
                         for name in element_sets if is_group(name)),
                     _apply_local, requirement=_needs_groups)


def effect(name: str) -> Effect:
    """A catalog effect, or one of the group effects (`patch:...`, `region:...`, `local`)."""
    if name in CATALOG:
        return CATALOG[name]
    if name.startswith(PATCH_PREFIX):
        return patch_effect(name)
    if name.startswith(REGION_PREFIX):
        return region_effect(name)
    if name.startswith(CUT_PREFIX):
        return cut_effect(name)
    if name == LOCAL_PROBE.name:
        return LOCAL_PROBE
    raise EffectError(f"unknown effect {name!r}; the catalog has: {', '.join(CATALOG)} (and patch:<groups>, "
                      "region:<fat|muscle>:<start deg>:<end deg>)")


def parse_effects(text: str | Sequence[str] | None) -> tuple[str, ...]:
    """'drainage,stiffening' (or a list) -> ('drainage', 'stiffening'), checked against the catalog."""
    if not text:
        return ()
    names = [n.strip() for n in (text.split(",") if isinstance(text, str) else text) if n.strip()]
    for name in names:
        effect(name)
    if len(set(names)) != len(names):
        raise EffectError(f"an effect is named twice in {names}")
    return tuple(names)


def describe() -> list[str]:
    """Human lines: the catalog with parameters."""
    lines = []
    for item in CATALOG.values():
        where = {("laplace", "explicit"): "", ("laplace",): "  [Laplace's law]"}.get(item.garments, "  [explicit garment]")
        lines.append(f"{item.name:<16} {item.adds}{where}")
        lines.append(f"{'':<16} {item.physics}")
    return lines
