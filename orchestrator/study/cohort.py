"""A cohort of cases through the whole pipeline on a Dask cluster: `calfit study STUDY --out DIR`.

STUDY is a folder of case folders, each a case as `calfit identify` takes it (case.toml and its images, perhaps
labels.png or points.csv), or a volume case, which `volume_study` first cuts into slice cases under DIR/slices/
(their rows then start with the slice's height, its tension, and how far the skin moves between neighbouring
slices there: `volume_study.skin_shift_px`, too_coarse beyond a pixel). Each case is one task on
`dask.distributed`: a LocalCluster of `workers` processes of one thread on this machine by default, or an
existing cluster (`scheduler`, whose workers must see STUDY and DIR at the same paths). A task runs the case's
stages one after the other in its worker: identify (measuring the images first), montecarlo, pressures (when case.toml names landmarks) and diagnose (when the model is the Laplace
law's with one loaded image). Inside a task the engine runs one deck at a time on one thread, so that engines
never outnumber a worker's cores: the cohort's parallelism is its cases.

DIR/cases/<case>/ is the case's run folder. When a case is done its row of the study table is written beside
it, DIR/cases/<case>/row.json. A study stopped, or a worker killed, and started again:
- skips the cases that have a row;
- resumes the others from their run folders, whose evaluation logs replay every finished engine run.
No finished case is lost and none is repeated. Dask gives a task whose worker died to another worker. A case
that fails (images that do not correlate, a deck the engine rejects) gets a row saying why and is tried again
on the next run; the others go on.

The table, one row per case, is rewritten as each case finishes:
- DIR/study.csv, each number with the digits its uncertainty allows (`digits`): a parameter by its 95 %
  interval (`digits.interval_uncertainty`), a pressure by its spread with the garment tension's;
- DIR/study.parquet, full precision, when pyarrow is installed (`pip install calfit[study]`).
Its columns are:
- case, status (done or failed), error;
- each parameter with its interval (<name>, <name>_low, <name>_high) and whether it is identifiable;
- the misfit over its noise floor, and the diagnosis' verdict, whether it finds a lack of fit and whether the
  catalog explains the residual;
- the garment's mean pressure on the skin (interface_pressure_kPa, 2 pi T / perimeter) and each landmark's
  pressure, each with its standard deviation (pressure_<landmark>_kPa, ..._std_kPa);
- the case's wall time.
DIR/study.json sums it up: cases done and failed, the wall time, the cases per hour, each worker's peak memory.
DIR/report/index.html is the study report (`study_report`), rewritten at the end of each run.
"""

from __future__ import annotations

import csv
import io
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.digits import rounded
from ..core.errors import RunFolderError
from ..core.files import atomic_write_text, read_json, write_json
from ..diagnose.score import ALPHA
from ..fit.identify import pressure_spreads
from ..report.study_report import cell_uncertainty, write_study_report
from ..run.stages import run_diagnose, run_identify, run_montecarlo, run_pressures
from .volume_cases import SLICES_JSON, is_volume_case, slice_volume_case

ROW_FILE = "row.json"
TABLE_CSV, TABLE_PARQUET, SUMMARY_JSON = "study.csv", "study.parquet", "study.json"
DONE, FAILED = "done", "failed"
CASE_RETRIES = 2    # a task whose worker died is run again elsewhere, this many times
STAGES = ("identify", "montecarlo", "pressures", "diagnose")
QUIET_LOCAL_CLUSTER = {"distributed.worker.profile.enabled": False, "distributed.admin.system-monitor.interval": "2s"}


@dataclass(frozen=True)
class CaseOptions:
    """What every case of a study is run with (`calfit study`'s options)."""

    n_elements: int | None = None      # the identification mesh (None: the pipeline's default)
    draws: int | None = None           # Monte-Carlo draws (None: the pipeline's default)
    pressure_draws: int = 30           # parameter draws of the pressure study (Avril et al. Table 3)
    timeout_s: float = 120.0           # one engine run
    stages: tuple[str, ...] = STAGES   # identify and montecarlo always; pressures and diagnose when listed

    def __post_init__(self):
        unknown = [stage for stage in self.stages if stage not in STAGES]
        if unknown or not {"identify", "montecarlo"} <= set(self.stages):
            raise ValueError(f"a study's stages are identify, montecarlo and any of pressures, diagnose; not "
                             f"{', '.join(self.stages)}")


def study_cases(study: Path) -> list[Path]:
    """The case folders of a cohort, sorted by name; a clear error for anything else."""
    study = Path(study)
    if not study.is_dir():
        raise RunFolderError(f"{study} is not a folder: a study is a folder of case folders (each with case.toml)")
    if (study / "case.toml").is_file():
        raise RunFolderError(f"{study} is one case (it holds case.toml): a study is a folder of case folders; "
                             "run `calfit identify` on a single case")
    cases = sorted(path for path in study.iterdir() if (path / "case.toml").is_file())
    if not cases:
        raise RunFolderError(f"{study} holds no case folder (a subfolder with case.toml): nothing to study")
    return cases


def run_case(case_dir: str, run_dir: str, options: CaseOptions, extra: dict | None = None) -> dict:
    """One case through the pipeline (module text), in a Dask worker; its row of the study table, which starts
    with `extra` (a slice's height and tension). A failure of the case is its row (status failed, the error),
    never an exception: the other cases go on."""
    began = time.perf_counter()
    case_dir, run_dir = Path(case_dir), Path(run_dir)
    row: dict = {"case": case_dir.name, "status": DONE, "error": "", **(extra or {})}
    # one engine at a time in this worker, on one thread (module text)
    evaluation = {"workers": 1, "timeout_s": options.timeout_s, "progress": False}
    try:
        identification = run_identify(case_dir, run_dir, n_elements=options.n_elements, **evaluation)
        montecarlo = run_montecarlo(run_dir, draws=options.draws, **evaluation)
        row.update(_parameters(identification, montecarlo))
        row.update(_interface_pressure(run_dir))
        if "pressures" in options.stages:
            try:
                row.update(_pressures(run_pressures(run_dir, draws=options.pressure_draws, **evaluation)))
            except RunFolderError:   # no [landmarks] in case.toml: no pressure asked for
                pass
        if "diagnose" in options.stages:
            try:
                diagnosis = run_diagnose(run_dir, **evaluation)
                row.update(verdict=diagnosis["verdict"], explained=bool(diagnosis["explained"]),
                           lack_of_fit=bool(diagnosis["lack_of_fit_p"] < ALPHA),
                           below_floor=bool(diagnosis.get("final", {}).get("below_floor")))
            except ValueError as refused:   # a model the diagnosis does not take yet (garment levels)
                row.update(verdict=f"not diagnosed: {refused}", explained=None)
    except Exception as error:   # noqa: BLE001 - one case's failure is its row; the study goes on
        row.update(status=FAILED, error=f"{type(error).__name__}: {error}")
    row["wall_s"] = time.perf_counter() - began
    if row["status"] == DONE:
        write_json(run_dir / ROW_FILE, row)
    return row


def _parameters(identification: dict, montecarlo: dict) -> dict:
    values = {"misfit_over_floor": identification.get("misfit_over_floor")}
    for k, name in enumerate(montecarlo["names"]):
        values[name] = identification["best"]["theta"][k]
        values[f"{name}_low"], values[f"{name}_high"] = montecarlo["lower"][k], montecarlo["upper"][k]
        values[f"{name}_identifiable"] = name not in montecarlo["poorly_identified"]
    return values


def _interface_pressure(run_dir: Path) -> dict:
    """The garment's mean pressure on the skin by Laplace's law, p = T / r (Avril et al. eq. 1), averaged around
    the leg: 2 pi T / perimeter, since the curvature integrates to 2 pi. The figure the compression standards give
    at the heights B to D, with the tension's uncertainty as its spread. The perimeter is the meshed skin of I0;
    the compressed skin's is shorter by the garment's compression (under 1 % on the phantoms), which this leaves
    out."""
    from ..fit.geometry_uncertainty import skin_perimeter_mm
    from ..run.setup import load_run

    setup = load_run(run_dir)
    pressure_kPa = 2.0 * np.pi * setup.case.tension_N_per_mm / skin_perimeter_mm(setup.mesh) * 1000.0
    return {"interface_pressure_kPa": pressure_kPa,
            "interface_pressure_std_kPa": pressure_kPa * setup.case.tension_rel_uncertainty}


def _pressures(pressures: dict) -> dict:
    _, _, total = pressure_spreads(pressures)
    values = {}
    for name, mean, spread in zip(pressures["landmarks"], pressures["mean_kPa"], total):
        values[f"pressure_{name}_kPa"], values[f"pressure_{name}_std_kPa"] = mean, spread
    return values


def run_study(study: str | Path, out: str | Path, options: CaseOptions = CaseOptions(), *, workers: int = 2,
              scheduler: str | None = None, report: Callable[[str], None] | None = None) -> dict:
    """Every case of `study` (module text); returns and writes DIR/study.json. report: a line per case finished
    and one at the end (the CLI prints them on stderr)."""
    try:
        import dask
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise RunFolderError("calfit study runs its cases on dask.distributed, which is not installed: "
                             "pip install 'calfit[study]'") from None
    began = time.perf_counter()
    say = report or (lambda line: None)
    out = Path(out)
    volume = None
    if is_volume_case(study):
        slices, volume = slice_volume_case(study, out, say)
        cases = [piece.folder for piece in slices]
        extras = {entry["folder"]: {key: entry[key] for key in ("height_mm", "tension_N_per_mm", "skin_shift_px",
                                                                 "too_coarse", "slide_mm", "slide_sd_mm")
                                           if key in entry}
                  for entry in volume["slices"]}
    else:
        cases, extras = study_cases(Path(study)), {}
    (out / "cases").mkdir(parents=True, exist_ok=True)
    rows = {case.name: _finished_row(out, case.name) for case in cases}
    todo = [case for case in cases if rows[case.name] is None]
    say(f"study of {len(cases)} cases: {len(cases) - len(todo)} done before, {len(todo)} to run on "
        + (f"the cluster at {scheduler}" if scheduler else f"{workers} local worker(s)"))
    _write_table(out, cases, rows)
    if todo:
        cluster = None
        if not scheduler:
            # the workers' sampling profiler (a stack walk every 10 ms) and 0.5 s system monitors feed a dashboard
            # that a local study does not open: an idle 2-worker cluster took 10.5 % of a core with them, 6.8 %
            # without, on a 2-core machine where every worker's core is a case's. The scheduler starts its HTTP
            # server whatever the dashboard (None means its default, port 8787): on a port the system picks, so
            # that two studies (or a study and a test) on one machine do not collide
            with dask.config.set(QUIET_LOCAL_CLUSTER):
                cluster = LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True,
                                       dashboard_address=":0")
        try:
            with Client(scheduler or cluster, timeout=30, set_as_default=False) as client:
                futures = [client.submit(run_case, str(case), str(out / "cases" / case.name), options,
                                         extras.get(case.name), key=f"calfit-case-{case.name}", pure=False,
                                         retries=CASE_RETRIES)
                           for case in todo]
                for finished, future in enumerate(as_completed(futures, loop=client.loop), start=1):
                    row = future.result()
                    rows[row["case"]] = row
                    _write_table(out, cases, rows)
                    detail = row.get("verdict", "") if row["status"] == DONE else row["error"]
                    say(f"[{finished}/{len(todo)}] {row['case']}: {row['status']} in {row['wall_s']:.0f} s; {detail}")
                memory = client.run(_peak_rss_mib)
        finally:
            if cluster is not None:
                cluster.close()
    else:
        memory = {}
    page = write_study_report(out, [rows[case.name] for case in cases if rows[case.name] is not None], volume)
    wall = time.perf_counter() - began
    done = sum(1 for row in rows.values() if row and row["status"] == DONE)
    summary = {"study": str(Path(study).resolve()), "cases": len(cases), "done": done,
               "failed": sorted(name for name, row in rows.items() if row and row["status"] == FAILED),
               "ran_now": len(todo), "wall_s": wall, "workers": None if scheduler else workers,
               "scheduler": scheduler, "cases_per_hour": 3600.0 * len(todo) / wall if todo else None,
               "worker_peak_rss_mib": memory,
               "table": TABLE_CSV, "parquet": TABLE_PARQUET if (out / TABLE_PARQUET).is_file() else None,
               "report": str(page.relative_to(out)), "volume_slices": SLICES_JSON if volume is not None else None,
               "slide": None if volume is None else volume.get("slide")}
    write_json(out / SUMMARY_JSON, summary)
    say(f"{done} of {len(cases)} cases done, {len(summary['failed'])} failed; {wall:.0f} s; table in {out / TABLE_CSV}")
    return summary


def _peak_rss_mib() -> float:
    """The peak resident memory of this process (a Dask worker), MiB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _finished_row(out: Path, name: str) -> dict | None:
    path = out / "cases" / name / ROW_FILE
    return read_json(path, "calfit study") if path.is_file() else None


def _columns(rows: list[dict]) -> list[str]:
    """The table's columns in the order they first appear, the case and its status first."""
    columns = ["case", "status", "error"]
    for row in rows:
        columns += [key for key in row if key not in columns]
    return columns


def _cell(column: str, row: dict) -> str:
    value = row.get(column)
    if value is None:
        return ""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    return rounded(float(value), cell_uncertainty(column, row))


def _write_table(out: Path, cases: list[Path], rows: dict[str, dict | None]) -> None:
    """study.csv (and study.parquet with pyarrow) from the rows there are, in the cases' order."""
    present = [rows[case.name] for case in cases if rows[case.name] is not None]
    columns = _columns(present)
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(columns)
    for row in present:
        writer.writerow([_cell(column, row) for column in columns])
    atomic_write_text(out / TABLE_CSV, text.getvalue())
    try:
        import pandas as pd
        import pyarrow  # noqa: F401  (pandas writes Parquet through it)
    except ImportError:
        return
    temporary = out / f".{TABLE_PARQUET}.tmp"
    pd.DataFrame(present, columns=columns).to_parquet(temporary, index=False)
    temporary.replace(out / TABLE_PARQUET)
