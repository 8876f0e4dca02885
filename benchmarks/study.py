"""Cases per hour of `calfit study` with 1 and 2 workers on this machine, and each worker's memory.

    cd /work/main && .venv/bin/python benchmarks/study.py [--cases 4] [--elements 2000] [--draws 200]
                                                          [--stages identify,montecarlo,pressures,diagnose]

A cohort of --cases phantom legs, each at its own random truth, rendered by the engine and made images-only (the
two images and case.toml: calfit segments, measures by DIC and meshes each), runs through `calfit study` twice on
a Dask LocalCluster: with one worker, then with two, each into a fresh study folder. Printed: the wall time, the
cases per hour, each case's own wall time and how much of the study's time the workers were busy, the speed-up
of two workers over one (target: at least 1.8x on this 2-core machine) and the peak resident memory of each
worker. Asserts nothing.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.core.files import read_json  # noqa: E402
from orchestrator.core.frame import RigidMotion  # noqa: E402
from orchestrator.phantom.cases import make_phantom_case  # noqa: E402
from orchestrator.phantom.truths import random_truth  # noqa: E402
from orchestrator.study.cohort import ROW_FILE, STAGES, CaseOptions, run_study  # noqa: E402

TARGET_SPEEDUP = 1.8


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", type=int, default=4)
    parser.add_argument("--elements", type=int, default=None, help="identification mesh (default: the pipeline's)")
    parser.add_argument("--draws", type=int, default=None, help="noise Monte-Carlo draws (default: the pipeline's)")
    parser.add_argument("--stages", default=",".join(STAGES))
    arguments = parser.parse_args()
    options = CaseOptions(n_elements=arguments.elements, draws=arguments.draws,
                          stages=tuple(arguments.stages.split(",")))
    with tempfile.TemporaryDirectory(prefix="calfit-bench-study-") as scratch:
        study = Path(scratch) / "study"
        for seed in range(1, arguments.cases + 1):
            make_phantom_case(study / f"leg-{seed}", theta_kPa=random_truth(seed), labels=None, points_spacing_mm=None,
                              noise_seeds=(10 + seed, 20 + seed), rigid=RigidMotion(0.8, (0.4, -0.3), (75.0, 75.0)))
        print(f"{arguments.cases} images-only phantom cases; stages {', '.join(options.stages)}; "
              f"elements {options.n_elements or 'default'}, draws {options.draws or 'default'}")
        hours = {}
        for workers in (1, 2):
            out = Path(scratch) / f"out-{workers}"
            summary = run_study(study, out, options, workers=workers)
            hours[workers] = summary["wall_s"] / 3600.0
            memory = ", ".join(f"{mib:.0f}" for mib in summary["worker_peak_rss_mib"].values())
            print(f"  {workers} worker(s): {summary['wall_s']:7.1f} s, {summary['cases_per_hour']:6.1f} cases per hour, "
                  f"{summary['done']} done, {len(summary['failed'])} failed; peak memory per worker {memory} MiB")
            walls = [read_json(row, "calfit study")["wall_s"] for row in sorted(out.glob(f"cases/*/{ROW_FILE}"))]
            print(f"    each case {', '.join(f'{w:.0f}' for w in walls)} s; the workers busy "
                  f"{100 * sum(walls) / (workers * summary['wall_s']):.0f} % of the study's wall time")
            shutil.rmtree(out)
        speedup = hours[1] / hours[2]
        print(f"  two workers over one: {speedup:.2f}x    target >= {TARGET_SPEEDUP}x")


if __name__ == "__main__":
    main()
