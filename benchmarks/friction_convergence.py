"""Mesh and increment convergence of the leg under the explicit garment band, with and without Coulomb friction.

    .venv/bin/python benchmarks/friction_convergence.py [--meshes 1100,2000,4000,8000] [--mu 0.3]
                                                         [--increments 5,10,20,80] [--increments-mesh 2000]

The phantom calf's own geometry (`study.truth_mesh`, CPE6) is meshed at each size, the band put on as
`forward.LegModel(mesh, 0.16, garment="explicit", friction_mu=mu)` writes it (orchestrator/engine/decks.py,
templates/leg_garment.inp.j2) at theta = (3.4, 14.1, 85.0, 52.0) kPa, and the tissue's displacements are compared
at common points (a 1 mm grid inside every mesh, more than 0.3 mm from the skin) by finite-element interpolation.
Printed:
1. mesh convergence: RMS and max |du| (um) of each mesh against the finest, and of the two coarsest against each
   other (a fit's mesh against a phantom's), for mu = 0 and mu; the band's pin reaction (N/mm) that stays at the
   end (GARMENT_PIN_Y) and the bones' torque (N mm/mm), which friction makes depend on the pins;
2. increment dependence: one mesh with the release (step 3) cut into fixed increments, each against the finest.
Every run is single-threaded; the defaults take about 4 minutes on one core.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from orchestrator.core.materials import deck_material
from orchestrator.engine.decks import leg_garment_deck
from orchestrator.engine.results import EngineResults
from orchestrator.engine.runner import run_engine, write_mesh_include
from orchestrator.fit.objectives import leg_rows
from orchestrator.model.forward import LegModel, MeshInterpolator, _barycentric
from orchestrator.phantom import CalfPhantom
from orchestrator.phantom.mesh import truth_mesh

THETA_KPA = (3.4, 14.1, 85.0, 52.0)
TENSION_N_PER_MM = 0.16
GRID_MM, SKIN_MARGIN_MM = 1.0, 0.3


def solve(mesh, mu: float, folder: Path, release_increments: int | None = None) -> dict:
    """One put-on; the leg's nodal displacements, the last pin's reaction, the bones' torque and the run's counts."""
    model = LegModel(mesh, TENSION_N_PER_MM, garment="explicit", friction_mu=mu)
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh_include(model, folder)
    if release_increments is None:
        deck = model.deck(THETA_KPA)
    else:
        state = model.deck_state(THETA_KPA)
        materials = {elset: deck_material(state.laws[elset], constants, False) for elset, constants in state.constants.items()}
        dt = 1.0 / release_increments
        deck = leg_garment_deck(materials, model.band, mesh, friction_mu=mu, release_static=(dt, 1.0, 1e-6, dt))
    (folder / "leg.inp").write_text(deck)
    start = time.perf_counter()
    outcome = run_engine(folder / "leg.inp", folder / "out", threads=1, timeout_s=3600)
    wall = time.perf_counter() - start
    results = EngineResults(folder / "out")
    summary = json.loads((folder / "out" / "summary.json").read_text())
    if summary["status"] != "converged":
        raise RuntimeError(f"{folder}: {summary['status']} (exit {getattr(outcome, 'returncode', '?')})")
    vtu = results.mesh()
    reaction = np.asarray(vtu.point_data["reaction"])[:, :2]
    u_all = np.asarray(vtu.point_data["displacement"])[:, :2]
    pin_y = model.band.node_sets["GARMENT_PIN_Y"] + len(mesh.nodes)
    bones = mesh.node_sets["BONES"]
    centre = mesh.nodes[mesh.skin_loop].mean(axis=0)
    arm = mesh.nodes[bones] + u_all[bones] - centre
    torque = float(np.sum(arm[:, 0] * reaction[bones, 1] - arm[:, 1] * reaction[bones, 0]))
    release = summary["steps"][2]
    return {"u": leg_rows(results.displacement(), len(mesh.nodes)), "pin": float(reaction[pin_y, 1].sum()),
            "torque": torque, "wall": wall, "increments": release["n_increments"], "cutbacks": release["n_cutbacks"],
            "iterations": sum(step["newton_iterations"] for step in summary["steps"])}


def common_points(meshes) -> np.ndarray:
    """A 1 mm grid of points strictly inside an element of every mesh and more than SKIN_MARGIN_MM from each skin."""
    coarse = min(meshes, key=lambda m: len(m.elements))
    low, high = coarse.nodes.min(axis=0), coarse.nodes.max(axis=0)
    grid = np.mgrid[low[0]:high[0]:GRID_MM, low[1]:high[1]:GRID_MM].reshape(2, -1).T
    keep = np.ones(len(grid), bool)
    for mesh in meshes:
        corners = mesh.elements[:, :3]
        _, candidates = cKDTree(mesh.nodes[corners].mean(axis=1)).query(grid, k=12)
        inside = (_barycentric(mesh.nodes, corners[candidates], grid[:, None, :]).min(axis=2) >= 1e-3).any(axis=1)
        near_skin = cKDTree(mesh.nodes[mesh.skin_loop]).query(grid)[0] <= SKIN_MARGIN_MM
        keep &= inside & ~near_skin
    return grid[keep]


def difference(a: np.ndarray, b: np.ndarray) -> str:
    d = np.linalg.norm(a - b, axis=1) * 1e3
    return f"{np.sqrt((d ** 2).mean()):6.1f} / {d.max():6.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default="1100,2000,4000,8000", help="element counts, finest last")
    ap.add_argument("--mu", type=float, default=0.3)
    ap.add_argument("--increments", default="5,10,20,80", help="fixed release increments, finest last")
    ap.add_argument("--increments-mesh", type=int, default=2000)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args()
    sizes = [int(v) for v in args.meshes.split(",")]
    counts = [int(v) for v in args.increments.split(",")]
    work = args.workdir or Path(tempfile.mkdtemp(prefix="friction-convergence-"))
    phantom = CalfPhantom()
    meshes = {n: truth_mesh(phantom, n_elements=n, order=2) for n in sorted(set(sizes) | {args.increments_mesh})}
    points = common_points([meshes[n] for n in sizes])
    weights = {n: MeshInterpolator(mesh).weights(points) for n, mesh in meshes.items()}
    finest = sizes[-1]
    print(f"phantom leg, truth meshes of {', '.join(str(len(meshes[n].elements)) for n in sizes)} CPE6; "
          f"{len(points)} common points; runs in {work}")

    print(f"\n1. mesh convergence: RMS / max |du| in um against the {finest}-element mesh (and {sizes[0]} against "
          f"{sizes[1]})")
    print(f"{'mu':>5s} {'mesh':>6s} {'vs finest':>16s} {'pin N/mm':>9s} {'torque':>8s} {'release incr.':>14s} "
          f"{'Newton':>6s} {'wall s':>6s}")
    for mu in (0.0, args.mu):
        runs = {n: solve(meshes[n], mu, work / f"mesh{n}-mu{mu:g}") for n in sizes}
        fields = {n: weights[n] @ runs[n]["u"] for n in sizes}
        for n in sizes:
            run = runs[n]
            versus = "" if n == finest else difference(fields[n], fields[finest])
            print(f"{mu:5.2f} {n:6d} {versus:>16s} {run['pin']:9.5f} {run['torque']:8.4f} "
                  f"{run['increments']:>8d} ({run['cutbacks']} cut) {run['iterations']:6d} {run['wall']:6.1f}")
        if len(sizes) > 2:
            print(f"{mu:5.2f} {sizes[0]} vs {sizes[1]}: {difference(fields[sizes[0]], fields[sizes[1]])}")

    n = args.increments_mesh
    print(f"\n2. increment dependence, {n}-element mesh, mu = {args.mu:g}: the release in k fixed increments, "
          f"RMS / max |du| in um against k = {counts[-1]}")
    runs = {k: solve(meshes[n], args.mu, work / f"increments{k}-mesh{n}", release_increments=k) for k in counts}
    reference = weights[n] @ runs[counts[-1]]["u"]
    for k in counts:
        run = runs[k]
        versus = "" if k == counts[-1] else difference(weights[n] @ run["u"], reference)
        print(f"k = {k:3d}: {versus:>16s}   pin {run['pin']:8.5f} N/mm, Newton {run['iterations']:4d}, "
              f"{run['wall']:5.1f} s")


if __name__ == "__main__":
    main()
