"""Deck fuzzer: mutated copies of the engine's verification decks, each run by calfit-fe under a timeout.

The engine's contract (solver_cpp/README.md): exit 0 converged, 2 a bad deck named by `FILE:LINE: what is
wrong`, 3 not converged (with the reason), 4 any other failure; never a signal, never a hang. Each input is
one seeded mutation (or a few) of one deck of `tests/support/ccx_reference` small enough to solve in milliseconds:
numbers out of range (1e308, nan, inf, huge and negative integers), deleted, duplicated, swapped and truncated
lines, a truncated file, wrong element connectivity (unknown, repeated or negative node ids), degenerate and
inverted elements, coincident nodes, flipped characters and binary garbage.

    python tests/fuzz_decks.py --inputs 100000 --seed 1 [--workers 2] [--engine PATH] [--keep DIR]

prints one summary line (inputs, exit codes, crashes, hangs, rejections naming a line, rejections that do not)
and writes every crashing or hanging input to --keep (default fuzz-findings/). `make fuzz` runs it; the test
suite runs a few thousand inputs with a fixed seed (`test_engine_fuzz.py`).
"""

from __future__ import annotations

import argparse
import os
import random
import re
import subprocess
import sys
import tempfile
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

CORPUS_DIR = Path(__file__).resolve().parent / "ccx_reference"
CORPUS = ("square_elastic_cpe6.inp", "square_mooney_rivlin_cpe6.inp", "square_arruda_boyce_cpe6.inp",
          "square_reduced_polynomial3_cpe6.inp", "annulus_avril_cpe6.inp")
TIMEOUT_S = 20.0
EXIT_CODES = {0: "converged", 2: "rejected", 3: "not converged", 4: "other failure"}
HOSTILE_NUMBERS = ("1e308", "-1e308", "1e-308", "4.9e-324", "1e400", "-1e400", "nan", "NaN", "inf", "-inf",
                   "0", "-0", "-1", "1e20", "-1e20", "2147483647", "2147483648", "-2147483649",
                   "99999999999999999999", "0x10", "1..2", "", "1e", "+", "--1", "1,5")
NUMBER = re.compile(r"(?<![A-Za-z_])[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")
LOCATED = re.compile(r"\.inp:\d+:")


def _element_lines(lines: list[str]) -> list[int]:
    """Indices of the data lines of *ELEMENT blocks."""
    found, inside = [], False
    for k, line in enumerate(lines):
        if line.startswith("*"):
            inside = line.upper().startswith("*ELEMENT")
        elif inside and line.strip():
            found.append(k)
    return found


def _node_lines(lines: list[str]) -> list[int]:
    found, inside = [], False
    for k, line in enumerate(lines):
        if line.startswith("*"):
            inside = line.upper().startswith("*NODE") and "FILE" not in line.upper() and "PRINT" not in line.upper()
        elif inside and line.strip():
            found.append(k)
    return found


def mutate(text: str, rng: random.Random) -> tuple[bytes, str]:
    """One mutation of a deck; returns the bytes and what was done."""
    lines = text.splitlines() or [""]     # an earlier mutation may have emptied the file
    kind = rng.choice(("number", "number", "number", "delete", "duplicate", "swap", "truncate_line", "truncate_file",
                       "connectivity", "degenerate", "inverted", "coincident", "flip", "garbage"))
    k = rng.randrange(len(lines))
    numbered = [i for i, line in enumerate(lines) if NUMBER.search(line)]
    if kind == "number" and not numbered:
        kind = "garbage"
    if kind == "number":
        k = rng.choice(numbered)
        matches = list(NUMBER.finditer(lines[k]))
        m = rng.choice(matches)
        lines[k] = lines[k][:m.start()] + rng.choice(HOSTILE_NUMBERS) + lines[k][m.end():]
    elif kind == "delete":
        del lines[k]
    elif kind == "duplicate":
        lines.insert(k, lines[k])
    elif kind == "swap":
        j = rng.randrange(len(lines))
        lines[k], lines[j] = lines[j], lines[k]
    elif kind == "truncate_line":
        lines[k] = lines[k][:rng.randrange(len(lines[k]) + 1)]
    elif kind == "truncate_file":
        data = "\n".join(lines).encode()
        return data[:rng.randrange(len(data) + 1)], f"{kind} line {k + 1}"
    elif kind in ("connectivity", "degenerate", "inverted"):
        elements = _element_lines(lines)
        if elements:
            k = rng.choice(elements)
            ids = [v.strip() for v in lines[k].split(",")]
            if len(ids) >= 4:
                if kind == "connectivity":
                    ids[rng.randrange(1, len(ids))] = rng.choice(("0", "-3", "999999", "2147483647", "1.5", "x"))
                elif kind == "degenerate":
                    ids[2] = ids[1]
                else:
                    ids[2], ids[3] = ids[3], ids[2]
                lines[k] = ", ".join(ids)
    elif kind == "coincident":
        nodes = _node_lines(lines)
        if len(nodes) >= 2:
            a, b = rng.sample(nodes, 2)
            lines[b] = lines[b].split(",")[0] + "," + ",".join(lines[a].split(",")[1:])
    elif kind == "flip":
        line = lines[k]
        if line:
            i = rng.randrange(len(line))
            lines[k] = line[:i] + chr(rng.randrange(32, 127)) + line[i + 1:]
    data = ("\n".join(lines) + "\n").encode()
    if kind == "garbage":
        at = rng.randrange(len(data) + 1)
        data = data[:at] + bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))) + data[at:]
    return data, f"{kind} line {k + 1}"


@dataclass
class Outcome:
    name: str
    mutation: str
    code: int | None          # None: hung (timeout)
    located: bool             # an exit 2 whose message names FILE:LINE
    message: str


@dataclass
class Summary:
    inputs: int = 0
    codes: Counter = field(default_factory=Counter)
    crashes: list[Outcome] = field(default_factory=list)
    hangs: list[Outcome] = field(default_factory=list)
    unlocated: list[Outcome] = field(default_factory=list)
    failures: list[Outcome] = field(default_factory=list)   # exit 4

    def add(self, outcome: Outcome) -> None:
        self.inputs += 1
        self.codes[outcome.code] += 1
        if outcome.code is None:
            self.hangs.append(outcome)
        elif outcome.code not in EXIT_CODES:
            self.crashes.append(outcome)
        elif outcome.code == 2 and not outcome.located:
            self.unlocated.append(outcome)
        elif outcome.code == 4:
            self.failures.append(outcome)

    def line(self) -> str:
        codes = ", ".join(f"{EXIT_CODES.get(c, 'hang' if c is None else f'crash {c}')} {n}"
                          for c, n in sorted(self.codes.items(), key=lambda item: (item[0] is None, item[0] or 0)))
        return (f"fuzz: {self.inputs} inputs; {codes}; crashes {len(self.crashes)}, hangs {len(self.hangs)}, "
                f"rejections naming a line {self.codes[2] - len(self.unlocated)} of {self.codes[2]}, "
                f"other failures {len(self.failures)}")


def run_one(engine: str, data: bytes, name: str, mutation: str, scratch: Path, timeout_s: float = TIMEOUT_S) -> Outcome:
    deck = scratch / f"{name}.inp"
    deck.write_bytes(data)
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", OMP_NUM_THREADS="1")
    try:
        done = subprocess.run([engine, str(deck), "-o", str(scratch / f"{name}.out"), "--threads", "1", "--quiet"],
                              capture_output=True, timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return Outcome(name, mutation, None, False, "timeout")
    message = done.stderr.decode(errors="replace").strip().splitlines()
    last = message[-1] if message else ""
    return Outcome(name, mutation, done.returncode, bool(LOCATED.search(last)), last)


def fuzz(engine: str, inputs: int, seed: int, workers: int = 2, keep: Path | None = None,
         timeout_s: float = TIMEOUT_S) -> Summary:
    """Run `inputs` mutated decks; each input's mutation depends only on (seed, its index)."""
    texts = {name: (CORPUS_DIR / name).read_text() for name in CORPUS}
    summary = Summary()

    def one(index: int) -> tuple[Outcome, bytes]:
        rng = random.Random(f"{seed}-{index}")
        source = rng.choice(CORPUS)
        data, what = mutate(texts[source], rng)
        for _ in range(rng.choice((0, 0, 0, 1, 2))):   # now and then, several faults at once
            more, extra = mutate(data.decode(errors="replace"), rng)
            data, what = more, f"{what}; {extra}"
        with tempfile.TemporaryDirectory(prefix="calfit-fuzz-") as scratch:
            return run_one(engine, data, f"input{index}", f"{source}: {what}", Path(scratch), timeout_s), data

    with ThreadPoolExecutor(max_workers=workers) as pool:
        for outcome, data in pool.map(one, range(inputs)):
            summary.add(outcome)
            if keep is not None and (outcome.code is None or outcome.code not in EXIT_CODES):
                keep.mkdir(parents=True, exist_ok=True)
                (keep / f"{outcome.name}.inp").write_bytes(data)
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--engine", help="calfit-fe to fuzz (default: the installed one)")
    parser.add_argument("--keep", type=Path, default=Path("fuzz-findings"), help="where crashing inputs go")
    parser.add_argument("--timeout", type=float, default=TIMEOUT_S, help="seconds before an input counts as a hang")
    args = parser.parse_args(argv)
    engine = args.engine
    if engine is None:
        sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
        from orchestrator.engine.locate import find_engine
        engine = str(find_engine())
    summary = fuzz(engine, args.inputs, args.seed, args.workers, args.keep, args.timeout)
    print(summary.line())
    for outcome in summary.crashes + summary.hangs + summary.unlocated + summary.failures:
        print(f"  {outcome.name} ({outcome.mutation}): exit {outcome.code}: {outcome.message}")
    return 1 if summary.crashes or summary.hangs or summary.unlocated else 0


if __name__ == "__main__":
    sys.exit(main())
