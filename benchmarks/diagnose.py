"""Cost of a full diagnosis (issues 6 and 29) on the 400-element model: every catalog effect that the model can
carry is scored, then the best one (and those tied with it) refitted; with Laplace's law, with the explicit garment
band (frictionless: the effects act under the band, the engine's sensitivities pass through its contact) and with
the band and friction 0.3 (the second paper's: the engine carries the sensitivities of the constants, a volume
change and the out-of-plane stretch along the put-on's path; a bone's motion and the band's prestretch profile are
differences of runs), side by side.

    .venv/bin/python benchmarks/diagnose.py [--order 1|2] [--hidden drainage] [--garment laplace explicit friction]
        [--lines engine-none engine-auto fd-none fd-auto]
    .venv/bin/python benchmarks/diagnose.py --stepwise [--hidden drainage unloaded_curvature] [--renderer calf|mri]
        [--seed 7]

For each garment model a phantom case is made with it and a hidden effect (default: 5 % fluid loss of the muscle;
its making and the baseline identification are not timed), then `pipeline.run_diagnose` runs from an empty
evaluation log twice: with the engine's sensitivities du/dtheta (`*SENSITIVITY`, one run for the whole ranking)
and with forward differences (one run per parameter). Prints for each the wall time of the ranking (with
--refit none, which still refits the best local patch when one is significant) and of the full diagnosis with its
refits (target: under 60 s on 2 cores with Laplace's law) and the engine runs each took.

--stepwise: the forward-backward path (`diagnose.stepwise`) from the images only: a phantom case with the hidden
effects (one or more at once; tissue constants drawn from --seed around Table 2, not its central values, the fit's
start), the images of --renderer, the truth on 8,000 CPE6 and the fit on calfit's own mesh of its segmentation, no
points.csv; measured and identified (not timed), then diagnosed. Prints, per step of the path, the effects in the
model, its misfit over the floor, BIC, and the wall time and engine runs the step took (ranking the model before
it, its refits, the backward refits, the floor at its fit), then the whole diagnosis' (issue 58 target: a
Laplace-law case in 5 minutes or less on this machine).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from orchestrator.core.frame import RigidMotion
from orchestrator.engine.runner import LOG_NAME, EvaluationLog
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.stages import run_diagnose, run_identify

HIDDEN_VALUES = {"drainage": {"dv_muscle": -0.05}, "bone_motion": {"ux_BONE2": 0.2, "uy_BONE2": -0.15},
                 "out_of_plane": {"eps_z": 0.05}, "tension_profile": {"a1": 0.08, "b1": -0.05},
                 "unloaded_curvature": {"alpha_unloaded": 1.0}}
GARMENTS = {"laplace": ("laplace", 0.0), "explicit": ("explicit", 0.0), "friction": ("explicit", 0.3)}
# sensitivities x refit: the engine's or finite differences, the ranking alone ("none") or with its refits ("auto")
LINES = ("engine-none", "engine-auto", "fd-none", "fd-auto")


def _fresh_copy(base: Path, target: Path) -> Path:
    """A copy of the identified run folder: each measurement starts from the same log, no diagnosis in it."""
    shutil.copytree(base, target)
    return target


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--order", type=int, choices=(1, 2), default=2, help="element order of the fit (default 2)")
    parser.add_argument("--hidden", nargs="+", choices=sorted(HIDDEN_VALUES), default=None,
                        help="the hidden effect (default drainage; with --stepwise, several at once: default "
                             "drainage unloaded_curvature)")
    parser.add_argument("--stepwise", action="store_true", help="time the stepwise path from the images, per step")
    parser.add_argument("--renderer", choices=("calf", "mri"), default="calf",
                        help="--stepwise: the phantom renderer of the images (default calf)")
    parser.add_argument("--seed", type=int, default=7, help="--stepwise: the draw of the tissue constants")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--garment", nargs="+", choices=sorted(GARMENTS), default=list(GARMENTS),
                        help="the garment models of the phantom and of the fit (default: all three, side by side)")
    parser.add_argument("--lines", nargs="+", default=list(LINES), choices=LINES,
                        help="which lines to time (default: all four); e.g. engine-auto alone for the band's refits")
    args = parser.parse_args()
    if args.stepwise:
        with tempfile.TemporaryDirectory(prefix="calfit-bench-") as scratch:
            _stepwise_timed(Path(scratch), args.hidden or ["drainage", "unloaded_curvature"], args)
        return
    if len(args.hidden or ()) > 1:
        parser.error("one hidden effect at a time without --stepwise")
    args.hidden = (args.hidden or ["drainage"])[0]
    garments = args.garment
    if set(garments) != {"laplace"} and args.hidden == "tension_profile":
        parser.error("a tension profile is Laplace's law's: the explicit band carries none (--garment laplace)")
    with tempfile.TemporaryDirectory(prefix="calfit-bench-") as scratch:
        for garment in garments:
            _diagnose_timed(Path(scratch) / garment, garment, args)


def _diagnose_timed(scratch: Path, garment: str, args) -> None:
    print(f"\n{garment} garment: making a phantom case with hidden {args.hidden} {HIDDEN_VALUES[args.hidden]} ...",
          flush=True)
    model, friction = GARMENTS[garment]
    case, _ = make_phantom_case(scratch / "case", effects={args.hidden: HIDDEN_VALUES[args.hidden]},
                                rigid=RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0)), points_sigma_mm=0.05,
                                points_spacing_mm=3.0, garment=model, friction_mu=friction)
    if model == "explicit":
        with open(case / "case.toml", "a") as toml:
            toml.write(f'\n[model]\ngarment = "explicit"\nfriction = {friction}\n')
    identified = scratch / "identified"
    fit = run_identify(case, identified, method="lm", order=args.order, workers=args.workers, progress=False)
    setup = json.loads((identified / "setup.json").read_text())
    print(f"baseline identification (not timed): {setup['n_elements']} elements of order {setup['order']}, "
          f"{fit['best']['engine_runs']} engine runs, misfit {fit['best']['cost']:.4g} mm^2")
    for label, engine in (("engine sensitivities", True), ("finite differences", False)):
        for refit in ("none", "auto"):
            if f"{'engine' if engine else 'fd'}-{refit}" not in args.lines:
                continue
            run = _fresh_copy(identified, scratch / f"{label}-{refit}".replace(" ", "-"))
            before = len(EvaluationLog(run / LOG_NAME))
            began = time.perf_counter()
            result = run_diagnose(run, refit_effects=refit, engine_sensitivities=engine, workers=args.workers,
                                  progress=False)
            elapsed = time.perf_counter() - began
            runs = len(EvaluationLog(run / LOG_NAME)) - before
            # --refit none still refits the best local patch when one is significant (pipeline.run_diagnose)
            what = "ranking (+ patch)" if refit == "none" else "ranking + refits"
            print(f"{garment:<9} {label:<21} {what:<16} {elapsed:6.1f} s  {runs:4d} engine runs  "
                  f"best: {result['ranking'][0]['effect']}  verdict: {result['verdict'][:90]}", flush=True)


def _stepwise_timed(scratch: Path, hidden: list[str], args) -> None:
    import numpy as np

    from orchestrator.diagnose.stepwise import path_lines
    from orchestrator.phantom import CalfPhantom, MRIPhantom

    rng = np.random.default_rng(args.seed)
    theta = (np.array([4.5, 11.2, 106.0, 69.5]) * rng.uniform(0.75, 1.3, 4)).tolist()
    effects = {name: HIDDEN_VALUES[name] for name in hidden}
    print(f"stepwise diagnosis from the images ({args.renderer} renderer): hidden {effects}, tissue constants "
          f"{[round(v, 2) for v in theta]} kPa; making the case ...", flush=True)
    phantom = CalfPhantom() if args.renderer == "calf" else MRIPhantom()
    case, _ = make_phantom_case(scratch / "case", theta_kPa=theta, effects=effects, points_spacing_mm=None,
                                rigid=RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0)), phantom=phantom)
    began = time.perf_counter()
    fit = run_identify(case, scratch / "run", workers=args.workers, progress=False)
    print(f"measured and identified (not timed): {fit['data']['description']}, {time.perf_counter() - began:.0f} s, "
          f"misfit {fit['misfit_over_floor']:.2f} x the floor", flush=True)
    before = len(EvaluationLog(scratch / "run" / LOG_NAME))
    began = time.perf_counter()
    result = run_diagnose(scratch / "run", workers=args.workers, progress=False)
    elapsed = time.perf_counter() - began
    runs = len(EvaluationLog(scratch / "run" / LOG_NAME)) - before
    print("\n".join(path_lines(result["path"], result["final"])))
    found = sorted(result["final"]["effects"]) == sorted(hidden)
    print(f"whole diagnosis: {elapsed:.1f} s, {runs} engine runs; final {result['final']['effects']} "
          f"({'the hidden effects' if found else 'NOT the hidden effects ' + str(sorted(hidden))}), "
          f"{result['final']['misfit_over_floor']:.2f} x the floor")
    print(f"verdict: {result['verdict']}", flush=True)


if __name__ == "__main__":
    main()
