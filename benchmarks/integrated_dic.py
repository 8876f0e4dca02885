"""Integrated DIC against the windows: parameters, misfit over floor, residual per band, cost. Prints, asserts nothing.

    OMP_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/integrated_dic.py [--foreign DIR] [--cases a,b,...]

Cases: the foreign cases blind-04 (control, nothing hidden) and blind-01 (muscle drainage hidden) of DIR (default
/work/shared/foreign-cases; their points.csv is ignored, their garment is p = T kappa0 of the undeformed skin, which
calfit fits with the catalog effect `unloaded_curvature`; blind-01 also gets `drainage`, what it hides), and one
engine-made case of each of calfit's renderers (`CalfPhantom`, `MRIPhantom`) at a random truth (seed 1, as
tests/fit/test_identify_images.py; 4,000 CPE6 for the truth, images and case.toml only, a scanner motion).

For each case, on one prepared run folder (the same segmentation, bone alignment and 1,000-CPE6 mesh for both):
- windows: `calfit identify` as it is today (`pipeline.run_identify`: DIC windows, LM from the default start, the
  skin's uncertainty, LM again); its misfit over its own floor as it reports it;
- I-DIC (`orchestrator.fit.integrated`): the same LM (`identify.levenberg_marquardt`) on the grey-level residual,
  started from the windows' result ("from windows"), and once more from a start away from the truth ("cold": the
  default start, Avril et al. Table 2, for the phantoms; for the foreign cases, whose truth IS Table 2, the default
  start moved by +-20 %, C10_fat x 1.2, C10_muscle x 0.8, Kv_fat x 0.8, Kv_muscle x 1.2, effects at zero);
- I-DIC's grey-level residual variance over the predicted image noise variance per band (`verification.band_masks`:
  fat within 5 mm of the skin, other fat, muscle; plus the 3-pixel air band outside the skin), at the converged
  fit and at the true field (the nuisances fitted in both);
- each fit's linearised 1-sigma of the parameters (% of the value): the windows' (J^T J)^-1 of their whitened residual,
  I-DIC's sandwich for its correlated (prefiltered) pixels (`IntegratedDIC.parameter_covariance`); neither inflated
  by a misfit above its floor;
- wall time and engine runs of each (the run folder's preparation, shared, timed apart; the windows' time holds
  their measurement, two fits and the skin's uncertainty).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from orchestrator.core.frame import RigidMotion
from orchestrator.engine.runner import Evaluator
from orchestrator.fit.identify import residual_jacobian
from orchestrator.fit.integrated import identify_integrated
from orchestrator.meshing.mesh import Mesh
from orchestrator.model.forward import LEG_PARAMETERS, MeshInterpolator
from orchestrator.phantom import CalfPhantom, MRIPhantom
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import random_truth
from orchestrator.run.setup import prepare_run
from orchestrator.run.stages import DEFAULT_MESH, run_identify

FOREIGN = Path("/work/shared/foreign-cases")
FOREIGN_EFFECTS = {"blind-04": ["unloaded_curvature"], "blind-01": ["unloaded_curvature", "drainage"]}
COLD_FACTORS = np.array([1.2, 0.8, 0.8, 1.2])
SCANNER_MOTION = RigidMotion(-0.8, (-0.5, 0.3), (75.0, 75.0))


def foreign_case(name: str, root: Path, scratch: Path):
    """(images-only case folder, truth (4,) kPa, effects, true displacement at points (n, 2) -> (n, 2))."""
    folder = scratch / name
    folder.mkdir()
    for item in (root / name).iterdir():
        if item.name != "points.csv":
            shutil.copy(item, folder / item.name)
    answers = json.loads((root / "answers.json").read_text())[name]
    truth = np.array([answers["truth_kPa"][p] for p in LEG_PARAMETERS])
    with np.load(root / "truth" / f"{name}.npz") as stored:
        mesh = Mesh(stored["nodes_mm"], stored["cells"], np.ones(len(stored["cells"]), int))
        nodal = stored["u_mm"]
    true_at = lambda points: MeshInterpolator(mesh).weights(points) @ nodal   # noqa: E731
    return folder, truth, FOREIGN_EFFECTS[name], true_at, COLD_FACTORS * truth


def phantom_case(renderer: str, scratch: Path, seed: int = 1):
    phantom = CalfPhantom() if renderer == "calf" else MRIPhantom.at_resolution(0.36)
    truth = random_truth(seed)
    case, truth_dir = make_phantom_case(scratch / f"{renderer}-{seed}", phantom=phantom, theta_kPa=truth,
                                        n_elements=4000, labels=None, points_spacing_mm=None, rigid=SCANNER_MOTION,
                                        noise_seeds=(10 + seed, 20 + seed))
    field = np.load(truth_dir / "displacement_mm.npy")
    dy, dx = phantom.pixel_size_mm

    def true_at(points):   # the truth is given on the pixels of I0: read at the pixel under each point
        rows = np.clip((points[:, 1] / dy).astype(int), 0, field.shape[1] - 1)
        cols = np.clip((points[:, 0] / dx).astype(int), 0, field.shape[2] - 1)
        return field[:, rows, cols].T

    return case, truth, [], true_at, None


def windows_sigma(setup, run: Path, effects, theta) -> list[float]:
    """The windows' linearised standard deviations at their fit, (J^T J)^-1 of their whitened residual (overlaps and
    the skin's uncertainty in its covariance), the evaluation replayed from the run's log."""
    model = setup.model_with(effects, sensitivities=True)
    objective = setup.objective_of(setup.level_measurements("dic"))
    with Evaluator(setup.at_every_level(model), objective, run, progress=False) as evaluator:
        record = evaluator(theta)
        launched = evaluator.launched
    jacobian = residual_jacobian(model, record, theta)
    if launched:
        print(f"  (the windows' fit point was not in the log: {launched} engine run for its Jacobian)")
    return np.sqrt(np.diagonal(np.linalg.inv(jacobian.T @ jacobian))).tolist()


def percent(theta, truth) -> str:
    return " ".join(f"{100 * (t - v) / v:+6.1f}" for t, v in zip(theta[:len(truth)], truth))


def run_case(title: str, case: Path, truth, effects, true_at, cold_start, scratch: Path) -> dict:
    print(f"\n=== {title}: effects {effects or 'none'}; truth {np.round(truth, 2).tolist()} kPa", flush=True)
    began = time.perf_counter()
    run = scratch / f"run-{title}"
    setup = prepare_run(case, run, n_elements=DEFAULT_MESH["displacement"][0], order=DEFAULT_MESH["displacement"][1])
    prepare_s = time.perf_counter() - began
    began = time.perf_counter()
    windows = run_identify(case, run, effects=effects, workers=1, progress=False)
    windows_s = time.perf_counter() - began
    rows = {"windows": {"theta": windows["best"]["theta"], "over_floor": windows["misfit_over_floor"],
                        "wall_s": windows_s, "runs": windows["engine_runs_total"],
                        "sigma": windows_sigma(setup, run, effects, windows["best"]["theta"]),
                        "note": windows["data"]["description"]}}
    model = setup.model_with(effects)
    cold = model.start(cold_start.tolist() if cold_start is not None else None)
    objective = None
    for label, start in (("I-DIC from windows", windows["best"]["theta"]), ("I-DIC cold", cold)):
        fit, objective, summary = identify_integrated(setup, scratch / f"idic-{title}-{label.split()[-1]}",
                                                      effects=effects, start=start)
        rows[label] = {"theta": fit.theta, "over_floor": summary["misfit_over_floor"], "wall_s": summary["wall_time_s"],
                       "runs": fit.engine_runs, "iterations": fit.iterations, "start": start,
                       "sigma": summary["standard_deviation"],
                       "note": f"{summary['pixels']} pixels; {fit.message}; nuisances "
                               + ", ".join(f"{k} {v:.2g}" for k, v in summary["nuisance"].items())}
        if label == "I-DIC from windows":
            best_fit = fit
    print(f"prepared run folder (segmentation, bone alignment, {len(setup.mesh.elements)} elements) in "
          f"{prepare_s:.1f} s; parameters {', '.join(model.space.names)}")
    print(f"{'method':<20s} {'error vs truth %':<29s} {'1-sigma %':<29s} {'effects':<14s} "
          f"{'misfit/floor':>12s} {'wall s':>7s} {'runs':>5s}   ({', '.join(LEG_PARAMETERS)})")
    for label, row in rows.items():
        extra = " ".join(f"{v:.3g}" for v in row["theta"][len(truth):])
        sigma = " ".join(f"{100 * s / t:6.2f}" for s, t in zip(row["sigma"][:len(truth)], row["theta"]))
        print(f"{label:<20s} {percent(row['theta'], truth):<29s} {sigma:<29s} {extra:<14s} {row['over_floor']:12.3f} "
              f"{row['wall_s']:7.1f} {row['runs']:5d}")
    for label, row in rows.items():
        print(f"  {label}: {row['note']}")
    # the grey-level residual per band, at the fit from the windows' result and at the true field
    fitted = setup.solve(best_fit.theta, scratch / f"solve-{title}", model=model).displacement()
    frame = setup.frame()
    at_fit = objective.band_ratios(frame, nodal_u=fitted)
    at_truth = objective.band_ratios(frame, displacement_mm=true_at(objective.positions_mm))
    print(f"  I-DIC residual variance / image noise variance ({objective.noise_sigma[0]:.4g}, "
          f"{objective.noise_sigma[1]:.4g} raw noise of I0, I1):")
    print(f"    {'band':<30s} {'pixels':>7s} {'at the fit':>11s} {'at the truth':>13s}")
    for band in at_fit:
        print(f"    {band:<30s} {at_fit[band]['pixels']:7d} {at_fit[band]['ratio']:11.3f} {at_truth[band]['ratio']:13.3f}")
    return {"rows": rows, "bands_fit": at_fit, "bands_truth": at_truth, "prepare_s": prepare_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--foreign", type=Path, default=FOREIGN, help="folder of the foreign cases (answers.json, truth/)")
    parser.add_argument("--cases", default="blind-04,blind-01,calf,mri", help="which cases, comma-separated")
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    arguments = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory(prefix="calfit-bench-idic-") as scratch:
        scratch = Path(scratch)
        for name in arguments.cases.split(","):
            if name in ("calf", "mri"):
                made = phantom_case(name, scratch)
                title = {"calf": "CalfPhantom", "mri": "MRIPhantom"}[name] + " seed 1"
            else:
                made = foreign_case(name, arguments.foreign, scratch)
                title = name
            results[title] = run_case(title, *made, scratch)
    if arguments.json:
        arguments.json.write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
