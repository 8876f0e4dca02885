"""calfit-fe's threads on a loaded machine: one thread, two, and the default, alone and beside busy programs.

    cd /work/main && .venv/bin/python benchmarks/threads.py [--dofs 25000,100000] [--runs 5] [--engine PATH]

A Dask worker runs engines beside other engines, and a laptop runs them beside a browser: a thread that waits for
a busy core makes every OpenMP loop wait for it. For each size of the leg-like slice (CPE6, the 20 mmHg follower
pressure of benchmarks/engine.py), calfit-fe runs with --threads 1, --threads 2 and no --threads (the default:
OMP_NUM_THREADS, else the cores that other programs leave idle when it starts), on the idle machine and beside
one and two programs that spin on a core. Printed: the median wall time over --runs runs, the threads the run
used (summary.json) and each time over the one-thread time of the same load. --engine runs another build (an
older calfit-fe, to compare). Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.engine.locate import find_engine  # noqa: E402
from orchestrator.meshing import leg_slice_deck, leg_slice_mesh_for_dof  # noqa: E402

LOADS = (0, 1, 2)          # programs spinning beside the engine
CHOICES = ("1", "2", "default")


def spinners(count: int) -> list[subprocess.Popen]:
    """`count` programs that keep a core busy until killed; a moment to start before the engine does."""
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    time.sleep(0.5 if busy else 0.0)
    return busy


def run(engine: str, deck: Path, choice: str, out: Path) -> tuple[float, int]:
    """(wall s, threads the run used) of one calfit-fe run."""
    command = [engine, str(deck), "-o", str(out), "--quiet"] + ([] if choice == "default" else ["--threads", choice])
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"calfit-fe failed on {deck}: {done.stderr[-500:]}")
    return wall, int(json.loads((out / "summary.json").read_text())["threads"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dofs", default="25000,100000", help="sizes of the slice, comma separated")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--engine", default=None, help="the calfit-fe to run (default: the installed one)")
    arguments = parser.parse_args()
    engine = arguments.engine or str(find_engine())
    print(f"calfit-fe: {engine}; median of {arguments.runs} runs; time / one thread's time under the same load")
    with tempfile.TemporaryDirectory(prefix="calfit-bench-threads-") as scratch:
        for target in (int(v) for v in arguments.dofs.split(",")):
            mesh = leg_slice_mesh_for_dof(target, order=2)
            folder = Path(scratch) / f"slice{target}"
            folder.mkdir()
            deck = folder / "leg.inp"
            leg_slice_deck(deck, mesh=mesh, include_mesh=False)
            print(f"\nleg slice, {mesh.n_dof} DOF ({len(mesh.elements)} CPE6)")
            print(f"  {'busy programs':>13} " + " ".join(f"{'--threads ' + c if c != 'default' else 'default':>24}"
                                                       for c in CHOICES))
            for load in LOADS:
                busy = spinners(load)
                try:
                    cells, one = [], None
                    for choice in CHOICES:
                        walls, used = [], set()
                        for k in range(arguments.runs):
                            wall, threads = run(engine, deck, choice, folder / f"out-{load}-{choice}-{k}")
                            walls.append(wall)
                            used.add(threads)
                        median = statistics.median(walls)
                        one = median if choice == "1" else one
                        threads = "/".join(str(t) for t in sorted(used))
                        cells.append(f"{median:7.3f} s {threads:>3} thr {median / one:4.2f}x")
                finally:
                    for program in busy:
                        program.kill()
                        program.wait()
                print(f"  {load:>13} " + " ".join(f"{cell:>24}" for cell in cells), flush=True)


if __name__ == "__main__":
    main()
