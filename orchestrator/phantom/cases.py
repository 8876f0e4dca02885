"""Phantom cases whose loaded image the engine makes: the truth solved in plane strain by calfit-fe on a mesh of the phantom's own exact geometry (not the fit's mesh), with hidden effects, laws and garment levels as asked, written as a case folder a user would bring and its truth folder apart."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.files import write_json
from ..core.frame import RigidMotion
from ..engine.runner import solve_once
from ..fit.objectives import leg_rows
from ..model.forward import TABLE2_CENTRAL_KPA, LegModel, MeshInterpolator, field_on_pixels
from ..run.setup import PARAMETERS_FILE
from .mesh import truth_mesh


def make_phantom_case(folder: str | Path, truth_folder: str | Path | None = None, *,
                      theta_kPa: Sequence[float] = TABLE2_CENTRAL_KPA, tension_N_per_mm: float = 0.16,
                      n_elements: int = 8000, order: int = 2, points_spacing_mm: float | None = 6.0,
                      points_sigma_mm: float = 0.02, noise_seeds: tuple[int, int] = (0, 1), rigid: RigidMotion | None = None,
                      effects: dict[str, dict[str, float]] | None = None, labels: str = "segmented",
                      edit_deck=None, phantom=None, garment: str = "laplace", friction_mu: float = 0.0,
                      tissues: dict | None = None, hybrid: bool = False,
                      levels: Sequence[float] = (), overwrite: bool = False) -> tuple[Path, Path]:
    """Write a phantom case whose loaded image is made by the engine at theta_kPa (see module text).

    levels: the tensions (N/mm) of more garment levels: each is solved with the same truth and mesh, rendered
    with the same scanner motion and its own noise, and written as loaded-level-<k>.png with its
    [[garment.levels]] table (and its points, points-level-<k>.csv, when the case has points).

    effects: catalog effects switched on in the truth, {effect: {parameter: value}} (a case with a hidden
    effect); with `compartments` the truth is meshed with the muscle compartments, and `labels` should then be
    "compartments" so that the fit can separate them. labels: what the case's labels.png holds
    (`orchestrator.phantom.write_case`). edit_deck(deck_text, mesh) -> deck_text: physics outside the catalog
    written into the truth's deck directly (how a case with an unknown effect is made). phantom: the phantom to
    mesh and render, an `orchestrator.phantom.CalfPhantom` (default: the standard calf and scanner) or
    `MRIPhantom` (the second, independent renderer). garment, friction_mu:
    the truth's garment, Laplace's law or the explicit band with that friction; tissues, hybrid: the tissues' laws
    (theta_kPa then holds their free constants) and u/p elements (`forward.LegModel`)."""
    from . import CalfPhantom, write_case

    effects = {name: dict(values) for name, values in (effects or {}).items()}
    phantom = phantom or CalfPhantom()
    mesh = truth_mesh(phantom, compartments="compartments" in effects, n_elements=n_elements, order=order)
    model = LegModel(mesh, tension_N_per_mm, fixed_effects=effects, garment=garment, friction_mu=friction_mu,
                     tissues=tissues, hybrid=hybrid)
    text = model.deck(theta_kPa)
    nodal = leg_rows(solve_once(model, edit_deck(text, mesh) if edit_deck else text,
                                f"the engine did not converge on the phantom at theta = {list(theta_kPa)} kPa with "
                                f"effects {effects}; choose stiffer parameters or a smaller tension"), len(mesh.nodes))
    weights = MeshInterpolator(mesh).pixel_weights(phantom.image_shape, phantom.pixel_size_mm)
    field = field_on_pixels(weights, nodal, phantom.image_shape)
    level_fields = [field_on_pixels(weights, _phantom_level_nodal(model, theta_kPa, tension, edit_deck), phantom.image_shape)
                    for tension in levels]
    laws = {tissue: {"law": law.law, "terms": law.terms, "incompressible": law.incompressible, "fixed": dict(law.fixed)}
            for tissue, law in model.tissue_laws.items()}
    truth = {"parameters_kPa": dict(zip(model.law_parameters, map(float, theta_kPa))),
             "tension_N_per_mm": tension_N_per_mm, "laws": laws,
             "effects": effects, "deck_edited": edit_deck is not None,
             "garment": garment, "friction_mu": friction_mu,
             "engine_mesh": {"elements": len(mesh.elements), "type": mesh.element_type + ("H" if hybrid else "")},
             "max_displacement_mm": float(np.abs(field).max())}
    case, truth_dir = write_case(folder, phantom, field, rigid=rigid, truth_folder=truth_folder,
                                 tension_N_per_mm=tension_N_per_mm, points_spacing_mm=points_spacing_mm,
                                 points_sigma_mm=points_sigma_mm, noise_seeds=noise_seeds, labels=labels,
                                 description=json.dumps(truth), levels=list(zip(levels, level_fields)),
                                 overwrite=overwrite)
    if levels:
        truth["levels"] = [{"tension_N_per_mm": float(tension), "max_displacement_mm": float(np.abs(f).max())}
                           for tension, f in zip(levels, level_fields)]
    write_json(Path(truth_dir) / PARAMETERS_FILE, truth)
    return Path(case), Path(truth_dir)


def _phantom_level_nodal(model: LegModel, theta_kPa, tension: float, edit_deck) -> np.ndarray:
    """The truth's nodal displacement under another garment tension (a phantom's more garment level)."""

    text = model.deck(theta_kPa, tension_N_per_mm=tension)
    return leg_rows(solve_once(model, edit_deck(text, model.mesh) if edit_deck else text,
                               f"the engine did not converge on the phantom at theta = {list(theta_kPa)} kPa under "
                               f"{tension} N/mm; choose stiffer parameters or a smaller tension"), len(model.mesh.nodes))
