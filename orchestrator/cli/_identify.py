"""Identify the tissue parameters of a case (Avril et al. sec. 2.2.5; Bouten and Drapier sec. 2.6).

    calfit identify CASE_DIR --out RUN_DIR [--method lm|nm] [--objective auto|displacement|contour]
                    [--data auto|dic|points] [--window 16|32|64] [--starts one|table1] [--start KPA ...]
                    [--elements N] [--order 1|2] [--effects NAME[,NAME]] [--skin-uncertainty MM]
                    [--workers N] [--scheduler ADDRESS] [--json] [--quiet]

From the two images alone: the loaded image is aligned on the bones, the displacements are measured by DIC
(`calfit measure`, run here when the run folder has none; --data points takes points.csv instead, which is the
default when the case has one), I0 is segmented and meshed (2,000 CPE6 by default), and the four parameters
(C10 and Kv of fat and muscle, kPa) are fitted by Levenberg-Marquardt with the engine's sensitivities, the
residual weighted by the DIC covariance. The uncertainty of the model's skin is then estimated at that point
and the fit repeated with it in the weights (--skin-uncertainty sets it, mm RMS; default: the error the skin's
own spectrum shows, 0.05 pixel where it cannot tell).
--objective contour fits the contour mismatch M of Avril et al. instead (Nelder-Mead, 400 T3 by default).
--starts table1 runs from the initial values of Avril et al. Table 1 (each parameter ±10 %).
Every evaluation is logged in RUN_DIR/evaluations.jsonl: run the same command again after an interruption and
it resumes without repeating one. Writes RUN_DIR/identification.json (which data, misfit against its floor).
--effects adds catalog effects (`calfit diagnose --catalog`), their parameters fitted from zero; --effects final
takes the final model of the run folder's diagnosis (`calfit diagnose RUN_DIR`), and the list its verdict prints
("drainage, then unloaded_curvature") is taken as it is.
"""

from __future__ import annotations

import argparse

from ..measure.measurements import DEFAULT_WINDOW_PX, WINDOW_CHOICES
from ..run.diagnose_stage import requested_effects
from ..run.setup import DATA_SOURCES
from ..run.stages import (
    OBJECTIVE_ALIASES,
    OBJECTIVES,
    fit_summary,
    floor_sentence,
    run_identify,
)
from ..run.timings import timing_line
from ._common import (
    add_parallel_arguments,
    emit,
    fail,
    folder,
    honours_quiet,
    notice,
    parallel_options,
    whole_number,
)

HELP = "fit the tissue parameters of a case (Nelder-Mead or Levenberg-Marquardt)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case_dir", help="case folder (case.toml, unloaded and loaded images, ...)")
    parser.add_argument("--out", type=folder, required=True, help="run folder (created; reused to resume)")
    parser.add_argument("--method", choices=("lm", "nm"), default="lm",
                        help="lm: Levenberg-Marquardt with the engine's sensitivities (default); nm: Nelder-Mead")
    parser.add_argument("--objective", choices=("auto",) + OBJECTIVES + tuple(OBJECTIVE_ALIASES), default="auto",
                        help="displacement: measured displacements (default); contour: the contour mismatch M "
                             "(Avril et al.; with --method nm)")
    parser.add_argument("--data", choices=DATA_SOURCES, default="auto",
                        help="dic: measure from the images; points: points.csv; auto: points.csv when present, else dic")
    parser.add_argument("--window", type=int, choices=WINDOW_CHOICES, default=DEFAULT_WINDOW_PX,
                        help=f"DIC window side in pixels when the displacements are measured here (default {DEFAULT_WINDOW_PX})")
    parser.add_argument("--starts", choices=("one", "table1"), default="one", help="one start, or the starts of Table 1")
    parser.add_argument("--start", type=float, nargs="+", metavar="KPA",
                        help="initial values of the laws' free constants in kPa, in the order of the fit's parameter "
                             "names (C10_fat C10_muscle Kv_fat Kv_muscle for the first paper's law; default: case.toml's "
                             "start, else Avril et al. Table 2 central values)")
    parser.add_argument("--elements", type=whole_number(1), help="elements of the identification mesh (default 2000; 400 with "
                                                     "--objective contour)")
    parser.add_argument("--order", type=int, choices=(1, 2),
                        help="1: CPE3; 2: CPE6 (default; 1 with --objective contour, as in Avril et al.)")
    parser.add_argument("--effects", help="comma-separated catalog effects whose parameters are fitted too "
                                           "(calfit diagnose --catalog lists them), or final: the final model of "
                                           "the diagnosis in --out")
    parser.add_argument("--skin-uncertainty", type=float, metavar="MM",
                        help="RMS uncertainty of the segmented skin's shape, mm (default: measured on the skin's "
                             "spectrum; 0.05 pixel where it cannot be)")
    add_parallel_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        result = run_identify(args.case_dir, args.out, method=args.method, objective=args.objective, data=args.data,
                              window_px=args.window, start=args.start, starts=args.starts, n_elements=args.elements,
                              order=args.order, effects=requested_effects(args.effects, args.out),
                              skin_sigma_mm=args.skin_uncertainty, **parallel_options(args))
    except (ValueError, RuntimeError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    lines = [fit_summary(fit, result["parameters"], result.get("unit_of")) for fit in result["fits"]]
    lines.append(f"best ({result['objective']}, {result['data']['description']}): "
                 + fit_summary(result["best"], result["parameters"], result.get("unit_of")))
    if "noise_floor" in result:
        lines.append(f"misfit {result['misfit_over_floor']:.2f} x its noise floor {result['noise_floor']:.4g} mm^2")
    if "floor_calibration" in result:
        lines.append(floor_sentence(result["floor_calibration"]))
    lines += result.get("setup_lines", [])
    lines.append(f"run folder {args.out}; next: calfit montecarlo {args.out}")
    lines += [line for line in [timing_line(result.get("timings"))] if line]
    emit(args, result, lines)
    notice(args, f"identification written to {args.out}/identification.json")
    return 0
