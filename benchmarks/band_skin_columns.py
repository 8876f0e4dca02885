"""The skin's shape uncertainty under the explicit band: Laplace's law's columns against the band's own (issue 29,
item 2).

    .venv/bin/python benchmarks/band_skin_columns.py [--modes 2,3,4,6,8,12,16] [--step 0.02]

`geometry_uncertainty` turns a segmentation error of the skin, a normal offset alpha cos k phi (and sin), into
what the measurements see of it through Laplace's law: the offset changes the skin's curvature, hence the garment
pressure by (k^2 - 1) alpha / R, a tension profile whose sensitivities the engine gives in one run. Under the
explicit band the pressure comes from the contact instead. Here the same offset is put on the model itself: the
skin nodes of the run's mesh moved by +-step along their normals, the band rebuilt on the moved skin as
calfit builds it, both solved at the truth, the central difference observed at the case's points. Against it,
Laplace's column and the engine's: `GAP PROFILE` (the offset given to the contact alone, the elements keep the
mesh's shape) and `SHAPE` (the skin's nodes moved radially, elements, contact and its weights with them: what
calfit uses under the band; the band is not rebuilt). Printed for each mode: the norm of each column over the
moved skin's, their correlation and their relative difference.
An explicit phantom case (frictionless band, truth (3.4, 14.1, 85, 52) kPa, its own 2,000-element mesh, points) is
made in a scratch folder. Asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.core.frame import RigidMotion  # noqa: E402
from orchestrator.engine.runner import solve_once  # noqa: E402
from orchestrator.fit.geometry_uncertainty import (  # noqa: E402
    skin_perimeter_mm,
    skin_pressure_sensitivities,
)
from orchestrator.meshing.curves import unit_normals  # noqa: E402
from orchestrator.model.forward import LegModel  # noqa: E402
from orchestrator.phantom.cases import make_phantom_case  # noqa: E402
from orchestrator.run.stages import _setup  # noqa: E402

TRUTH_KPA = (3.4, 14.1, 85.0, 52.0)


def _gap_profile_sensitivities(model, count: int) -> dict:
    """du/d(a_k, b_k) of the band's *GAP PROFILE of the skin, k = 1 .. count, at TRUTH_KPA."""
    from orchestrator.engine.results import EngineResults, sensitivity_name
    from orchestrator.engine.runner import run_engine, write_mesh_include

    lines = [f"GAP PROFILE, SKIN, {kind}{k}" for k in range(1, count + 1) for kind in ("A", "B")]
    with tempfile.TemporaryDirectory(prefix="calfit-bench-gap-") as scratch:
        write_mesh_include(model, Path(scratch))
        deck = Path(scratch) / "deck.inp"
        deck.write_text(model.deck(TRUTH_KPA, extra_sensitivities=lines, own_sensitivities=False))
        found = EngineResults(run_engine(deck, Path(scratch) / "out", threads=None).outdir).sensitivities()
    return {line: found[sensitivity_name(line)] for line in lines}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--modes", default="2,3,4,6,8,12,16", help="the skin offset's harmonics k")
    parser.add_argument("--step", type=float, default=0.02, help="the offset of the central differences (mm)")
    arguments = parser.parse_args()
    modes = [int(k) for k in arguments.modes.split(",")]
    with tempfile.TemporaryDirectory(prefix="calfit-bench-band-skin-") as scratch:
        case, _ = make_phantom_case(Path(scratch) / "case", Path(scratch) / "truth", theta_kPa=TRUTH_KPA,
                                    n_elements=2000, rigid=RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0)),
                                    garment="explicit")
        with open(case / "case.toml", "a") as toml:
            toml.write('\n[model]\nelement = "CPE6"\ngarment = "explicit"\n')
        setup = _setup(case, Path(scratch) / "run", None, None)
        mesh, tension = setup.mesh, setup.case.tension_N_per_mm
        observe = setup.measurements("points", with_geometry=False).observation(mesh)
        laplace = LegModel(mesh, tension, tissues=setup.model.tissues, hybrid=setup.model.hybrid)
        sensitivities = skin_pressure_sensitivities(laplace, TRUTH_KPA, max(modes))
        explicit = LegModel(mesh, tension, garment="explicit", tissues=setup.model.tissues, hybrid=setup.model.hybrid)
        gap = skin_pressure_sensitivities(explicit, TRUTH_KPA, max(modes))   # SHAPE lines
        gap.update(_gap_profile_sensitivities(explicit, max(modes)))
        radius = skin_perimeter_mm(mesh) / (2.0 * np.pi)
        skin = mesh.nodes[mesh.skin_loop]
        centre = skin.mean(axis=0)
        angle = np.arctan2(skin[:, 1] - centre[1], skin[:, 0] - centre[0])
        normals = unit_normals(skin, True)
        normals *= np.sign(np.mean(np.einsum("ij,ij->i", normals, skin - centre)))   # outwards

        def observed_with_offset(offset: np.ndarray) -> np.ndarray:
            nodes = mesh.nodes.copy()
            nodes[mesh.skin_loop] += offset[:, None] * normals
            model = LegModel(dataclasses.replace(mesh, nodes=nodes), tension, garment="explicit",
                             tissues=setup.model.tissues, hybrid=setup.model.hybrid)
            displacement = solve_once(model, model.deck(TRUTH_KPA), "the band did not converge on the moved skin")
            return observe @ displacement[:len(mesh.nodes)].ravel()

        print(f"explicit band, {len(mesh.elements)} {mesh.element_type}, R = {radius:.1f} mm, offsets "
              f"+-{arguments.step} mm; per unit offset amplitude:")
        print(f"  {'mode':>5} {'column':>12} {'|column| / |moved skin|':>24} {'correlation':>12} "
              f"{'relative difference':>20}")
        for k in modes:
            for kind, shape in (("A", np.cos), ("B", np.sin)):
                offset = arguments.step * shape(k * angle)
                band = (observed_with_offset(offset) - observed_with_offset(-offset)) / (2.0 * arguments.step)
                laplace_column = observe @ sensitivities[f"PROFILE, GARMENT, {kind}{k}"].ravel() * (k * k - 1) / radius
                columns = {"Laplace": laplace_column,
                           "GAP PROFILE": observe @ gap[f"GAP PROFILE, SKIN, {kind}{k}"][:len(mesh.nodes)].ravel(),
                           "SHAPE": observe @ gap[f"SHAPE, SKIN, {kind}{k}"][:len(mesh.nodes)].ravel()}
                norm_band = np.linalg.norm(band)
                for name, column in columns.items():
                    norm = np.linalg.norm(column)
                    correlation = band @ column / (norm_band * norm)
                    print(f"  {k:>4}{kind} {name:>12} {norm / norm_band:24.3f} {correlation:+12.3f} "
                          f"{np.linalg.norm(band - column) / norm_band:20.3f}", flush=True)


if __name__ == "__main__":
    main()
