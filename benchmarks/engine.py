"""Speed and memory of calfit-fe on the leg-like slice, and the same deck in CalculiX.

    cd /work/main && .venv/bin/python benchmarks/engine.py [--runs 5] [--ccx-runs 5] [--no-ccx]
                                                          [--dofs 1000,3000,...,200000] [--threads N]
                                                          [--only paper,follower,hybrid,garment,sensitivities,
                                                                  grouped,second-paper,scaling,compression]

1. The leg-like slice at the size of the second paper (about 5,500 T6 elements, about
   25,000 DOF; that paper reports about 1,200 s per FE solve): median wall time of
   calfit-fe over --runs runs, the median of CalculiX (`ccx -i`, single thread, the same
   standard-keyword deck) in the same run, and their ratio (target: calfit-fe at least
   10x faster; target: under 0.5 s). Then FElupe (pip install felupe) as a second peer
   on the same mesh: NEO HOOKE tissues in both (C10 and D1 = 1/Kv of DEFAULT_MATERIALS;
   FElupe NeoHooke mu = 2 C10, bulk = 2/D1 is the same energy), plane strain, bones
   clamped, the 20 mmHg follower pressure on the skin faces (FElupe has no triangle
   boundary region, so the skin faces are built here for SolidBodyPressure), one step,
   FElupe's own Newton (Job): median wall time of calfit-fe on that deck and of FElupe's
   solve alone (Job.evaluate, not the import or the model setup), their ratio, the
   Newton iterations of each and max |u_fe - u_felupe| / max |u|. FElupe 11.3.0's
   QuadraticTriangle.gradient is wrong, so FElupe runs with the exact T6 gradient (the
   script says when the installed FElupe's differs).
1b. The same slice under a non-uniform follower pressure (1 + 0.5 cos theta + 0.2 sin 2 theta around the leg) in
   6 increments: the tangent is unsymmetric. calfit-fe and CalculiX on the same deck, their ratio and agreement.
2. The same slice nearly incompressible (NEO HOOKE, D1 for nu = 0.499, CPE6H Taylor-Hood
   elements): median wall time and its DOF count (displacement and pressure).
3. The leg slice under the explicit garment band (orchestrator.meshing.garment_band,
   templates/leg_garment.inp.j2: inflate, let go, contact + release, settle), frictionless and with friction: on
   --garment-elements T6 elements (1,000: 5k DOF) median wall time and Newton iterations per step (targets: at
   most 40 for the release, contact and settling, under 2 s); on --garment-ccx-elements (2,000) the same beside
   CalculiX, with their ratio and agreement (leg and band apart too); with friction both run CalculiX's
   node-to-surface contact (whose friction gives the slider's closed form) with the release in 200 increments
   (tests/support/leg_decks.py garment_friction_text; solver_cpp/README.md, Contact).
4. Parameter sensitivities on the paper-size slice under a Laplace-law garment (uniform
   tension, a TYPE=FOURIER profile with no terms): *SENSITIVITY for 10 parameters (C10
   and D1 of fat and muscle, the garment TENSION, profile coefficients A1, B1, A2, B2,
   A3 at 0): median wall time of the solve (the engine's wall time without the
   sensitivities), of the sensitivities (summary time_s.sensitivity) and their ratio
   (target: under 20 %).
4b. Fitted constants shared by many material groups under the band with friction (`--only grouped`): calfit's
   deck, one `*SENSITIVITY, NAME=` column per parameter, against the same lines one column each; wall times, their
   ratio and the columns' agreement (measured on 994 CPE6 with 94 groups, beside two other jobs: the local probe's
   98 parameters over 188 lines 1.38 x faster, 11 region factors 2.53 x; agreement 1e-10).
4c. The second paper's model as calfit fits it (`--only second-paper`): Bouten and Drapier's Table 1 tissues,
   incompressible on CPE6H (`phantom.truths.SECOND_PAPER_TISSUES`), under the band with friction 0.3, the constants'
   sensitivities carried along the put-on, on --second-paper-elements T6 (the size a diagnosis's discretization
   check asked for): median wall time, Newton iterations and factorizations. Every Newton iteration there is an LU
   of an unsymmetric saddle-point matrix; with UMFPACK's symmetric strategy (solver_cpp/src/solver/sparse_system.cpp)
   a run of a diagnosis's deck (20.5k unknowns, 120 factorizations) took 18.9 s of CPU against 37.7 s with its
   automatic choice (the same engine otherwise, beside two other jobs; displacements equal to 3e-12 mm), and this
   section 34.9 s against 66.7 s with the engine before it (CALFIT_FE, the same load).
5. Scaling from 1k to 200k DOF: wall time and peak resident memory of each calfit-fe
   process (os.wait4 resource usage of that child, i.e. /usr/bin/time -v's "Maximum
   resident set size"; target: under 1 GiB at 200k DOF). After the table: the exponent p
   of wall time ~ N^p (least squares of log t on log N over the sizes that converged;
   goal: N^1.2; the fixed cost of a process flattens it at small sizes) and the peak
   memory of the largest size against the 1 GiB target.
6. Prescribed displacements (issue 18): a 50 mm square pushed down by 2, 10 and 20 % at
   3.4k and 22k DOF, Newton iterations per increment, beside CalculiX and FElupe (pip
   install felupe) on the same mesh, agreement with CalculiX (targets: <= 5 iterations
   per increment, >= 10x CalculiX, faster than FElupe).

The deck comes from orchestrator.meshing.leg_slice_deck (Table 2 materials of Avril et
al., bones clamped, 20 mmHg follower pressure on the skin). This script prints; it never
asserts wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))

from engine_run import parse_ccx_dat  # noqa: E402
from leg_decks import (  # noqa: E402
    GARMENT_FRICTION,
    garment_friction_text,
    garment_text,
    nonuniform_follower_text,
)

from orchestrator.engine.locate import find_engine  # noqa: E402
from orchestrator.meshing import (
    DEFAULT_MATERIALS,
    DEFAULT_PRESSURE_MPA,
    garment_band,
    leg_slice_deck,
    leg_slice_mesh,
    leg_slice_mesh_for_dof,
)
from orchestrator.meshing.garment import neo_hooke_D1  # noqa: E402

NEARLY_INCOMPRESSIBLE_NU = 0.499

PAPER_SECONDS = 1200.0  # second paper, per FE solve of its ~25k-DOF model
TARGET_25K_S = 0.5
TARGET_SPEEDUP = 10.0
TARGET_200K_BYTES = 1 << 30
TARGET_SCALING_EXPONENT = 1.2   # wall time ~ N^1.2 over the scaling sizes
DEFAULT_DOFS = (1_000, 3_000, 10_000, 25_000, 50_000, 100_000, 200_000)


# A small launcher process measures the engine: the kernel counts a child's peak RSS from
# the moment it is forked, so forking the engine straight from this (large) Python process
# would report at least this process's own RSS. The launcher (python -S, a few MiB) forks
# and execs the command, waits with os.wait4 and prints the child's rusage as JSON.
_LAUNCHER = r"""
import json, os, signal, sys, time
out, cwd, limit, argv = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4:]
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    os.chdir(cwd)
    fd = os.open(os.path.join(cwd, "run.log"), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(fd, 1); os.dup2(fd, 2)
    try:
        os.execvp(argv[0], argv)
    finally:
        os._exit(127)
signal.signal(signal.SIGALRM, lambda *_: os.kill(pid, signal.SIGKILL))
signal.alarm(limit)
_, status, ru = os.wait4(pid, 0)
wall = time.perf_counter() - t0
with open(out, "w") as f:
    json.dump({"wall_s": wall, "peak_rss": ru.ru_maxrss * 1024, "exit": os.waitstatus_to_exitcode(status),
               "cpu_s": ru.ru_utime + ru.ru_stime}, f)
"""


def run_measured(cmd: list[str], cwd: Path, timeout: float, env: dict | None = None) -> dict:
    """Run cmd in cwd; wall time, peak RSS (bytes) of that process (os.wait4), exit code."""
    result = cwd / "rusage.json"
    launcher = [sys.executable, "-S", "-c", _LAUNCHER, str(result), str(cwd), str(int(timeout)), *cmd]
    proc = subprocess.run(launcher, env=env, timeout=timeout + 60, capture_output=True, text=True)
    if proc.returncode != 0 or not result.is_file():
        return {"wall_s": float("nan"), "peak_rss": float("nan"), "exit": -1, "cpu_s": float("nan")}
    return json.loads(result.read_text())


def run_engine(deck: Path, threads: int | None, timeout: float) -> dict:
    outdir = deck.parent / "out"
    cmd = [str(find_engine()), str(deck), "-o", str(outdir), "--quiet"]
    if threads:
        cmd += ["--threads", str(threads)]
    res = run_measured(cmd, deck.parent, timeout)
    summary = outdir / "summary.json"
    if summary.is_file():
        s = json.loads(summary.read_text())
        res["status"] = s.get("status")
        res["engine_wall_s"] = s.get("wall_time_s")
        res["newton"] = sum(st.get("newton_iterations", 0) for st in s.get("steps", []))
        res["increments"] = sum(st.get("n_increments", 0) for st in s.get("steps", []))
        res["linear_solver"] = s.get("linear_solver")
        res["solves"] = s.get("linear_solves", {})
        res["threads"] = s.get("threads")
    return res


def run_ccx(deck: Path, timeout: float) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_STIFFNESS="1", CCX_NPROC_EQUATION_SOLVER="1")
    return run_measured(["ccx", "-i", deck.stem], deck.parent, timeout, env)


def fmt_bytes(n: float) -> str:
    return f"{n / 2**20:8.1f} MiB"


def paper_size(args, root: Path) -> None:
    mesh = leg_slice_mesh(5500, order=2)
    print(f"leg-like slice at the second paper's size: {len(mesh.elements)} CPE6 elements, "
          f"{len(mesh.nodes)} nodes, {mesh.n_dof} DOF")
    fe_times, rss = [], []
    for k in range(args.runs):
        d = root / f"fe{k}"
        d.mkdir()
        r = run_engine(_paper_deck(d, mesh), args.threads, args.timeout)
        if r["exit"] != 0:
            print(f"  calfit-fe run {k}: exit {r['exit']} (see {d / 'run.log'}):")
            print("   ", (d / "run.log").read_text()[-1500:])
            return
        fe_times.append(r["wall_s"])
        rss.append(r["peak_rss"])
        last = r
    fe_med = statistics.median(fe_times)
    print(f"  calfit-fe  median wall {fe_med:8.3f} s over {args.runs} runs "
          f"(min {min(fe_times):.3f}, max {max(fe_times):.3f}); peak RSS {fmt_bytes(max(rss))}; "
          f"{last.get('increments')} increments, {last.get('newton')} Newton iterations, "
          f"solver {last.get('linear_solver')}, {last.get('threads')} thread(s)    target < {TARGET_25K_S} s")
    print(f"  the second paper: about {PAPER_SECONDS:.0f} s per solve -> {PAPER_SECONDS / fe_med:,.0f}x")
    versus_ccx(args, root, "ccx", lambda folder: _paper_deck(folder, mesh), root / "fe0", fe_med)
    _paper_felupe(args, root, mesh)


def versus_ccx(args, root: Path, name: str, write_deck, fe_dir: Path, fe_med: float, timeout: float | None = None,
               parts: dict[str, int] | None = None, runs: int | None = None) -> None:
    """CalculiX on the deck that write_deck(folder) writes, --ccx-runs times: its median wall time, the agreement
    of its displacements with calfit-fe's run in fe_dir and the ratio of the medians. A run killed at `timeout`
    seconds (default --timeout) is reported as such, with the ratio it bounds."""
    if args.no_ccx or shutil.which("ccx") is None:
        print("  ccx: skipped" + ("" if args.no_ccx else " (not installed)"))
        return
    limit = timeout or args.timeout
    ccx_times = []
    for k in range(runs or args.ccx_runs):
        d = root / f"{name}{k}"
        d.mkdir()
        r = run_ccx(write_deck(d), limit)
        if r["exit"] != 0:
            killed = r["wall_s"] >= limit - 1 or r["exit"] in (-9, 137)
            log = d / "run.log"
            errors = [line.strip() for line in log.read_text(errors="replace").splitlines()
                      if "*ERROR" in line] if log.is_file() else []
            print(f"  ccx run {k}: " + (f"not finished within {limit:.0f} s: ratio ccx / calfit-fe > "
                                        f"{limit / fe_med:.0f}x" if killed else
                                        f"exit {r['exit']} after {r['wall_s']:.0f} s"
                                        + (f" ({errors[0]})" if errors else "")) + ccx_reached(d / "leg.sta"))
            return
        ccx_times.append(r["wall_s"])
    ccx_med = statistics.median(ccx_times)
    print(f"  ccx 2.20   median wall {ccx_med:8.3f} s over {len(ccx_times)} runs (single thread), same deck")
    agreement(fe_dir, root / f"{name}0", parts)
    print(f"  ratio ccx / calfit-fe = {ccx_med / fe_med:6.1f}x    target >= {TARGET_SPEEDUP:.0f}x")


def ccx_reached(status: Path) -> str:
    """Where a CalculiX run got to, from the last line of its .sta file (step, increment, attempt, iterations,
    total time, step time, increment size)."""
    rows = [line.split() for line in status.read_text().splitlines()[2:]] if status.is_file() else []
    if not rows or len(rows[-1]) < 7:
        return ""
    step, _, _, _, _, step_time, increment = rows[-1][:7]
    return f"; its last increment: step {step}, step time {float(step_time):.4g}, size {float(increment):.2e}"


def _paper_deck(folder: Path, mesh) -> Path:
    leg_slice_deck(folder / "leg.inp", mesh=mesh, include_mesh=False)
    return folder / "leg.inp"


# --- FElupe as a second peer on the paper-size slice -------------------------------------------------------

FELUPE_INCREMENTS = 1   # as the deck's *STATIC 1, 1: FElupe's Newton converges the 20 mmHg in one increment
# face k of an element joins corners k and k+1: these node orders make face k the element's edge 1-2 (s = 0),
# keeping the element counter-clockwise (corners and mid-side nodes rotate together)
FACE_FIRST_ORDER = {1: [0, 1, 2, 3, 4, 5], 2: [1, 2, 0, 4, 5, 3], 3: [2, 0, 1, 5, 3, 4]}


def paper_neo_hooke_materials() -> dict[str, tuple[str, tuple[float, float]]]:
    """NEO HOOKE (C10, D1) of each tissue of DEFAULT_MATERIALS, the law both calfit-fe and FElupe have.

    The engine's NEO HOOKE is CalculiX's, W = C10 (I1bar - 3) + (J - 1)^2 / D1 (initial bulk modulus 2 / D1).
    DEFAULT_MATERIALS already give it with D1 = 1 / Kv, the D1 whose initial bulk modulus 2 Kv is that of the
    Avril law (orchestrator/meshing/leg_slice.py); an AVRIL entry (C10, Kv[, C20]) is mapped the same way."""
    materials = {}
    for name, (law, constants) in DEFAULT_MATERIALS.items():
        if law == "NEO HOOKE":
            materials[name] = (law, (constants[0], constants[1]))
        elif law == "AVRIL":
            materials[name] = ("NEO HOOKE", (constants[0], 1.0 / constants[1]))
        else:
            raise ValueError(f"no NEO HOOKE equivalent of {law} ({name})")
    return materials


def _felupe_quadratic_triangle(fem):
    """FElupe's 6-node triangle with the exact shape-function gradient, and whether FElupe's own differs.

    FElupe 11.3.0's QuadraticTriangle.gradient has d h6/ds = 4 (1 - 2 r - s) where it should be 4 (1 - r - 2 s)
    (and the corner terms built from it are off too): its T6 solutions then differ from any other T6 code by
    about 0.5 % on the paper-size slice (1.6 % on a coarser one, shrinking with the mesh size like a
    discretization error). The shape functions themselves are right, so only gradient is replaced."""

    class ExactGradientQuadraticTriangle(fem.QuadraticTriangle):
        def gradient(self, rs):
            r, s = rs
            t = 1.0 - r - s
            return np.array([[1.0 - 4.0 * t, 1.0 - 4.0 * t], [4.0 * r - 1.0, 0.0], [0.0, 4.0 * s - 1.0],
                             [4.0 * (t - r), -4.0 * r], [4.0 * s, 4.0 * r], [-4.0 * s, 4.0 * (t - s)]])

    element = ExactGradientQuadraticTriangle()
    probe = np.array([0.2, 0.3])
    library_is_wrong = not np.allclose(fem.QuadraticTriangle().gradient(probe), element.gradient(probe))
    return element, library_is_wrong


def _felupe_leg_model(fem, mesh, materials, element):
    """The paper-size slice in FElupe: the unknowns, the items (one NeoHooke body per tissue, the skin pressure)
    and a one-step Job that ramps the pressure over FELUPE_INCREMENTS increments with the bones clamped."""
    quadrature = fem.TriangleQuadrature(order=2)   # the 3-point rule of CPE6 (the engine's default)
    whole = fem.Region(fem.Mesh(mesh.nodes, mesh.elements, "triangle6"), element, quadrature)
    unknowns = fem.FieldContainer([fem.FieldPlaneStrain(whole, dim=2)])
    bodies = []
    for name, cells in mesh.element_sets().items():
        C10, D1 = materials[name][1]
        tissue = fem.Region(fem.Mesh(mesh.nodes, mesh.elements[cells], "triangle6"), element, quadrature)
        # NeoHooke: W = mu/2 (I1bar - 3) + bulk/2 (J - 1)^2, the engine's NEO HOOKE with mu = 2 C10, bulk = 2 / D1
        bodies.append(fem.SolidBody(fem.NeoHooke(mu=2.0 * C10, bulk=2.0 / D1),
                                    fem.FieldContainer([fem.FieldPlaneStrain(tissue, dim=2)])))

    # FElupe 11.3 has boundary regions for quads and hexahedra only, so the skin faces are made here: each
    # skin element with its loaded face as edge s = 0, a 3-point Gauss rule on that edge (the engine's), and the
    # area vectors dA = outward normal x |dX/dr| x weight that SolidBodyPressure (ensure_3d) expects. The
    # pressure then acts on the deformed face, J F^-T dA: a follower load, as *DLOAD.
    gauss = fem.GaussLegendre(order=2, dim=1)
    on_edge = fem.quadrature.Scheme(np.column_stack([(gauss.points[:, 0] + 1.0) / 2.0, np.zeros(len(gauss.points))]),
                                    gauss.weights / 2.0)
    loaded = np.array([mesh.elements[e][FACE_FIRST_ORDER[face]] for e, face in mesh.skin_faces.tolist()])
    skin = fem.Region(fem.Mesh(mesh.nodes, loaded, "triangle6"), element, on_edge)
    along = skin.dXdr[:, 0]   # dX/dr on the edge; the tissue is on its left, so (dy, -dx) points outwards
    skin.dA = np.stack([along[1], -along[0], np.zeros_like(along[0])]) * on_edge.weights[:, None]
    skin.dV = np.linalg.norm(skin.dA, axis=0)
    skin.normals = skin.dA / skin.dV
    pressure = fem.SolidBodyPressure(fem.FieldContainer([fem.FieldPlaneStrain(skin, dim=2)]))

    bones = np.zeros(len(mesh.nodes), dtype=bool)
    bones[mesh.node_sets["BONES"]] = True
    step = fem.Step(items=[*bodies, pressure],
                    ramp={pressure: DEFAULT_PRESSURE_MPA * np.arange(1, FELUPE_INCREMENTS + 1) / FELUPE_INCREMENTS},
                    boundaries={"bones": fem.Boundary(unknowns[0], mask=bones)})
    return unknowns, fem.Job(steps=[step])


def _paper_felupe(args, root: Path, mesh) -> None:
    """calfit-fe and FElupe on the paper-size slice with NEO HOOKE tissues: wall times, Newton iterations and
    agreement of the displacements."""
    try:
        import felupe as fem
    except ImportError:
        print("  felupe: skipped (pip install felupe)")
        return
    import time

    materials = paper_neo_hooke_materials()
    laws = ", ".join(f"{name} C10 = {C10:g} MPa, D1 = {D1:.4g} /MPa" for name, (_, (C10, D1)) in materials.items())
    print(f"  FElupe on the same mesh, NEO HOOKE in both ({laws}), plane strain, bones clamped, follower pressure "
          f"{DEFAULT_PRESSURE_MPA:.4g} MPa on the skin, one step:")

    def write(folder: Path) -> Path:
        leg_slice_deck(folder / "leg.inp", mesh=mesh, include_mesh=False, materials=materials)
        return folder / "leg.inp"

    result = _median_runs(args, root, "neo", write)
    if not result:
        return
    fe_times, fe_last = result
    fe_med = statistics.median(fe_times)
    print(f"    calfit-fe  median wall {fe_med:8.3f} s over {len(fe_times)} runs (whole process: start, parse, solve, "
          f"output); {fe_last.get('increments')} increment(s), {fe_last.get('newton')} Newton iterations")

    element, library_is_wrong = _felupe_quadratic_triangle(fem)
    if library_is_wrong:
        print(f"    note: FElupe {fem.__version__}'s QuadraticTriangle.gradient is wrong (d h6/ds); FElupe runs here "
              "with the exact T6 gradient")
    setup_times, solve_times = [], []
    for _ in range(args.runs):
        began = time.perf_counter()
        unknowns, job = _felupe_leg_model(fem, mesh, materials, element)
        built = time.perf_counter()
        try:
            job.evaluate(x0=unknowns, verbose=0)
        except Exception as error:   # FElupe's own failure is a result of the comparison, not of this script
            print(f"    FElupe failed: {str(error)[:200]}")
            return
        solve_times.append(time.perf_counter() - built)
        setup_times.append(built - began)
    iterations = [len(norms) for norms in job.fnorms]
    felupe_med = statistics.median(solve_times)
    print(f"    FElupe {fem.__version__} median {felupe_med:8.3f} s over {len(solve_times)} runs (Job.evaluate only: "
          f"not the import, not the model setup, median {statistics.median(setup_times):.3f} s); "
          f"{len(iterations)} increment(s), {sum(iterations)} Newton iterations {iterations}, "
          "linear solver SciPy spsolve")
    print(f"    ratio FElupe / calfit-fe = {felupe_med / fe_med:6.1f}x")

    ours = np.load(sorted((root / "neo0" / "out").glob("step-*.u.npy"))[-1])
    theirs = unknowns[0].values[ours[:, 0].astype(int) - 1]   # engine rows are 1-based node ids
    scale = np.abs(ours[:, 3:5]).max()
    print(f"    agreement: max |u_fe - u_felupe| = {np.abs(ours[:, 3:5] - theirs).max() / scale:.2e} "
          f"of max |u| = {scale:.4g} mm    (the same model: well under 0.5 %)")


def agreement(fe_dir: Path, ccx_dir: Path, parts: dict[str, int] | None = None) -> None:
    """Max nodal displacement difference calfit-fe vs ccx on the benchmark deck, of the max |u| of all nodes and,
    with parts (name -> number of nodes, in node order), of each part's own."""
    table = sorted((fe_dir / "out").glob("step-*.u.npy"))
    dat = ccx_dir / "leg.dat"
    if not table or not dat.is_file():
        return
    u = np.load(table[-1])
    disp = parse_ccx_dat(dat)
    u_ccx = np.array([disp[int(i)][:2] for i in u[:, 0]])
    scale = np.abs(u_ccx).max()
    print(f"  agreement: max |u_fe - u_ccx| = {np.abs(u[:, 3:5] - u_ccx).max() / scale:.2e} of max |u| = {scale:.4g} mm")
    start = 0
    for part, count in (parts or {}).items():
        rows = slice(start, start + count)
        start += count
        part_scale = np.abs(u_ccx[rows]).max()
        print(f"    {part}: {np.abs(u[rows, 3:5] - u_ccx[rows]).max() / part_scale:.2e} of its max |u| = "
              f"{part_scale:.4g} mm")


def _median_runs(args, root: Path, name: str, write_deck) -> tuple[list[float], dict] | None:
    """Run the deck that write_deck(folder) writes --runs times; None (and the log) on a failure."""
    times, last = [], {}
    for k in range(args.runs):
        d = root / f"{name}{k}"
        d.mkdir()
        deck = write_deck(d)
        last = run_engine(deck, args.threads, args.timeout)
        if last["exit"] != 0:
            print(f"  {name} run {k}: exit {last['exit']} (see {d / 'run.log'}):")
            print("   ", (d / "run.log").read_text()[-1500:])
            return None
        times.append(last["wall_s"])
    return times, last


def _report(label: str, times: list[float], last: dict, n_dof: int) -> None:
    print(f"  {label}: {n_dof} DOF, median wall {statistics.median(times):8.3f} s over {len(times)} runs "
          f"(min {min(times):.3f}, max {max(times):.3f}); {last.get('increments')} increments, "
          f"{last.get('newton')} Newton iterations, solver {last.get('linear_solver')}, "
          f"{last.get('solves', {}).get('factorized', '?')} factorizations, "
          f"{last.get('solves', {}).get('reused', '?')} solves on an earlier factor, "
          f"{last.get('solves', {}).get('gmres_steps', '?')} GMRES steps")


FOLLOWER_INCREMENTS = 6


def write_leg_deck(folder: Path, text: str) -> Path:
    """A deck text written as folder/leg.inp, once per run (the text is made once per deck)."""
    (folder / "leg.inp").write_text(text)
    return folder / "leg.inp"


def follower(args, root: Path) -> None:
    mesh = leg_slice_mesh(5500, order=2)
    print(f"\nleg-like slice under a non-uniform follower pressure ({mesh.n_dof} DOF, at most 1/{FOLLOWER_INCREMENTS} "
          "of the load per increment; unsymmetric tangent)")
    text = nonuniform_follower_text(mesh, FOLLOWER_INCREMENTS)   # tests/support/leg_decks.py
    result = _median_runs(args, root, "follower", lambda folder: write_leg_deck(folder, text))
    if not result:
        return
    times, last = result
    _report("calfit-fe", times, last, mesh.n_dof)
    versus_ccx(args, root, "follower-ccx", lambda folder: write_leg_deck(folder, text), root / "follower0",
               statistics.median(times))


def nearly_incompressible(args, root: Path) -> None:
    mesh = leg_slice_mesh(5500, order=2)
    materials = {name: ("NEO HOOKE", (C10, neo_hooke_D1(C10, NEARLY_INCOMPRESSIBLE_NU)))
                 for name, (_, (C10, _)) in DEFAULT_MATERIALS.items()}
    n_pressure = len(np.unique(mesh.elements[:, :3]))

    def write(folder: Path) -> Path:
        leg_slice_deck(folder / "leg.inp", mesh=mesh, include_mesh=False, materials=materials)
        text = (folder / "leg.inp").read_text().replace("TYPE=CPE6,", "TYPE=CPE6H,")
        (folder / "leg.inp").write_text(text)
        return folder / "leg.inp"

    print(f"\nleg-like slice, nearly incompressible (nu = {NEARLY_INCOMPRESSIBLE_NU}), CPE6H")
    result = _median_runs(args, root, "hybrid", write)
    if result:
        _report(f"CPE6H ({mesh.n_dof} displacement + {n_pressure} pressure)", *result, mesh.n_dof + n_pressure)


TARGET_GARMENT_ITERATIONS = 40   # Newton iterations of the release and contact (step 3) and the settling (step 4)
TARGET_GARMENT_S = 2.0
# CalculiX's node-to-surface contact took 485 s on the 2,000-element garment with friction, its release in 200
# increments (one run, the machine loaded); a bound keeps the benchmark finite
GARMENT_CCX_TIMEOUT_S = 1800.0


def explicit_garment(args, root: Path) -> None:
    """The garment's targets on the --garment-elements deck (5k DOF: Newton iterations and wall time), then the same
    put-on on the --garment-ccx-elements deck beside CalculiX (ratio and agreement): with 1,000 elements the two
    contact discretizations differ by 0.62 % of max |u|, with 2,000 by 0.31 % (tests/support/ccx_reference). With friction
    CalculiX runs the deck of tests/support/leg_decks.py garment_friction_text (node-to-surface contact, the release in 200
    increments, where its face-to-face friction depends on its increments), and so does calfit-fe beside it."""
    for n_elements, with_ccx in ((args.garment_elements, False), (args.garment_ccx_elements, True)):
        leg = leg_slice_mesh(n_elements, order=2)
        band = garment_band(leg)
        n_dof = leg.n_dof + 2 * len(band.nodes)
        print(f"\nleg-like slice under the explicit garment band ({len(leg.elements)} CPE6 + {len(band.elements)} "
              f"band elements, {n_dof} DOF; inflate, let go, contact + release, settle): penalty contact, "
              f"frictionless and with friction mu = {GARMENT_FRICTION}" + (", beside CalculiX" if with_ccx else ""))
        for mu in (0.0, GARMENT_FRICTION):
            name, text = f"garment{n_elements}-mu{mu:g}", garment_text(leg, band, mu)   # tests/support/leg_decks.py
            result = _median_runs(args, root, name, lambda folder: write_leg_deck(folder, text))
            if not result:
                continue
            times, last = result
            _report(f"mu = {mu:g}", times, last, n_dof)
            steps = json.loads((root / f"{name}0" / "out" / "summary.json").read_text())["steps"]
            per_step = [step["newton_iterations"] for step in steps]
            put_on = sum(per_step[2:])
            print(f"    Newton iterations per step (inflate, let go, release + contact, settle): {per_step}; release, "
                  f"contact and settling {put_on}" + ("" if with_ccx else f"    target <= {TARGET_GARMENT_ITERATIONS}, "
                                                      f"< {TARGET_GARMENT_S:.0f} s"))
            if with_ccx and mu == 0:
                versus_ccx(args, root, f"{name}-ccx", lambda folder: write_leg_deck(folder, text),
                           root / f"{name}0", statistics.median(times), timeout=GARMENT_CCX_TIMEOUT_S,
                           parts={"leg": len(leg.nodes), "band": len(band.nodes)})
            elif with_ccx:
                garment_friction_versus_ccx(args, root, leg, band, n_dof)


def garment_friction_versus_ccx(args, root: Path, leg, band, n_dof: int) -> None:
    """calfit-fe and CalculiX on the garment deck with friction whose release is converged in its increments
    (tests/support/leg_decks.py garment_friction_text: CalculiX's node-to-surface contact, the release in 200 increments)."""
    name, text = f"garment{len(leg.elements)}-friction-reference", garment_friction_text(leg, band)
    print(f"  mu = {GARMENT_FRICTION:g} beside CalculiX: node-to-surface contact in both (CalculiX's face-to-face "
          "friction depends on its increments: tests/engine/test_engine_friction.py), the release in 200 increments in both")
    result = _median_runs(args, root, name, lambda folder: write_leg_deck(folder, text))
    if not result:
        return
    times, last = result
    _report("calfit-fe", times, last, n_dof)
    versus_ccx(args, root, f"{name}-ccx", lambda folder: write_leg_deck(folder, text), root / f"{name}0",
               statistics.median(times), timeout=GARMENT_CCX_TIMEOUT_S,
               parts={"leg": len(leg.nodes), "band": len(band.nodes)}, runs=1)


SENSITIVITY_PARAMETERS = [
    "MATERIAL, FAT, C10", "MATERIAL, FAT, D1", "MATERIAL, MUSCLE, C10", "MATERIAL, MUSCLE, D1", "TENSION, SKIN",
    "PROFILE, GARMENT, A1", "PROFILE, GARMENT, B1", "PROFILE, GARMENT, A2", "PROFILE, GARMENT, B2", "PROFILE, GARMENT, A3",
]
TARGET_SENSITIVITY_RATIO = 0.20
GARMENT_TENSION = 0.16  # N/mm


def sensitivities(args, root: Path) -> None:
    mesh = leg_slice_mesh(5500, order=2)

    def write(folder: Path) -> Path:
        deck = folder / "leg.inp"
        leg_slice_deck(deck, mesh=mesh, include_mesh=False, laplace_tension=GARMENT_TENSION)
        text = deck.read_text().replace("*STEP,", "*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n*STEP,", 1)
        text = text.replace(f"TENSION={GARMENT_TENSION:.10g}", f"TENSION={GARMENT_TENSION:.10g}, PROFILE=GARMENT")
        deck.write_text(text + "*SENSITIVITY\n" + "\n".join(SENSITIVITY_PARAMETERS) + "\n")
        return deck

    print(f"\nsensitivities, {len(SENSITIVITY_PARAMETERS)} parameters, {mesh.n_dof} DOF "
          f"(leg slice, Laplace-law garment, {len(mesh.elements)} CPE6)")
    solve, sens, newton = [], [], []
    for k in range(args.runs):
        d = root / f"sens{k}"
        d.mkdir()
        r = run_engine(write(d), args.threads, args.timeout)
        if r["exit"] != 0:
            print(f"  run {k}: exit {r['exit']} (see {d / 'run.log'}):")
            print("   ", (d / "run.log").read_text()[-1500:])
            return
        summary = json.loads((d / "out" / "summary.json").read_text())
        times = summary["time_s"]
        sens.append(times["sensitivity"])
        solve.append(summary["wall_time_s"] - times["sensitivity"])
        newton.append(times["assembly"] + times["factorization"])
    ratios = [s / t for s, t in zip(sens, solve)]
    print(f"  solve (wall, without sensitivities)  median {statistics.median(solve):8.3f} s over {args.runs} runs "
          f"(Newton: assembly + factorization {statistics.median(newton):.3f} s); solver {summary['linear_solver']}")
    print(f"  sensitivities ({len(SENSITIVITY_PARAMETERS)} parameters)     median {statistics.median(sens):8.3f} s")
    print(f"  ratio sensitivities / solve          median {100 * statistics.median(ratios):7.1f} % "
          f"(min {100 * min(ratios):.1f}, max {100 * max(ratios):.1f}); of the Newton part "
          f"{100 * statistics.median([s / n for s, n in zip(sens, newton)]):.1f} %    "
          f"target < {100 * TARGET_SENSITIVITY_RATIO:.0f} %")


def grouped_sensitivities(args, root: Path) -> None:
    """4b. Fitted constants shared by many material groups, under the band with friction 0.3: the diagnosis's probe of
    a local stiffness change (`effects.LOCAL_PROBE`: every group its own factor too) and a model with a few region
    factors over the groups (`heterogeneity`, as a patch's refit has one). The deck that calfit writes (one
    `*SENSITIVITY, NAME=` column per parameter) against the same member lines asked one column each, as before such
    blocks: wall time of the whole run (the path carries every column through friction) and
    max |du_combined - sum w du_line| / max |du|."""
    from orchestrator.engine.results import EngineResults, sensitivity_name
    from orchestrator.model.forward import TABLE2_CENTRAL_KPA, LegModel

    mesh = leg_slice_mesh(args.garment_elements, order=2)
    for effect in ("local", "heterogeneity"):
        model = LegModel(mesh, GARMENT_TENSION, garment="explicit", friction_mu=0.3, engine_sensitivities=True,
                         effects=(effect,))
        theta = list(TABLE2_CENTRAL_KPA) + [0.0] * (model.space.size - len(TABLE2_CENTRAL_KPA))
        state = model.deck_state(theta)
        terms = {name: state.sensitivity[name] for name in model.space.names}
        lines = sorted({line for parts in terms.values() for line, _ in parts})
        decks = {"one column per parameter (NAME= blocks)": model.deck(theta),
                 "one column per line": model.deck(theta, extra_sensitivities=lines, own_sensitivities=False)}
        print(f"\ngrouped sensitivities through friction 0.3, effect {effect}: the leg under the band, "
              f"{len(mesh.elements)} CPE6, {len(model.groups)} material groups, {model.space.size} parameters over "
              f"{len(lines)} engine lines")
        outputs, medians = {}, {}
        for label, text in decks.items():
            name = f"grouped-{effect}-{len(outputs)}-"
            measured = _median_runs(args, root, name, lambda folder, t=text: _with_mesh(folder, t, model))
            if measured is None:
                return
            times, last = measured
            medians[label] = statistics.median(times)
            outputs[label] = EngineResults(root / f"{name}{args.runs - 1}" / "out").sensitivities()
            _report(label, times, last, mesh.n_dof)
        combined, single = outputs.values()
        worst = max(np.abs(combined[name] - sum(w * single[sensitivity_name(line)] for line, w in parts)).max()
                    / max(np.abs(combined[name]).max(), 1e-300) for name, parts in terms.items())
        first, second = medians.values()
        print(f"  per line / combined: {second / first:.2f} x the wall time; the combined columns against the "
              f"weighted sums of the lines' own: {worst:.1e} at worst (relative)")


def second_paper(args, root: Path) -> None:
    """4c (module text): the second paper's model under the band with friction, as a diagnosis runs it."""
    from orchestrator.model.forward import LegModel
    from orchestrator.phantom.truths import SECOND_PAPER_KPA, SECOND_PAPER_TISSUES

    mesh = leg_slice_mesh(args.second_paper_elements, order=2)
    model = LegModel(mesh, GARMENT_TENSION, garment="explicit", friction_mu=0.3, tissues=SECOND_PAPER_TISSUES,
                     hybrid=True, engine_sensitivities=True)
    text = model.deck(list(SECOND_PAPER_KPA.values()))
    print(f"\nthe second paper's model: {len(mesh.elements)} CPE6H, Table 1 Mooney-Rivlin tissues (incompressible), "
          f"the band with friction 0.3, {model.space.size} sensitivity columns along the put-on")
    result = _median_runs(args, root, "second-paper", lambda folder: _with_mesh(folder, text, model))
    if result:
        _report("calfit-fe", *result, mesh.n_dof)


def _with_mesh(folder: Path, text: str, model) -> Path:
    from orchestrator.engine.runner import write_mesh_include

    write_mesh_include(model, folder)
    return write_leg_deck(folder, text)


def scaling(args, root: Path) -> None:
    print("\nscaling on the leg-like slice (CPE6): one calfit-fe process per size")
    print(f"  {'target DOF':>10} {'DOF':>8} {'elements':>9} {'wall s':>9} {'peak RSS':>13} {'status':>14} {'Newton':>6}")
    converged, largest = [], None
    for n in args.dofs:
        mesh = leg_slice_mesh_for_dof(n, order=2)
        d = root / f"scale{n}"
        d.mkdir()
        r = run_engine(_paper_deck(d, mesh), args.threads, args.timeout)
        note = ""
        if abs(mesh.n_dof - 25_000) < 5_000:
            note = f"   target < {TARGET_25K_S} s"
        if mesh.n_dof > 150_000:
            note = f"   target peak < {fmt_bytes(TARGET_200K_BYTES).strip()}"
        status = r.get("status") or f"exit {r['exit']}"
        print(f"  {n:>10} {mesh.n_dof:>8} {len(mesh.elements):>9} {r['wall_s']:>9.3f} {fmt_bytes(r['peak_rss']):>13} "
              f"{status:>14} {r.get('newton', '-'):>6}{note}", flush=True)
        if r["exit"] == 0 and r.get("status") == "converged":
            converged.append((mesh.n_dof, r["wall_s"]))
        if largest is None or mesh.n_dof > largest[0]:
            largest = (mesh.n_dof, r["peak_rss"], status)
    _scaling_summary(converged, largest)


def _scaling_summary(converged: list[tuple[int, float]], largest: tuple[int, float, str] | None) -> None:
    """The exponent p of wall time ~ N^p (least squares of log t on log N over the converged sizes) and the peak
    memory of the largest size, against their goals."""
    if len(converged) >= 2:
        dofs, walls = np.array(converged, dtype=float).T
        exponent = np.polyfit(np.log(dofs), np.log(walls), 1)[0]
        # the fixed cost of a process (start, parse, output) weighs most at the small sizes and lowers the fit
        print(f"  wall time ~ N^{exponent:.2f} (least squares of log t on log N over {len(converged)} converged sizes, "
              f"{dofs.min():.0f} to {dofs.max():.0f} DOF)    goal: time ~ N^{TARGET_SCALING_EXPONENT} or flatter")
    else:
        print(f"  wall time exponent: needs 2 converged sizes, got {len(converged)}")
    if largest is not None:
        n_dof, peak, status = largest
        verdict = "not measured" if not np.isfinite(peak) else "under" if peak < TARGET_200K_BYTES else "OVER"
        print(f"  peak RSS at the largest size ({n_dof} DOF, {status}): {fmt_bytes(peak).strip()}, {verdict} the "
              f"{TARGET_200K_BYTES / 2**30:.0f} GiB target (set for 200k DOF)")


# --- issue 18: the square pushed down by prescribed displacements ------------------------------------------

SQUARE_MM = 50.0
SQUARE_C10, SQUARE_D1 = 0.005, 2.0     # NEO HOOKE, MPa and 1/MPa
SQUARE_PUSHES = ((1.0, "2 %"), (5.0, "10 %"), (10.0, "20 %"))
SQUARE_SIZES = ((20, "3.4k"), (52, "22k"))   # cells per side: 2 (2 n + 1)^2 DOF


def _square_case(n: int, push: float):
    from engine_closed_forms import Law
    from fe_cases import deck, unit_square

    mesh = unit_square(n, 2, SQUARE_MM)
    text = deck(mesh, Law("NEO HOOKE", (SQUARE_C10, SQUARE_D1)), fixed=[("BOTTOM", 1, 2), ("TOP", 1, 1)],
                prescribed=[("TOP", 2, -push)], static=(0.2, 1.0))
    return mesh, text


def _felupe_square(mesh, push: float, increments: int = 5) -> tuple[float, list[int], np.ndarray] | None:
    """FElupe on the same T6 mesh (3-point rule like CPE6): NeoHooke mu = 2 C10, bulk = 2 / D1 is Abaqus's NEO
    HOOKE; five equal increments of the push (the deck's *STATIC 0.2, 1.0), Newton to FElupe's default tolerance."""
    try:
        import felupe as fem
    except ImportError:
        return None
    import time

    element, _ = _felupe_quadratic_triangle(fem)   # FElupe's own T6 gradient is wrong (see there)
    region = fem.Region(fem.Mesh(mesh.nodes, mesh.elems, "triangle6"), element, fem.TriangleQuadrature(order=2))
    field = fem.FieldContainer([fem.FieldPlaneStrain(region, dim=2)])
    y = mesh.nodes[:, 1]
    bottom, top = np.isclose(y, 0.0), np.isclose(y, SQUARE_MM)
    boundaries = {"bottom": fem.Boundary(field[0], mask=bottom),
                  "top_x": fem.Boundary(field[0], mask=top, skip=(0, 1)),
                  "top_y": fem.Boundary(field[0], mask=top, skip=(1, 0))}
    solid = fem.SolidBody(fem.NeoHooke(mu=2 * SQUARE_C10, bulk=2 / SQUARE_D1), field)
    step = fem.Step(items=[solid], ramp={boundaries["top_y"]: -push * np.arange(1, increments + 1) / increments},
                    boundaries=boundaries)
    job = fem.Job(steps=[step])
    began = time.perf_counter()
    job.evaluate(verbose=0)
    iterations = [len(norms) for norms in job.fnorms]
    return time.perf_counter() - began, iterations, solid.field[0].values


def compression(args, root: Path) -> None:
    print("\nthe square of issue 18 (50 mm, NEO HOOKE C10 = 0.005 MPa, D1 = 2, CPE6; bottom clamped, top pushed down "
          "with x held; *STATIC 0.2, 1.0), beside CalculiX and FElupe on the same mesh:")
    print(f"  {'DOF':>6} {'push':>5} {'calfit-fe s':>11} {'iterations per increment':<30} {'ccx s':>7} {'ratio':>6} "
          f"{'|u - u_ccx|':>11} {'FElupe s':>9} {'ratio':>6} {'FElupe iterations':<18}")
    for n, label in SQUARE_SIZES:
        for push, strain in SQUARE_PUSHES:
            mesh, text = _square_case(n, push)
            folder = root / f"square{n}_{push:g}"
            times, histories = [], []
            for k in range(args.runs):
                d = folder / f"fe{k}"
                d.mkdir(parents=True)
                r = run_engine(write_leg_deck(d, text), args.threads, args.timeout)
                times.append(r["wall_s"] if r["exit"] == 0 else float("nan"))
                summary = d / "out" / "summary.json"
                if summary.is_file():   # converged increments; a cut-back shows as its iterations and "x"
                    histories = [str(len(i["residual_norms"]) - 1) + ("" if i["converged"] else "x")
                                 for i in json.loads(summary.read_text())["steps"][0]["increments"]]
            fe = statistics.median(times)
            ccx_s, ccx_ratio, diff = float("nan"), float("nan"), float("nan")
            if not args.no_ccx and shutil.which("ccx"):
                ccx_times = []
                for k in range(args.ccx_runs):
                    d = folder / f"ccx{k}"
                    d.mkdir()
                    ccx_times.append(run_ccx(write_leg_deck(d, text), args.timeout)["wall_s"])
                ccx_s = statistics.median(ccx_times)
                ccx_ratio = ccx_s / fe
                ours = np.load(sorted((folder / "fe0" / "out").glob("step-*.u.npy"))[-1])[:, 3:5]
                disp = parse_ccx_dat(folder / "ccx0" / "leg.dat")
                theirs = np.array([disp[i + 1][:2] for i in range(len(mesh.nodes))])
                diff = np.abs(ours - theirs).max() / np.abs(theirs).max()
            try:
                felupe = _felupe_square(mesh, push)
                fl_s, fl_ratio, fl_its = ((felupe[0], felupe[0] / fe, str(felupe[1])) if felupe
                                          else (float("nan"), float("nan"), "not installed"))
            except Exception as error:   # FElupe's own failure is a result of the comparison, not of this script
                fl_s, fl_ratio, fl_its = float("nan"), float("nan"), f"failed: {str(error)[:40]}"
            print(f"  {2 * (2 * n + 1) ** 2:>6} {strain:>5} {fe:>11.3f} {' '.join(histories):<30} {ccx_s:>7.2f} {ccx_ratio:>5.1f}x "
                  f"{diff:>11.1e} {fl_s:>9.3f} {fl_ratio:>5.1f}x {fl_its:<18}", flush=True)
    print("  targets: converged, <= 5 iterations per increment (x: an increment cut back), ccx / calfit-fe >= 10x, "
          "faster than FElupe")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--ccx-runs", type=int, default=5)
    ap.add_argument("--no-ccx", action="store_true")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--garment-elements", type=int, default=1000,
                    help="T6 elements of the garment deck that the iteration and time targets are for")
    ap.add_argument("--garment-ccx-elements", type=int, default=2000,
                    help="T6 elements of the garment deck run beside CalculiX")
    ap.add_argument("--second-paper-elements", type=int, default=4000,
                    help="T6 elements of the second paper's model under the band with friction")
    ap.add_argument("--dofs", type=lambda s: [int(x) for x in s.split(",")], default=list(DEFAULT_DOFS))
    sections = {"paper": paper_size, "follower": follower, "hybrid": nearly_incompressible, "garment": explicit_garment,
                "sensitivities": sensitivities, "grouped": grouped_sensitivities, "second-paper": second_paper,
                "scaling": scaling, "compression": compression}
    ap.add_argument("--only", type=lambda s: s.split(","), default=list(sections),
                    help=f"comma-separated sections to run, of {','.join(sections)} (default: all)")
    args = ap.parse_args()
    unknown = sorted(set(args.only) - set(sections))
    if unknown:
        ap.error(f"unknown section(s) {', '.join(unknown)}: choose from {', '.join(sections)}")
    print(f"calfit-fe: {find_engine()}; machine: {os.cpu_count()} logical CPUs")
    with tempfile.TemporaryDirectory(prefix="calfit-bench-") as tmp:
        root = Path(tmp)
        for name, section in sections.items():
            if name in args.only:
                section(args, root)


if __name__ == "__main__":
    main()
