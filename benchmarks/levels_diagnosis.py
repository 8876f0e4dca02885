"""Two socks against one in the diagnosis (issue 29, item 3): the rank and the p-value of a hidden effect, side by
side, when the same slice is diagnosed from one loaded image or from two under garments of different tensions.

    .venv/bin/python benchmarks/levels_diagnosis.py [--effects drainage compartments] [--seed 4]
        [--model laplace|band|second-paper] [--data points|dic] [--second-tension 0.32] [--workers 2] [--keep DIR]
        [--resume] [--together]

For each hidden effect, a phantom calf is made by the engine at a truth drawn in physiological ranges (not the fit's
start; `phantom.truths.random_truth(seed)`), on the phantom's own 8,000-element mesh, with scanner motion, under
0.16 N/mm and under the second tension, the effect switched on in both. The case with the two loaded images
([[garment.levels]]) and the same case without the second are identified (`calfit identify`, on the fit's own mesh
from the segmentation) and diagnosed (`calfit diagnose`, refit "auto"); every effect is scored on all the levels at
once. Models:
- laplace: neo-Hookean tissues under Laplace's law (the first paper's), engine sensitivities;
- band: the same tissues under the explicit frictionless band, engine sensitivities through the contact;
- second-paper: Bouten and Drapier's Table 1 Mooney-Rivlin tissues, incompressible on CPE6H, the band with friction
  0.3 (the engine carries the sensitivities of the constants, a volume change and the out-of-plane stretch along
  the put-on's path; a bone's motion and the band's prestretch profile are differences of runs).
With --together the effects are hidden at once, in one case, and the stepwise diagnosis must add each of them and
nothing else (issue 58, item 7: the same loop with every garment model): printed per sock count, the path (the
effects in the model and the misfit over the floor at each step), the final model, whether it holds exactly the
hidden effects, and the wall times.

Printed per effect: one sock and two socks, the hidden effect's rank, score statistic and p-value, the best effect,
the design effect D of the residual's correlation (the statistic is the chi^2 reduction over D), the misfit over the
floor before and after the refit (and each level's own after it), and the wall times.

With the second paper's model a case takes about 45 minutes a level set on two cores: `--keep DIR --resume` goes
on from the cases and runs an interrupted benchmark left in DIR. A level set that ended is not run again (its row,
with the wall times it took, is kept in DIR); one that was interrupted goes on where it stopped (the pipeline
replays the engine runs it logged), and its wall times are then those of the resumed run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from levels import first_level_only

from orchestrator.core.files import write_json
from orchestrator.core.frame import RigidMotion
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import (
    SECOND_PAPER_FIT_TABLES,
    SECOND_PAPER_KPA,
    SECOND_PAPER_TISSUES,
    random_truth,
)
from orchestrator.run.stages import run_diagnose, run_identify

SCANNER_MOTION = RigidMotion(-0.8, (-0.5, 0.3), (75.0, 75.0))
FIRST_TENSION = 0.16   # N/mm
HIDDEN = {
    "drainage": {"values": {"dv_muscle": -0.05}},
    "tension_profile": {"values": {"a1": 0.08, "b1": -0.05}},
    "bone_motion": {"values": {"ux_BONE2": 0.2, "uy_BONE2": -0.15}},
    "compartments": {"values": {"dC10_COMPARTMENT5": -0.6, "dC10_COMPARTMENT6": 2.0, "dC10_COMPARTMENT7": -0.6},
                     "labels": "compartments"},
    "band_profile": {"values": {"band_a1": 0.05, "band_b1": -0.03}},   # the band's own, with friction only
}
BAND_TABLES = '\n[model]\nelement = "CPE6"\ngarment = "explicit"\n'


def make_case(folder: Path, model: str, effects: list[str], seed: int, second_tension: float, data: str) -> Path:
    """The two-sock phantom case of `model` with `effects` hidden (module text)."""
    specs = [HIDDEN[effect] for effect in effects]
    labels = "compartments" if any(spec.get("labels") == "compartments" for spec in specs) else "segmented"
    options = dict(tension_N_per_mm=FIRST_TENSION, levels=(second_tension,), rigid=SCANNER_MOTION,
                   effects={effect: spec["values"] for effect, spec in zip(effects, specs)}, labels=labels,
                   points_spacing_mm=6.0 if data == "points" else None, noise_seeds=(10 + seed, 20 + seed),
                   overwrite=True)
    if model == "second-paper":
        options.update(theta_kPa=list(SECOND_PAPER_KPA.values()), garment="explicit", friction_mu=0.3, hybrid=True,
                       points_sigma_mm=0.05, tissues=SECOND_PAPER_TISSUES)
    else:
        options.update(theta_kPa=random_truth(seed), garment="explicit" if model == "band" else "laplace")
    case, _ = make_phantom_case(folder, **options)
    tables = {"second-paper": SECOND_PAPER_FIT_TABLES, "band": BAND_TABLES}.get(model, "")
    if tables:
        with open(case / "case.toml", "a") as toml:
            toml.write(tables)
    return case


def identify_and_diagnose(case: Path, run: Path, data: str, workers: int) -> dict:
    began = time.perf_counter()
    identification = run_identify(case, run, data=data, workers=workers, progress=False)
    identified = time.perf_counter()
    diagnosis = run_diagnose(run, workers=workers, progress=False)
    return {"identification": identification, "diagnosis": diagnosis, "identify_s": identified - began,
            "diagnose_s": time.perf_counter() - identified}


def summary(effect: str, result: dict) -> dict:
    """The hidden effect's place in the ranking and what its refit reached."""
    diagnosis = result["diagnosis"]
    ranking = diagnosis["ranking"]
    names = [score["effect"] for score in ranking]
    rank = names.index(effect) + 1 if effect in names else None
    score = ranking[rank - 1] if rank else None
    refit = next((fit for fit in diagnosis["refits"] if fit["effects"][-1:] == [effect]), None)
    return {"rank": rank, "of": len(names), "statistic": score["statistic"] if score else float("nan"),
            "p_value": score["p_value"] if score else float("nan"), "best": names[0] if names else "-",
            "before": diagnosis["before"]["misfit_over_floor"],
            "after": refit["misfit_over_floor"] if refit else float("nan"),
            "after_levels": [level["misfit_over_floor"] for level in (refit or {}).get("levels", [])],
            "design_effect": diagnosis["design_effect"], "verdict": diagnosis["verdict"],
            "identify_s": result["identify_s"], "diagnose_s": result["diagnose_s"],
            "engine_runs": diagnosis["engine_runs"]}


def path_summary(effects: list[str], result: dict) -> dict:
    """What the stepwise diagnosis of a case with `effects` hidden at once did (--together)."""
    diagnosis = result["diagnosis"]
    final = diagnosis["final"]
    return {"path": [{"effects": step["effects"], "misfit_over_floor": step["misfit_over_floor"]}
                     for step in diagnosis["path"]],
            "final": final["effects"], "final_misfit_over_floor": final["misfit_over_floor"],
            "explained": final["explained"], "exactly_hidden": sorted(final["effects"]) == sorted(effects),
            "verdict": diagnosis["verdict"], "identify_s": result["identify_s"], "diagnose_s": result["diagnose_s"],
            "engine_runs": diagnosis["engine_runs"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--effects", nargs="+", default=["drainage", "compartments"], choices=sorted(HIDDEN))
    parser.add_argument("--model", default="laplace", choices=("laplace", "band", "second-paper"))
    parser.add_argument("--data", default="points", choices=("points", "dic"))
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--second-tension", type=float, default=0.32)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--keep", type=Path, help="keep the cases and runs in this folder")
    parser.add_argument("--resume", action="store_true",
                        help="go on from the cases and runs that an interrupted benchmark left in --keep's folder")
    parser.add_argument("--together", action="store_true",
                        help="hide the effects at once, in one case, and print the stepwise diagnosis' path")
    arguments = parser.parse_args()
    if arguments.resume and arguments.keep is None:
        parser.error("--resume goes on from the folder of an earlier --keep: give it")
    if "band_profile" in arguments.effects and arguments.model != "second-paper":
        parser.error("band_profile is the band's own and needs friction: --model second-paper")
    if "tension_profile" in arguments.effects and arguments.model != "laplace":
        parser.error("tension_profile is Laplace's law's: --model laplace")
    rows = []
    with tempfile.TemporaryDirectory(prefix="calfit-levels-diagnosis-") as scratch:
        root = arguments.keep or Path(scratch)
        groups = [arguments.effects] if arguments.together else [[effect] for effect in arguments.effects]
        for hidden in groups:
            effect = "+".join(hidden)
            folder = root / f"{arguments.model}-{effect}"
            made = folder / "cases-made"
            two, one = folder / "two-socks", folder / "one-sock"
            made_with = (f"seed {arguments.seed}, second tension {arguments.second_tension:g} N/mm, "
                         f"data {arguments.data}\n")
            if arguments.resume and made.is_file():
                if made.read_text() != made_with:
                    parser.error(f"{folder} holds cases made with {made.read_text().strip()}, not {made_with.strip()}: "
                                 "give those options or leave out --resume")
                print(f"{effect}: the cases and runs of {folder} taken up again", flush=True)
            else:
                if folder.exists():
                    shutil.rmtree(folder)
                began = time.perf_counter()
                two = make_case(two, arguments.model, hidden, arguments.seed, arguments.second_tension, arguments.data)
                one = first_level_only(two, one)
                made.write_text(made_with)
                print(f"{effect}: phantom made in {time.perf_counter() - began:.0f} s", flush=True)
            pair = {}
            for label, case in (("one sock", one), ("two socks", two)):
                finished = folder / f"summary-{case.name}.json"
                if arguments.resume and finished.is_file():
                    # a level set that ended is not run again: its row keeps the wall times it took
                    pair[label] = json.loads(finished.read_text())
                    print(f"  {label}, finished earlier: {json.dumps(pair[label])}", flush=True)
                    continue
                result = identify_and_diagnose(case, folder / f"run-{case.name}", arguments.data, arguments.workers)
                pair[label] = path_summary(hidden, result) if arguments.together else summary(effect, result)
                write_json(finished, pair[label])
                print(f"  {label}: {json.dumps(pair[label])}", flush=True)
            rows.append((effect, pair))
    print()
    print(f"model {arguments.model}, data {arguments.data}, truth seed {arguments.seed}, socks {FIRST_TENSION:g} and "
          f"{arguments.second_tension:g} N/mm")
    if arguments.together:
        for effect, pair in rows:
            for label, s in pair.items():
                steps = " -> ".join(f"{step['misfit_over_floor']:.2f}" for step in s["path"])
                print(f"{effect} hidden, {label}: path {steps} x the floor; final {', '.join(s['final']) or 'nothing'}"
                      f" ({'exactly the hidden effects' if s['exactly_hidden'] else 'NOT the hidden effects'}, "
                      f"{'explained' if s['explained'] else 'unexplained'}); identify {s['identify_s']:.0f} s, "
                      f"diagnose {s['diagnose_s']:.0f} s, {s['engine_runs']} engine runs")
        return
    header = (f"{'hidden':<16}{'socks':>6} {'rank':>6} {'statistic':>10} {'p-value':>9} {'best':>16} "
              f"{'D':>6} {'x floor':>8} {'refit':>7}  {'each level after':<18}{'identify':>9}{'diagnose':>9}")
    print(header)
    print("-" * len(header))
    for effect, pair in rows:
        for label, s in pair.items():
            rank = f"{s['rank']}/{s['of']}" if s["rank"] else "-"
            levels = ", ".join(f"{v:.2f}" for v in s["after_levels"])
            print(f"{effect:<16}{label.split()[0]:>6} {rank:>6} {s['statistic']:10.1f} {s['p_value']:9.2g} "
                  f"{s['best']:>16} {s.get('design_effect', float('nan')):6.1f} {s['before']:8.2f} {s['after']:7.2f}  "
                  f"{levels:<18}{s['identify_s']:8.0f}s"
                  f"{s['diagnose_s']:8.0f}s")


if __name__ == "__main__":
    main()
