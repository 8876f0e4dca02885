"""The identified leg a garment is designed for, and what a garment gives on it through the FE model.

A run folder is one slice; a volume study (DIR of `calfit study` on a volume case, its slices.json) is one slice per
height, each its own run folder, and the heights B, B1, C, D its slices.json names go to the nearest slices. Each
slice keeps the model its identification fitted, the effects its diagnosis added included (identification.json's
`effects`), at its identified parameters, and the Monte-Carlo draws of montecarlo.json.

A garment on a slice is its tension per height T (N/mm) and, with harmonics, the knitted-in profile
T(t) = T (1 + sum_k a_k cos kt + b_k sin kt) of the tension_profile effect (k = 1, 2; t the deck's polar angle
about the skin's centroid, image frame, y down). `evaluate` solves it once and returns, in mmHg:

- at each landmark, the hydrostatic pressure -tr(sigma)/3 (what the veins feel, `fit.objectives.LandmarkPressure`);
- the skin's mean pressure, sum_i T(t_i) kappa_i l_i / sum_i l_i on the deformed skin (kappa_i the turning angle over
  the tributary length l_i): with a uniform tension 2 pi T / perimeter, the figure the standards give at a height;
- the skin's largest pressure over each region (anywhere, the tibial crest: the anterior eighth of the skin about the
  tibia, each quarter), T(t) kappa smoothed over SMOOTHING_MM of skin;

and their derivatives with respect to T and the profile's coefficients. With Laplace's law (the models calfit
fits by default) the engine differentiates them itself: the deck asks `*SENSITIVITY, PRESSURE=YES` for
`TENSION, SKIN` and the `PROFILE, GARMENT, A<k>|B<k>` lines (solver_cpp/README.md, Sensitivities), which give du/dv
and each element's d(-tr sigma/3)/dv; the skin's pressures follow from du/dv by the chain rule on the deformed
curvature. The explicit band has no Laplace load to differentiate: there a forward difference of 1 % of T."""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import RunFolderError
from ..core.files import read_json
from ..core.units import KPA_PER_MPA, MMHG_PER_KPA
from ..model.forward import MeshInterpolator
from ..run.setup import RunSetup, load_run

SMOOTHING_MM = 10.0         # the skin's local pressure is read over this length (a pressure sensor's pad is 1-2 cm)
PROFILE_NAMES = ("a1", "b1", "a2", "b2")
REGION_NAMES = ("anywhere", "tibial_crest", "anterior", "lateral", "posterior", "medial")
DIFFERENCE_STEP = 0.01      # the band's relative tension step


@dataclass
class DesignSlice:
    """One identified slice: its run folder, the model with its effects, where the profile's coefficients sit in
    theta, its named height and its height along the leg (a study's)."""

    name: str
    run_dir: Path
    setup: RunSetup
    model: object
    theta: list[float]
    samples: list[list[float]]
    height_name: str | None = None
    height_mm: float | None = None
    profile_index: dict = field(default_factory=dict)   # a1 -> its index in theta

    def __post_init__(self):
        self.mesh = self.model.mesh
        self.landmarks = dict(self.setup.case.landmarks or {})
        self._landmark_weights = (MeshInterpolator(self.mesh).weights(np.array(list(self.landmarks.values())))
                                  if self.landmarks else None)
        loop = np.asarray(self.mesh.skin_loop)
        self.skin_nodes = loop
        reference = self.mesh.nodes[loop]
        self.centre = reference.mean(axis=0)
        self.deck_angle = np.arctan2(reference[:, 1] - self.centre[1], reference[:, 0] - self.centre[0])
        frame = self.setup.frame()
        display = frame.angles_deg(reference)
        self.regions = {"anywhere": np.ones(len(loop), bool),
                        "tibial_crest": np.array([frame.direction(a) == "anterior" for a in display])}
        for quarter in ("anterior", "lateral", "posterior", "medial"):
            self.regions[quarter] = np.array([frame.quarter(a) == quarter for a in display])
        self.unloaded_perimeter_mm = float(np.sum(np.linalg.norm(reference - np.roll(reference, -1, 0), axis=1)))
        self.laplace = self.model.garment == "laplace"

    @property
    def tension_N_per_mm(self) -> float:
        return float(self.setup.case.tension_N_per_mm)

    @property
    def tension_rel_uncertainty(self) -> float:
        return float(self.setup.case.tension_rel_uncertainty)

    def theta_with(self, theta: Sequence[float], profile: Sequence[float]) -> list[float]:
        out = [float(v) for v in theta]
        for k, name in enumerate(PROFILE_NAMES):
            if name in self.profile_index:
                out[self.profile_index[name]] = float(profile[k]) if k < len(profile) else 0.0
        return out

    def factor(self, profile: Sequence[float]) -> np.ndarray:
        """T(t) / T at each skin node of the loop."""
        out = np.ones(len(self.skin_nodes))
        for k, name in enumerate(PROFILE_NAMES[:len(profile)]):
            harmonic = int(name[1])
            out += profile[k] * (np.cos(harmonic * self.deck_angle) if name[0] == "a"
                                 else np.sin(harmonic * self.deck_angle))
        return out


def read_slices(source: str | Path, *, harmonics: int = 0, slice_height: str | None = None) -> list[DesignSlice]:
    """The identified slices of a run folder or of a volume study (module text). RunFolderError naming the file
    and the command when a stage is missing."""
    source = Path(source)
    if (source / "slices.json").is_file():
        record = read_json(source / "slices.json", "calfit study VOLUME_CASE --out DIR")
        named = record.get("compression_heights_mm") or {}
        entries = record["slices"]
        heights = np.array([float(entry["height_mm"]) for entry in entries])
        nearest = {name: int(np.argmin(np.abs(heights - value))) for name, value in named.items()}
        slices = []
        for k, entry in enumerate(entries):
            run = source / "cases" / Path(entry["folder"]).name
            name = next((n for n, i in nearest.items() if i == k), None)
            slices.append(_slice(run, harmonics, name, float(entry["height_mm"])))
        return sorted(slices, key=lambda s: s.height_mm)
    if (source / "setup.json").is_file():
        return [_slice(source, harmonics, slice_height, None)]
    raise RunFolderError(f"{source} is neither a run folder (setup.json) nor a volume study (slices.json): give the "
                         "folder of calfit identify or of calfit study on a volume case")


def _slice(run: Path, harmonics: int, height_name: str | None, height_mm: float | None) -> DesignSlice:
    from ..model.effects import parse_effects

    identification = read_json(run / "identification.json", f"calfit identify CASE_DIR --out {run}")
    montecarlo = read_json(run / "montecarlo.json", f"calfit montecarlo {run}")
    setup = load_run(run)
    effects = list(identification.get("effects") or ())
    names = list(identification["parameters"])
    if harmonics and "tension_profile" not in effects:
        effects.append("tension_profile")
    model = setup.model_with(parse_effects(effects))
    if model.garment != "laplace" and harmonics:
        raise RunFolderError(f"{run} fits the explicit garment band, whose tension a knitted-in profile does not "
                             "describe: design with harmonics = 0 under [design]")
    values = dict(zip(names, identification["best"]["theta"]))
    # the garment the MRI saw is not the one designed: an identified tension profile is the design's variable
    theta = [0.0 if name in PROFILE_NAMES else float(values.get(name, 0.0)) for name in model.space.names]
    samples = []
    for draw in montecarlo.get("samples") or [montecarlo["central"]]:
        drawn = dict(zip(montecarlo["names"], draw))
        samples.append([0.0 if name in PROFILE_NAMES else float(drawn.get(name, values.get(name, 0.0)))
                        for name in model.space.names])
    index = {name: model.space.names.index(name) for name in PROFILE_NAMES if name in model.space.names}
    return DesignSlice(run.name, run, setup, model, theta, samples, height_name, height_mm, index)


# ------------------------------------------------------------------------------------------------ the engine

@dataclass
class Response:
    """What one garment gives on one slice at one theta (mmHg), and the derivatives with respect to the design
    variables (T, then the profile's coefficients): d<name>[j]."""

    landmarks: dict
    skin_mean: float
    regions: dict
    d_landmarks: dict
    d_skin_mean: np.ndarray
    d_regions: dict
    deformed_perimeter_mm: float
    nodal_pressure_mmHg: np.ndarray | None = None
    deformed_nodes: np.ndarray | None = None
    sensitivity: str = "engine"

    def value(self, kind: str, where: str | None) -> float:
        if kind == "landmark":
            return self.landmarks[where]
        return self.skin_mean if kind == "skin" else self.regions[where]

    def gradient(self, kind: str, where: str | None) -> np.ndarray:
        if kind == "landmark":
            return self.d_landmarks[where]
        return self.d_skin_mean if kind == "skin" else self.d_regions[where]


def evaluate(piece: DesignSlice, tension: float, profile: Sequence[float], theta: Sequence[float] | None = None,
             *, keep_fields: bool = False) -> Response:
    """Solve the garment (tension, profile) on the slice at theta (default the identified one): `Response`."""
    theta = piece.theta_with(piece.theta if theta is None else theta, profile)
    if piece.laplace:
        return _solve(piece, tension, profile, theta, keep_fields, sensitivities=True)
    base = _solve(piece, tension, profile, theta, keep_fields, sensitivities=False)
    step = DIFFERENCE_STEP * tension
    up = _solve(piece, tension + step, profile, theta, False, sensitivities=False)
    base.d_landmarks = {n: np.array([(up.landmarks[n] - v) / step]) for n, v in base.landmarks.items()}
    base.d_skin_mean = np.array([(up.skin_mean - base.skin_mean) / step])
    base.d_regions = {n: np.array([(up.regions[n] - v) / step]) for n, v in base.regions.items()}
    base.sensitivity = "difference"
    return base


def _solve(piece: DesignSlice, tension: float, profile: Sequence[float], theta: list[float], keep_fields: bool,
           sensitivities: bool) -> Response:
    from ..engine.results import EngineResults
    from ..engine.runner import run_engine, write_mesh_include

    lines = ["TENSION, SKIN"] + [f"PROFILE, GARMENT, {name.upper()}" for name in PROFILE_NAMES[:len(profile)]]
    if sensitivities:
        deck = piece.model.deck(theta, tension_N_per_mm=tension, extra_sensitivities=lines, own_sensitivities=False)
        # templates/sensitivity.inp.j2 writes the plain block first; the element pressures' derivatives are asked
        # on it (the fits read du/dtheta alone and never ask them)
        deck = deck.replace("*SENSITIVITY\n", "*SENSITIVITY, PRESSURE=YES\n", 1)
        if "*SENSITIVITY, PRESSURE=YES\n" not in deck:
            raise RuntimeError("the leg deck has no plain *SENSITIVITY block for the tension's line: "
                               "templates/sensitivity.inp.j2 changed; ask PRESSURE=YES there")
    else:
        deck = piece.model.deck(theta, tension_N_per_mm=tension, sensitivities=False)
    with tempfile.TemporaryDirectory(prefix="calfit-design-") as scratch:
        folder = Path(scratch)
        write_mesh_include(piece.model, folder)
        (folder / "deck.inp").write_text(deck)
        outcome = run_engine(folder / "deck.inp", folder / "out", threads=1, timeout_s=300)
        if not outcome.converged:
            raise RunFolderError(f"the engine did not converge on {piece.run_dir} under a garment of {tension:.4g} "
                                 f"N/mm: narrow tension_range_N_per_mm under [design] in TARGET.toml")
        results = EngineResults(outcome.outdir)
        return _response(piece, results, tension, np.asarray(profile, float), sensitivities, keep_fields)


def _response(piece, results, tension, profile, sensitivities, keep_fields) -> Response:
    n_leg = len(piece.mesh.nodes)
    u = results.displacement()[:n_leg]
    pressure = np.asarray(results.point_field("pressure"), float)[:n_leg] * KPA_PER_MPA * MMHG_PER_KPA
    names = list(piece.landmarks)
    at = piece._landmark_weights @ pressure if names else np.zeros(0)
    landmarks = dict(zip(names, map(float, at)))
    x = piece.mesh.nodes[piece.skin_nodes] + u[piece.skin_nodes]
    factor = piece.factor(profile)
    skin = skin_pressures(x, tension * factor, piece)
    n_vars = 1 + len(profile)
    d_landmarks = {n: np.zeros(n_vars) for n in names}
    d_skin, d_regions = np.zeros(n_vars), {n: np.zeros(n_vars) for n in REGION_NAMES}
    if sensitivities:
        du = results.sensitivities()
        dp = results.pressure_sensitivities()
        keys = ["TENSION:SKIN"] + [f"PROFILE:GARMENT:{name.upper()}" for name in PROFILE_NAMES[:len(profile)]]
        nodal_of = _cell_to_nodes(piece.mesh)
        for j, key in enumerate(keys):
            dp_nodes = nodal_of @ (np.asarray(dp[key], float)[:len(piece.mesh.elements)]) * KPA_PER_MPA * MMHG_PER_KPA
            values = piece._landmark_weights @ dp_nodes if names else []
            for name, value in zip(names, values):
                d_landmarks[name][j] = float(value)
            direction = np.asarray(du[key], float)[:n_leg][piece.skin_nodes]
            # explicit: T(t) itself; implicit: the skin's curvature moved along du/dv (a central difference)
            explicit = factor if j == 0 else tension * harmonic(piece, PROFILE_NAMES[j - 1])
            size = float(np.max(np.abs(direction))) or 1.0
            eps = 1e-3 / size
            ahead = skin_pressures(x + eps * direction, tension * factor, piece)
            behind = skin_pressures(x - eps * direction, tension * factor, piece)
            moved = skin_pressures(x, explicit, piece)   # linear in the load: the explicit part alone
            d_skin[j] = moved["mean"] + (ahead["mean"] - behind["mean"]) / (2 * eps)
            for region in REGION_NAMES:
                # the maximum's derivative at the node where it is
                d_regions[region][j] = (moved["local"][skin["argmax"][region]]
                                        + (ahead["local"][skin["argmax"][region]]
                                           - behind["local"][skin["argmax"][region]]) / (2 * eps))
    return Response(landmarks, skin["mean"], skin["regions"], d_landmarks, d_skin, d_regions,
                    float(skin["perimeter"]), pressure if keep_fields else None,
                    (piece.mesh.nodes + u) if keep_fields else None)


def harmonic(piece: DesignSlice, name: str) -> np.ndarray:
    k = int(name[1])
    return np.cos(k * piece.deck_angle) if name[0] == "a" else np.sin(k * piece.deck_angle)


def skin_pressures(points: np.ndarray, tension_at_nodes: np.ndarray, piece: DesignSlice) -> dict:
    """Laplace's law p = T(t) kappa on a closed skin polyline (mmHg): its mean over the length, the local value
    smoothed over SMOOTHING_MM, its largest value over each region and where (`argmax`), and the perimeter."""
    ahead, behind = np.roll(points, -1, 0), np.roll(points, 1, 0)
    e1, e2 = points - behind, ahead - points
    l1, l2 = np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1)
    turn = np.arctan2(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0], np.sum(e1 * e2, axis=1))
    # the loop runs with the tissue on its left: a convex leg turns one way all round; take the sense it turns
    turn = turn * np.sign(np.sum(turn)) if np.sum(turn) != 0 else turn
    tributary = 0.5 * (l1 + l2)
    force = tension_at_nodes * turn   # N/mm x rad: the load T kappa l of each node, N per mm of height
    perimeter = float(np.sum(l2))
    mean = float(np.sum(force) / perimeter) * 1000.0 * MMHG_PER_KPA     # N/mm^2 = MPa -> kPa -> mmHg
    arc = np.concatenate([[0.0], np.cumsum(l2)[:-1]])
    local = np.empty(len(points))
    for i in range(len(points)):
        gap = np.abs(arc - arc[i])
        inside = np.minimum(gap, perimeter - gap) <= SMOOTHING_MM / 2.0
        local[i] = np.sum(force[inside]) / np.sum(tributary[inside])
    local *= 1000.0 * MMHG_PER_KPA
    regions, argmax = {}, {}
    for name, mask in piece.regions.items():
        indices = np.nonzero(mask)[0] if mask.any() else np.arange(len(points))
        best = indices[int(np.argmax(local[indices]))]
        regions[name], argmax[name] = float(local[best]), int(best)
    return {"mean": mean, "local": local, "regions": regions, "argmax": argmax, "perimeter": perimeter}


def _cell_to_nodes(mesh):
    """Sparse (n_nodes, n_elements): a node's value the mean of its elements' (the VTU's nodal pressure is such an
    average of the elements' values)."""
    from scipy import sparse

    elements = np.asarray(mesh.elements)
    rows = elements.ravel()
    cols = np.repeat(np.arange(len(elements)), elements.shape[1])
    matrix = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(mesh.nodes), len(elements)))
    counts = np.asarray(matrix.sum(axis=1)).ravel()
    counts[counts == 0] = 1.0
    return sparse.diags(1.0 / counts) @ matrix
