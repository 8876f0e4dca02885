"""The model's skin is only as good as the segmentation: its uncertainty belongs to the error budget.

DIC measures the skin's motion to a few micrometres (a 32-pixel window on the skin edge: 0.002-0.003 mm across
the edge). The model cannot predict it that well, because its skin comes from a segmentation and the garment
presses it by Laplace's law, p = T kappa (Avril et al. eq. 1): curvature amplifies short shape errors, and a
bump of 0.01 mm over 15 mm of skin changes the local pressure by several percent. On the phantom calf, whose
true shape is known, the skin `meshing.mesh_from_labels` took from the image (edges snapped, low-pass at a fixed
8 mm) was off the true skin by 0.011 mm RMS at wavelengths over 8 mm, and that alone put the model's predictions 0.2
times the DIC variance away from the truth's (the fascia and the bones, segmented as well, by under 0.05;
moving the whole skin by 0.14 mm, by under 0.1). Ignored, it makes every fit look worse than the noise and
every diagnosis find physics that is missing only from the outline.

Shape error as pressure error. A normal offset delta(theta) of a contour of radius R changes its curvature by
-(delta + delta'') / R^2 (theta the polar angle), so the offset's Fourier mode k (alpha_k cos k theta + ...)
changes the Laplace pressure by the relative amount a_k = (k^2 - 1) alpha_k / R: exactly a garment tension
profile T (1 + sum a_k cos k theta + b_k sin k theta), whose sensitivities du/da_k the engine gives in one run
(`*SENSITIVITY`, `PROFILE, GARMENT, A<k>`). With the skin offset modelled as white noise low-passed at the
skin's cut-off wavelength (where the skin's spectrum puts it, `meshing.labels`; Butterworth H_k at the wavelength
L / k, L the perimeter) and of RMS `skin_sigma_mm`, mode k has the variance v_k = sigma^2 H_k^2 / sum_j H_j^2 in each
of alpha_k and beta_k. The skin's own spectrum measures its error too (`meshing.curves.outline_error`: v per mode,
white, from its modes of 6-12 mm, where a calf has no shape), which gives sigma^2 = v sum_j H_j^2 and v_k = v H_k^2
(`measured_skin_sigma`); where it cannot, sigma is `SKIN_UNCERTAINTY_PX` pixels. The predictions get the covariance

    C_geo = sum_{k >= 2} (k^2 - 1)^2 v_k / R^2 (g_Ak g_Ak^T + g_Bk g_Bk^T),   g = O du/da (what is measured of it),

which `measure.Measurements.with_model_covariance` adds to the measurements'. k = 1 (a shift of the contour)
changes no curvature, so the first harmonic of a real tension profile (the `tension_profile` effect) stays
fully visible.

Under the explicit band (the second paper's garment) there is no law p = T kappa to perturb: the band's contact
pressure is what the band's tension, its bending and the friction make of the skin's shape, bridges included.
The skin itself is then moved: the engine's `SHAPE` sensitivities differentiate the solution with respect to the
skin nodes' reference positions moved radially by delta = alpha_k cos k theta (beta_k sin k theta), the tissue's
elements, the band's contact and its tributary lengths all on the moved skin, carried along the put-on through
friction, every mode in one run. The columns are g = O du/d alpha_k with the offset's own variances v_k (the model
does the curvature's amplification), from k = 1 (a shift of the contour thickens the fat on one side, which a
band, unlike Laplace's law, feels). Against whole runs on meshes whose skin was moved along its normals and the
band rebuilt on it (benchmarks/band_skin_columns.py, the frictionless band, 2,000 CPE6, modes 2-16): these columns
correlate 0.997-1.000 with them, norms 0.99-1.03 times, relative difference 0.004-0.08; Laplace's columns 0.83-0.996,
norms 0.77-1.48 times, relative difference 0.11-0.86; the contact's offset alone (`GAP PROFILE`, the elements
unmoved) 0.88-0.99, 0.15-0.57.

Where the interfaces are. A uniform shift of the skin or of the fascia changes little of the misfit (0.14 mm of
skin: under 0.1 of the noise variance) but what it changes, the fat's thickness, the fitted fat constants
absorb: a bias of the parameters, not of the misfit, that the intervals must hold. The fascia of the phantom
calf comes out 0.06 mm (0.17 pixel) off, its skin 0.03 mm. Both shifts, of standard deviation `interface_sigma_mm`
(default `INTERFACE_UNCERTAINTY_PX` pixels), enter C_geo through the change they make in the predictions,
g = (y(+h) - y(-h)) / 2h from two meshes moved by +-h (`meshing.labels.interface_shift`), solved at the same
parameters. The floor then counts every part, and the identification reports the measurement's share.

Several garment levels ([[garment.levels]]). Each level's windows get their own C_geo, made at that level's
tension and stored as geometry_uncertainty-level-<k>.npz (`level_file`), with its columns G_k and their variances
w (`geometry_columns`): the same modes and the same w at every level, since they describe the segmentation, not
the load. One skin error acts on every level at once, so the levels' geometry errors are correlated, G_k W G_l^T
between levels k and l, and the joint fit (`levels.JointDisplacementObjective`) whitens all the levels' data
together with them. A run folder of several levels whose files hold no columns (written before) is refused by the
commands after `calfit identify`, which estimates them again (`discard_without_columns`).
"""

from __future__ import annotations

import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np

SKIN_UNCERTAINTY_PX = 0.05
INTERFACE_UNCERTAINTY_PX = 0.15
SHIFT_STEP_MM = 0.1          # the +-h of the interface shifts' central differences
RESPONSE_FLOOR = 1e-3        # modes whose low-pass response is below this carry no uncertainty
FILE = "geometry_uncertainty.npz"
SHIFTS = tuple((interface, sign) for interface in ("skin", "fascia") for sign in (1.0, -1.0))
COLUMN_RUNS = 1 + len(SHIFTS)   # the engine runs of `geometry_columns`: the skin's modes, each shifted interface


def level_file(level: int = 1) -> str:
    """The stored C_geo of garment level `level`: FILE for the first, geometry_uncertainty-level-<level>.npz."""
    return FILE if level == 1 else FILE.replace(".npz", f"-level-{level}.npz")


def skin_perimeter_mm(mesh) -> float:
    loop = mesh.nodes[mesh.skin_loop]
    return float(np.sum(np.linalg.norm(np.diff(np.vstack([loop, loop[:1]]), axis=0), axis=1)))


def _responses(perimeter_mm: float, cutoff_mm: float, order: int = 4) -> np.ndarray:
    """The skin's low-pass response H_k at the wavelengths L / k, k = 1 .. K, K where it falls below RESPONSE_FLOOR."""
    last = int(np.ceil(perimeter_mm / cutoff_mm * (1.0 / RESPONSE_FLOOR - 1.0) ** (1.0 / (2 * order))))
    k = np.arange(1, max(last, 2) + 1, dtype=float)
    return 1.0 / (1.0 + (k * cutoff_mm / perimeter_mm) ** (2 * order))


def offset_variances(perimeter_mm: float, skin_sigma_mm: float, cutoff_mm: float, order: int = 4) -> np.ndarray:
    """Variance of the skin offset's Fourier coefficients alpha_k (= of beta_k), k = 1 .. K, mm^2, for an offset of
    RMS skin_sigma_mm low-passed at cutoff_mm (module text)."""
    response = _responses(perimeter_mm, cutoff_mm, order)
    return skin_sigma_mm ** 2 * response ** 2 / np.sum(response ** 2)


def measured_skin_sigma(perimeter_mm: float, mode_variance_mm2: float, cutoff_mm: float, order: int = 4) -> float:
    """The RMS skin_sigma_mm of `offset_variances` for the skin's own error, white with `mode_variance_mm2` per
    coefficient (`meshing.curves.outline_error`), low-passed at cutoff_mm: its modes then have v H_k^2."""
    return float(np.sqrt(mode_variance_mm2 * np.sum(_responses(perimeter_mm, cutoff_mm, order) ** 2)))


def mode_variances(perimeter_mm: float, skin_sigma_mm: float, cutoff_mm: float, order: int = 4) -> np.ndarray:
    """Variance of the relative pressure coefficients a_k (= of b_k) of Laplace's law, k = 1 .. K, for the skin
    offset of `offset_variances`: a_k = (k^2 - 1) alpha_k / R (module text)."""
    offset_variance = offset_variances(perimeter_mm, skin_sigma_mm, cutoff_mm, order)
    k = np.arange(1, len(offset_variance) + 1, dtype=float)
    radius = perimeter_mm / (2 * np.pi)
    return (k ** 2 - 1.0) ** 2 * offset_variance / radius ** 2


def profile_lines(count: int) -> list[str]:
    from ..model.effects import PROFILE_NAME

    return [f"PROFILE, {PROFILE_NAME}, {kind}{k}" for k in range(1, count + 1) for kind in ("A", "B")]


def shape_lines(count: int) -> list[str]:
    """The explicit band's counterpart of `profile_lines`: the skin itself moved (module text)."""
    return [f"SHAPE, SKIN, {kind}{k}" for k in range(1, count + 1) for kind in ("A", "B")]


def skin_mode_lines(model, count: int) -> list[str]:
    """The *SENSITIVITY lines of the skin's modes k = 1 .. count on this model's garment."""
    return shape_lines(count) if model.band is not None else profile_lines(count)


def skin_pressure_sensitivities(model, theta: Sequence[float], count: int) -> dict[str, np.ndarray]:
    """du/d(mode) of the skin's modes k = 1 .. count (`skin_mode_lines`; nodal (M, 2) each) of the model at theta,
    from one engine run (only these lines: the model's own are not needed here)."""
    from ..engine.results import EngineResults, sensitivity_name
    from ..engine.runner import DEFAULT_TIMEOUT_S, run_engine, run_timeout, write_mesh_include

    lines = skin_mode_lines(model, count)
    with tempfile.TemporaryDirectory(prefix="calfit-geometry-") as scratch:
        write_mesh_include(model, Path(scratch))
        deck = Path(scratch) / "deck.inp"
        text = model.deck(theta, extra_sensitivities=lines, own_sensitivities=False)
        deck.write_text(text)
        outcome = run_engine(deck, Path(scratch) / "out", threads=None, timeout_s=run_timeout(text, DEFAULT_TIMEOUT_S))
        if not outcome.converged:
            raise RuntimeError(f"the engine did not converge at {list(theta)} for the skin's sensitivities")
        found = EngineResults(outcome.outdir).sensitivities()
    return {line: found[sensitivity_name(line)] for line in lines}


def _model_on(setup, mesh, effects, tension_N_per_mm):
    """The run's model (its tissues, elements and garment) on `mesh` under `tension_N_per_mm`, with `effects`."""
    from ..model.forward import LegModel

    model = setup.model
    return LegModel(mesh, tension_N_per_mm, effects=tuple(effects), tissues=model.tissues, hybrid=model.hybrid,
                    garment=model.garment, friction_mu=model.friction_mu)


def _observed(setup, measurements, theta, effects, interface, shift_mm, tension_N_per_mm) -> np.ndarray:
    """What the measurements see of the run's model meshed again with one interface shifted by shift_mm
    (`run.setup.RunSetup.shifted_mesh`, made once a run), solved at theta."""
    from ..engine.runner import solve_once

    mesh = setup.shifted_mesh(interface, shift_mm)
    model = _model_on(setup, mesh, effects, tension_N_per_mm)
    displacement = solve_once(model, model.deck(theta, sensitivities=False),
                              f"the engine did not converge on a shifted interface at {list(theta)}")
    return measurements.observation(mesh) @ displacement[:len(mesh.nodes)].ravel()   # the leg's nodes (not a band's)


def geometry_columns(setup, theta: Sequence[float], measurements, *, effects: Sequence[str] = (),
                     skin_sigma_mm: float, interface_sigma_mm: float, cutoff_mm: float,
                     tension_N_per_mm: float | None = None, workers: int = 1) -> tuple[np.ndarray, list[float], dict]:
    """The columns g of C_geo (module text: what is measured of each skin mode and interface shift, (2N, m) mm per
    unit), their variances w (the same at every garment level: they hold the segmentation, not the load) and what
    made them, under the case's [garment] tension or `tension_N_per_mm` (another garment level's). workers > 1: the
    modes' run and the shifted interfaces' remeshes and solves go side by side in that many threads (an engine
    solves while another interface is meshed), with the same results."""
    tension = setup.case.tension_N_per_mm if tension_N_per_mm is None else float(tension_N_per_mm)
    model = _model_on(setup, setup.mesh, effects, tension)
    perimeter = skin_perimeter_mm(model.mesh)
    # the band's model moves the skin itself; Laplace's law feels its curvature's change (module text)
    variances = (offset_variances if model.band is not None else mode_variances)(perimeter, skin_sigma_mm, cutoff_mm)
    setup.tissue_curves()   # made once, before the threads mesh them, as the compartments found in I0
    setup.compartment_labels()
    shifts = SHIFTS

    def shifted(interface: str, sign: float) -> np.ndarray:
        return _observed(setup, measurements, theta, effects, interface, sign * SHIFT_STEP_MM, tension)

    with ThreadPoolExecutor(max(1, int(workers))) as pool:
        modes = pool.submit(skin_pressure_sensitivities, model, theta, len(variances))
        observed = [pool.submit(shifted, *shift) for shift in shifts]
        sensitivities = modes.result()
        observed = [future.result() for future in observed]
    observation = measurements.observation(model.mesh)
    leg_nodes = len(model.mesh.nodes)   # a band's nodes come after the leg's
    columns = [observation @ sensitivities[line][:leg_nodes].ravel() for line in skin_mode_lines(model, len(variances))]
    weights = list(np.repeat(variances, 2))
    for k in range(0, len(shifts), 2):
        plus, minus = observed[k], observed[k + 1]
        columns.append((plus - minus) / (2 * SHIFT_STEP_MM))
        weights.append(interface_sigma_mm ** 2)
    info = {"skin_sigma_mm": skin_sigma_mm, "interface_sigma_mm": interface_sigma_mm, "cutoff_mm": cutoff_mm,
            "modes": len(variances), "perimeter_mm": perimeter, "theta": [float(v) for v in theta],
            "effects": list(model.effects),
            "skin_model": "the skin moved under the band" if model.band is not None else "laplace"}
    if tension_N_per_mm is not None:
        info["tension_N_per_mm"] = tension
    return np.column_stack(columns), weights, info


def covariance_of(columns: np.ndarray, weights) -> np.ndarray:
    """G diag(w) G^T (mm^2); between two garment levels, G_k diag(w) G_l^T of their columns."""
    return (columns * np.array(weights)) @ columns.T


def write(run_dir: Path, covariance: np.ndarray, info: dict, level: int = 1, columns: np.ndarray | None = None,
          weights=None) -> None:
    """C_geo of garment level `level` and what made it; with `columns` and `weights` (a case of several levels) also
    its columns G_k and their variances, from which the joint fit forms the blocks between levels."""
    name = level_file(level)
    temporary = Path(run_dir) / f".{name}.tmp.npz"
    extra = {} if columns is None else {"columns": np.asarray(columns, float), "weights": np.asarray(weights, float)}
    np.savez_compressed(temporary, covariance=covariance, **extra, **{k: np.asarray(v) for k, v in info.items()})
    temporary.replace(Path(run_dir) / name)


ARRAYS = ("covariance", "columns", "weights")


def read_covariance(run_dir: Path, size: int, level: int = 1) -> tuple[np.ndarray, dict] | None:
    """The stored C_geo (mm^2) of garment level `level` and what made it; None without the file or when it
    belongs to other measurements (another count)."""
    path = Path(run_dir) / level_file(level)
    if not path.is_file():
        return None
    with np.load(path) as stored:
        covariance = stored["covariance"]
        info = {key: stored[key].tolist() for key in stored.files if key not in ARRAYS}
    if covariance.shape != (size, size):
        return None
    return covariance, info


def read_columns(run_dir: Path, size: int, level: int = 1) -> tuple[np.ndarray, np.ndarray] | None:
    """The stored columns G_k (size, m) and variances w of garment level `level`'s C_geo; None without the file, when
    it belongs to other measurements, or when it was written without them (a run of one level, or a run of several
    made before the levels' common skin error was kept: `levels.JointDisplacementObjective`)."""
    path = Path(run_dir) / level_file(level)
    if not path.is_file():
        return None
    with np.load(path) as stored:
        if "columns" not in stored.files:
            return None
        columns, weights = stored["columns"], stored["weights"]
    if columns.shape[0] != size:
        return None
    return columns, weights


def discard_without_columns(run_dir: Path, levels: Sequence[int]) -> list[int]:
    """Remove the stored C_geo of the garment levels (of a case of several) that were written without their
    columns, which a joint fit cannot join (`read_columns`); `calfit identify` then estimates them again.
    Returns the levels removed."""
    removed = []
    for level in levels:
        path = Path(run_dir) / level_file(level)
        if not path.is_file():
            continue
        with np.load(path) as stored:
            stale = "columns" not in stored.files
        if stale:
            path.unlink()
            removed.append(level)
    return removed
