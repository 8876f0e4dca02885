"""The demonstration, end to end on a phantom case made by the engine, from its two images only:

    calfit demo [--out DIR] [--workers N] [--quiet]

1. `calfit phantom`: a calf slice whose loaded image is computed by calfit-fe with the Avril law at
   parameters that are not the fit's start, a garment of 0.16 N/mm (about 20 mmHg), image noise and a
   scanner motion; the case folder holds the two images and case.toml, nothing else (no segmentation,
   no points.csv); the truth is kept apart;
2. `calfit measure`: bones aligned, displacements measured by DIC with their covariance;
3. `calfit identify`: Levenberg-Marquardt on the measured displacements from Avril et al.'s Table 2
   central values, the engine's sensitivities, then again with the skin's uncertainty in the weights;
4. `calfit montecarlo`: 95 % intervals over the measurement noise, and which parameters are identifiable;
5. `calfit pressures`: the five landmark pressures, their spread (Table 3) and the tension ±10 % (Table 4);
6. `calfit diagnose`: the misfit against its floor and the ranking of the effects the model lacks;
7. `calfit report`: the HTML page; its path is printed last.
The phantom and every evaluation are kept in DIR, so running the demo again resumes.

`calfit demo --volume` runs the whole calf instead (about 15 minutes): the 3D phantom leg
(`orchestrator.phantom.volume`: 15 slices 3 mm apart around the calf's widest girth, whose outline, fat and bones
change with height, the truth and the garment's graduated tension varying along the leg, the leg moved in 3D
between the sessions) written as two NIfTI volumes, then `calfit study` on it: the volumes aligned on the bones, 12 slices cut, each identified
with its intervals and pressures, and the study report with the profiles along the leg and the pressure at B,
B1, C and D. The truth's profile is printed beside the identified one.

`calfit demo --leg-slice` runs the earlier quick demonstration instead: the analytic leg slice
solved once at the Table 2 central values, with the pressures it transmits.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..core.files import read_json
from ..core.frame import RigidMotion
from ..core.units import KPA_PER_MPA
from ..engine.results import EngineResults
from ..engine.runner import run_engine
from ..measure.measurements import read_window_table
from ..meshing import leg_slice_deck
from ..phantom.cases import make_phantom_case
from ..report.run_report import write_report
from ..run.setup import PARAMETERS_FILE
from ..run.stages import (
    fit_summary,
    intervals_summary,
    pressure_summary,
    run_diagnose,
    run_identify,
    run_measure,
    run_montecarlo,
    run_pressures,
)
from ._common import (
    add_output_arguments,
    folder,
    honours_quiet,
    notice,
    show_progress,
    tension,
    whole_number,
)
from ._measure import summary_lines
from ._solve import describe

HELP = "phantom case -> identification -> uncertainty -> HTML report (or --leg-slice: one solve)"

# Avril et al. (2010), Table 2, central values, in MPa: (C10, Kv).
TABLE2_CENTRAL = {"FAT": ("AVRIL", (4.5e-3, 106e-3)), "MUSCLE": ("AVRIL", (11.2e-3, 69.5e-3))}
# the phantom's truth, kPa: not the fit's start (Table 2 central values), within Avril et al.'s Table 1 ranges
DEMO_TRUTH_KPA = (3.6, 12.4, 92.0, 74.0)
DEMO_SCANNER_MOTION = RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=folder, default="demo-out", help="folder for the case, the run and the report (default demo-out)")
    parser.add_argument("--workers", type=whole_number(1), default=2, help="engine evaluations in parallel (default 2)")
    parser.add_argument("--draws", type=whole_number(1), default=200, help="Monte-Carlo draws (default 200)")
    parser.add_argument("--leg-slice", action="store_true", help="only solve the analytic leg slice once")
    parser.add_argument("--volume", action="store_true",
                        help="the whole calf: the 3D phantom leg through calfit study (about 15 minutes)")
    parser.add_argument("--elements", type=whole_number(1), default=5500, help="--leg-slice: number of elements (default 5500)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=2, help="--leg-slice: 1: CPE3, 2: CPE6 (default)")
    parser.add_argument("--tension", type=tension, default=0.16, help="garment tension in N/mm (default 0.16, about 20 mmHg)")
    add_output_arguments(parser, json_help=None)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    if args.volume:
        return run_volume(args)
    return run_leg_slice(args) if args.leg_slice else run_full(args)


def run_full(args: argparse.Namespace) -> int:
    began = time.perf_counter()
    out = Path(args.out)
    case_dir, truth_dir, run_dir = out / "case", out / "case.truth", out / "run"
    if not (case_dir / "case.toml").is_file():
        notice(args, f"[1/7] phantom case made by the engine (two images, no segmentation, no points) -> {case_dir}")
        make_phantom_case(case_dir, truth_dir, theta_kPa=DEMO_TRUTH_KPA, tension_N_per_mm=args.tension,
                          rigid=DEMO_SCANNER_MOTION, labels=None, points_spacing_mm=None, overwrite=True)
    else:
        notice(args, f"[1/7] reusing the phantom case in {case_dir}")
    truth = read_json(truth_dir / PARAMETERS_FILE, "calfit phantom")["parameters_kPa"]
    notice(args, "[2/7] displacements measured from the images (DIC)")
    measured = run_measure(case_dir, run_dir) if read_window_table(run_dir) is None else None
    progress = show_progress(args)
    notice(args, "[3/7] identification: Levenberg-Marquardt on the measured displacements")
    identification = run_identify(case_dir, run_dir, workers=args.workers, progress=progress)
    names = identification["parameters"]
    notice(args, "[4/7] Monte-Carlo intervals over the measurement noise")
    montecarlo = run_montecarlo(run_dir, draws=args.draws, workers=args.workers, progress=progress)
    notice(args, "[5/7] landmark pressures: 30 draws in the intervals, tension ±10 %")
    pressures = run_pressures(run_dir, workers=args.workers, progress=progress)
    notice(args, "[6/7] diagnosis: misfit against its floor, missing effects")
    diagnosis = run_diagnose(run_dir, workers=args.workers, progress=progress)
    notice(args, "[7/7] report")
    page = write_report(run_dir, truth)
    best = identification["best"]
    if measured is not None:
        print("\n".join(summary_lines(measured, str(run_dir))))
    print(fit_summary(best, names))
    print("truth:      " + ", ".join(f"{n} = {truth[n]:.3f}" for n in names) + " kPa")
    print("error:      " + ", ".join(f"{n} {100 * (v - truth[n]) / truth[n]:+.1f} %" for n, v in zip(names, best["theta"])))
    print(f"misfit {identification['misfit_over_floor']:.2f} x its noise floor")
    print("\n".join(intervals_summary(montecarlo)))
    print("\n".join(pressure_summary(pressures)))
    print(f"diagnosis: {diagnosis['verdict']}")
    print(f"demo finished in {time.perf_counter() - began:.0f} s")
    print(f"report: {page}")
    return 0


def run_volume(args: argparse.Namespace) -> int:
    from ..phantom.volume import FINE_HEIGHTS_MM, FINE_STUDIED_MM, write_volume_case
    from ..study.cohort import CaseOptions, run_study

    began = time.perf_counter()
    out = Path(args.out)
    case_dir, truth_dir, study_dir = out / "leg", out / "leg.truth", out / "study"
    if not (case_dir / "case.toml").is_file():
        notice(args, f"[1/2] the 3D phantom leg: two NIfTI volumes and case.toml -> {case_dir} (about 3 minutes)")
        write_volume_case(case_dir, truth_dir, heights_mm=FINE_HEIGHTS_MM, studied=FINE_STUDIED_MM,
                          overwrite=True)
    else:
        notice(args, f"[1/2] reusing the 3D phantom leg in {case_dir}")
    notice(args, f"[2/2] calfit study {case_dir} --out {study_dir}")
    summary = run_study(case_dir, study_dir, CaseOptions(draws=args.draws), workers=args.workers,
                        report=lambda line: notice(args, line))
    truth = {round(entry["height_mm"], 1): entry["parameters_kPa"]
             for entry in read_json(truth_dir / "truth.json", "calfit demo --volume")["slices"]}
    rows = sorted((read_json(path, "calfit study") for path in (study_dir / "cases").glob("*/row.json")),
                  key=lambda row: row["height_mm"])
    names = [name for name in rows[0] if f"{name}_low" in rows[0]] if rows else []
    print("height   " + "".join(f"{name:>28}" for name in names) + "   misfit/floor")
    for row in rows:
        expected = truth[round(row["height_mm"], 1)]
        cells = "".join(f"{row[n]:8.2f} [{row[n + '_low']:6.2f},{row[n + '_high']:6.2f}] ({expected[n]:5.1f})"
                        for n in names)
        print(f"{row['height_mm']:5.0f} mm {cells}   {row['misfit_over_floor']:.2f}")
    print("(each parameter: identified [95 % interval] (truth), kPa)")
    print(f"{summary['done']} of {summary['cases']} slices done in {time.perf_counter() - began:.0f} s")
    print(f"report: {study_dir / summary['report']}")
    return 0 if not summary["failed"] else 1


def run_leg_slice(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    deck = out / "leg_slice.inp"
    notice(args, f"writing {deck} ({args.elements} elements, garment tension {args.tension} N/mm)")
    leg_slice_deck(deck, n_elements=args.elements, order=args.order, materials=TABLE2_CENTRAL,
                   laplace_tension=args.tension)
    outcome = run_engine(deck, out / "results", threads=None, echo=show_progress(args))
    results = EngineResults(outcome.outdir)
    print(describe(results))
    pressure = results.cell_field("pressure") * KPA_PER_MPA
    material = results.cell_field("material_id").astype(int)
    skin = results.point_field("laplace_pressure") * KPA_PER_MPA
    for index, name in enumerate(TABLE2_CENTRAL, start=1):
        p = pressure[material == index]
        print(f"{name.lower():<11} hydrostatic pressure {p.min():.2f} .. {p.max():.2f} kPa (mean {p.mean():.2f})")
    loaded = skin[skin != 0.0]
    print(f"garment     Laplace pressure on the skin {loaded.min():.2f} .. {loaded.max():.2f} kPa")
    print(f"open {outcome.outdir / 'step-1.vtu'} in ParaView to see the fields")
    return 0 if outcome.converged else 3
