"""Speed of the orchestrator loop (issue 5), on the 400-element T3 model of Avril et al.
(sec. 2.2.1) meshed from the phantom calf, one increment, `--threads 1` per engine process:

    .venv/bin/python benchmarks/loop.py [--draws 200]

prints (1) engine evaluations per second of a Monte-Carlo sweep scored by the contour mismatch
M (sec. 2.2.5) with 1 and 2 local workers (target: at least 50/s on 2 cores), (2) the wall time
of a Nelder-Mead identification (F, Bouten and Drapier eq. 2, from a start off the truth), the wall
time and engine runs of Levenberg-Marquardt with the Jacobian from the engine's sensitivities and
from finite differences (issue 7: at most 15 runs with sensitivities), and
(3) the time of the 30-draw uncertainty study of sec. 4.2 (the paper: 15 minutes; target under
3 s), (4) Levenberg-Marquardt with 4, 6 and 8 free parameters on a phantom made with the 8 (the base
four, C20 of fat and muscle: `stiffening`, the garment's first tension harmonic: `tension_profile`):
iterations, engine solves, wall time, errors (issue 13), and (5) the images-first path: a case folder
with two images only -> identified parameters and diagnosis (target under 10 s, issue 59; 30 s in issue 28), with
where its time went, stage by stage, as identification.json and diagnosis.json keep it (`run.timings`). Every
measurement starts from an empty run folder (no cache).

    .venv/bin/python benchmarks/loop.py --only images-first [--repeat 3]

runs (5) alone (`--repeat`: that many times, each from an empty run folder, and the fastest and the median said).
To see where the time goes inside a stage: `python -m cProfile -o loop.prof benchmarks/loop.py --only images-first`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from orchestrator.core.frame import RigidMotion
from orchestrator.engine.runner import Evaluator
from orchestrator.fit.identify import nelder_mead, pressure_uncertainty
from orchestrator.model.forward import TABLE2_CENTRAL_KPA
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.blas import single_blas_thread
from orchestrator.run.setup import prepare_run, read_json
from orchestrator.run.stages import run_diagnose, run_identify
from orchestrator.run.timings import timing_line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--draws", type=int, default=200, help="Monte-Carlo draws per measurement (default 200)")
    parser.add_argument("--only", choices=("images-first",), help="run this measurement alone")
    parser.add_argument("--repeat", type=int, default=1, help="times to run the images-first path (default 1)")
    args = parser.parse_args()
    single_blas_thread()   # as calfit runs (`run.blas`)
    with tempfile.TemporaryDirectory(prefix="calfit-bench-") as scratch:
        scratch = Path(scratch)
        if args.only == "images-first":
            images_first(scratch, args.repeat)
            return
        print("making the phantom case (engine-made loaded image) ...", flush=True)
        case, _ = make_phantom_case(scratch / "case", scratch / "case.truth")
        setup = prepare_run(case, scratch / "setup")
        print(f"model: {len(setup.mesh.elements)} {setup.mesh.element_type} elements, {len(setup.mesh.nodes)} nodes")
        rng = np.random.default_rng(0)
        central = np.array(TABLE2_CENTRAL_KPA)
        mismatch = setup.mismatch_objective()
        for workers in (1, 2):
            thetas = central * np.exp(rng.uniform(-0.5, 0.5, (args.draws, 4)))
            with Evaluator(setup.model, mismatch, scratch / f"mc{workers}", workers=workers, progress=False) as evaluator:
                evaluator.evaluate(thetas[:workers].tolist())   # start the pool outside the timing
                began = time.perf_counter()
                records = evaluator.evaluate(thetas[workers:].tolist())
                elapsed = time.perf_counter() - began
            failed = sum(record["status"] != "ok" for record in records)
            print(f"Monte-Carlo sweep, {workers} worker(s): {len(records) / elapsed:.1f} evaluations/s "
                  f"({len(records)} engine runs + contour mismatch, {failed} failed, {elapsed:.2f} s)")
        start = central * np.array([1.3, 0.8, 0.8, 1.25])
        with Evaluator(setup.model, setup.displacement_objective(), scratch / "nm", workers=1, progress=False) as evaluator:
            fit = nelder_mead(evaluator, start)
        print(f"Nelder-Mead identification (F at {len(setup.case.points)} points): {fit.wall_time_s:.2f} s, "
              f"{fit.iterations} iterations, {fit.engine_runs} engine runs")
        for label, engine in (("engine sensitivities", True), ("finite differences", False)):
            lm = run_identify(case, scratch / f"lm-{label.split()[0]}", method="lm", objective="displacement",
                              start=start.tolist(), engine_sensitivities=engine, progress=False)["best"]
            print(f"Levenberg-Marquardt, Jacobian from {label}: {lm['wall_time_s']:.2f} s, {lm['iterations']} "
                  f"iterations, {lm['engine_runs']} engine runs, misfit {lm['cost']:.6g} mm^2")
        pressure = setup.pressure_objective()
        with Evaluator(setup.model, pressure, scratch / "uq", workers=2, progress=False) as evaluator:
            evaluator.evaluate([central.tolist(), (central * 1.01).tolist()])   # start the pool outside the timing
            began = time.perf_counter()
            stats = pressure_uncertainty(evaluator, pressure.names, central * 0.8, central * 1.2, central,
                                         setup.case.tension_N_per_mm, draws=30, seed=7)
            elapsed = time.perf_counter() - began
        print(f"30-draw uncertainty study (+ tension +-10 %): {elapsed:.2f} s with 2 workers "
              f"(the paper: 15 minutes); CV {np.round(stats.cv_percent, 1)} %")
        parameter_counts(scratch)
        images_first(scratch, args.repeat)


# A phantom with all eight parameters of the largest fit switched on (kPa and dimensionless)
COUNTS_TRUTH_KPA = (3.8, 13.0, 90.0, 80.0)
COUNTS_EFFECTS = {"stiffening": {"C20_fat": 600.0, "C20_muscle": 1500.0}, "tension_profile": {"a1": 0.15, "b1": -0.1}}
COUNTS_FITS = ((), ("stiffening",), ("stiffening", "tension_profile"))


def parameter_counts(scratch: Path) -> None:
    """Levenberg-Marquardt (Jacobian from the engine's sensitivities) with 4, 6 and 8 free parameters, from the same
    start off the truth, on a phantom made with all 8 (points at 6 mm, 0.02 mm noise): how its iterations and solves
    grow with the parameters; the 4- and 6-parameter fits miss an effect, which their misfits show."""
    case, _ = make_phantom_case(scratch / "counts-case", scratch / "counts-case.truth", theta_kPa=COUNTS_TRUTH_KPA,
                                effects=COUNTS_EFFECTS)
    truth = dict(zip(("C10_fat", "C10_muscle", "Kv_fat", "Kv_muscle"), COUNTS_TRUTH_KPA))
    truth.update({name: value for values in COUNTS_EFFECTS.values() for name, value in values.items()})
    start = (np.array(COUNTS_TRUTH_KPA) * np.array([1.3, 0.8, 0.8, 1.25])).tolist()
    print(f"Levenberg-Marquardt against the number of free parameters (phantom made with {truth}):")
    for effects in COUNTS_FITS:
        began = time.perf_counter()
        result = run_identify(case, scratch / f"counts-{len(effects)}", method="lm", objective="displacement",
                              start=start, effects=effects, progress=False)
        elapsed = time.perf_counter() - began
        best = result["best"]
        names = result["parameters"]
        errors = ", ".join(f"{name} {100 * (value - truth[name]) / truth[name]:+.1f} %"
                           for name, value in zip(names, best["theta"]) if name in truth)
        stop = "converged" if best["converged"] else f"not converged: {best['message']}"
        print(f"  {len(best['theta'])} parameters ({', '.join(effects) or 'base'}): {best['iterations']} iterations "
              f"({stop}), {best['engine_runs']} engine solves, {elapsed:.1f} s; misfit {result['misfit_over_floor']:.2f} x its "
              f"floor; {errors}")


def images_first(scratch: Path, repeat: int = 1) -> None:
    """Case folder (two images, case.toml) -> identified parameters + diagnosis, as `calfit identify` and
    `calfit diagnose` run it: segmentation, bone alignment, meshing, DIC, Levenberg-Marquardt, the skin's
    uncertainty and the second fit, then the effect ranking. Target: 10 s on this 2-core machine (issue 59); each
    repeat from an empty run folder, the case made once."""
    truth = (3.6, 12.4, 92.0, 74.0)
    case, _ = make_phantom_case(scratch / "images-case", scratch / "images-case.truth", theta_kPa=truth, labels=None,
                                points_spacing_mm=None, rigid=RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0)))
    totals = []
    for attempt in range(max(1, repeat)):
        run = scratch / f"images-run-{attempt}"
        began = time.perf_counter()
        identification = run_identify(case, run, workers=2, progress=False)
        identified = time.perf_counter()
        diagnosis = run_diagnose(run, workers=2, progress=False)
        done = time.perf_counter()
        totals.append(done - began)
        measured = read_json(run / "measurements.json", "calfit measure")
        theta = np.array(identification["best"]["theta"])
        print(f"images first, case folder (two 420x420 images) -> parameters + diagnosis: {done - began:.1f} s "
              f"(target 10 s) = identify {identified - began:.1f} s (of which DIC {measured['wall_time_s']:.1f} s, "
              f"{identification['engine_runs_total']} engine runs in the log) + diagnose {done - identified:.1f} s "
              f"({diagnosis['engine_runs']} runs for the ranking, {len(diagnosis['refits'])} refits)")
        print(f"  identify {timing_line(identification.get('timings'))}")
        print(f"  diagnose {timing_line(diagnosis.get('timings'))}")
        print(f"  error {np.round(100 * (theta - np.array(truth)) / np.array(truth), 1)} %, misfit "
              f"{identification['misfit_over_floor']:.2f} x its floor; {diagnosis['verdict']}")
    if len(totals) > 1:
        print(f"images first over {len(totals)} runs: fastest {min(totals):.1f} s, median {np.median(totals):.1f} s")


if __name__ == "__main__":
    main()
