"""Region-boundary curves and their resampling to a target edge length.

A `Curve` is one piece of interface between two regions (tissue, background or a
bone), densely sampled: either a closed loop or an open chain between two
junctions (points where three regions meet). Every interface is one curve, shared
by the regions on its two sides, so the mesh built from the curves is conforming.

Resampling places vertices at equal steps of the integral of ds / h(s), where the
local edge length h(s) is the smallest of
  - the requested edge length,
  - max_turn * R(s), R the radius of curvature (a chord turns at most max_turn),
  - feature_factor * lfs(s), lfs the distance to the nearest other part of the
    boundary (thin layers such as anterior fat get edges no longer than their width),
  - bounded below by min_spacing, and graded so that h changes by at most
    `gradation` per unit length along the curve.
The chords of a resampled curve cut inside its convex parts and lose an area of
about h^3 kappa / 12 each. Each interior vertex is therefore moved away from its
centre of curvature by delta = (h1^2 + h2^2) kappa / 24 (h1, h2 the adjacent chord
lengths; L/6 of the discrete Laplacian L for equal chords), which cancels that loss
to second order, so region areas are kept (about 1e-4 relative on a circle cut in 12
chords instead of 4.5e-2). Junction end points never move.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree


@dataclass
class Curve:
    """A densely sampled interface. points (k, 2) mm; sides = the two region keys it separates."""

    points: np.ndarray
    closed: bool
    sides: tuple[int, int]

    def arc_length(self) -> np.ndarray:
        """Cumulative arc length at each point (for a closed curve, the closing chord not included)."""
        steps = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])

    def length(self) -> float:
        length = self.arc_length()[-1]
        if self.closed:
            length += float(np.linalg.norm(self.points[0] - self.points[-1]))
        return length


def smooth_points(points: np.ndarray, closed: bool, sigma: float) -> np.ndarray:
    """Gaussian smoothing along the curve (sigma in samples); open curves keep their end points."""
    if sigma <= 0 or len(points) < 3:
        return points.copy()
    if closed:
        return gaussian_filter1d(points, sigma, axis=0, mode="wrap")
    # Point reflection about each end keeps the ends in place and straight lines straight.
    pad = min(len(points) - 1, int(np.ceil(4 * sigma)))
    head = 2 * points[0] - points[pad:0:-1]
    tail = 2 * points[-1] - points[-2 : -pad - 2 : -1]
    extended = np.vstack([head, points, tail])
    smoothed = gaussian_filter1d(extended, sigma, axis=0, mode="nearest")[pad : pad + len(points)]
    smoothed[0], smoothed[-1] = points[0], points[-1]
    return smoothed


def equal_arc_samples(points: np.ndarray) -> tuple[np.ndarray, float]:
    """A closed curve's points resampled at as many equal steps of arc length, and the step (mm)."""
    closed_loop = np.vstack([points, points[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed_loop, axis=0), axis=1))])
    count = len(points)
    even = np.linspace(0.0, arc[-1], count, endpoint=False)
    return np.column_stack([np.interp(even, arc, closed_loop[:, k]) for k in range(2)]), arc[-1] / count


def lowpass_closed(points: np.ndarray, cutoff_mm: float, order: int = 4) -> np.ndarray:
    """A closed curve low-pass filtered along its arc length: resampled at equal steps, its coordinates' Fourier
    series multiplied by the Butterworth response 1 / (1 + (lambda_c / lambda)^(2 order)), lambda the wavelength.
    Shapes longer than the cut-off wavelength are kept as they are (a Gaussian shrinks every convex curve); the
    pixel staircase and the noise of a segmentation, shorter, are removed."""
    if cutoff_mm <= 0 or len(points) < 8:
        return points.copy()
    samples, spacing = equal_arc_samples(points)
    return lowpass_periodic(samples, spacing, cutoff_mm, order)


def lowpass_periodic(values: np.ndarray, spacing_mm: float, cutoff_mm: float, order: int = 4) -> np.ndarray:
    """Columns of periodic samples `spacing_mm` apart, through the Butterworth low-pass of `lowpass_closed`."""
    values = np.asarray(values, float)
    frequency = np.fft.rfftfreq(len(values), d=spacing_mm)     # cycles per mm
    response = 1.0 / (1.0 + (frequency * cutoff_mm) ** (2 * order))
    shape = (-1,) + (1,) * (values.ndim - 1)
    return np.fft.irfft(np.fft.rfft(values, axis=0) * response.reshape(shape), n=len(values), axis=0)


SHAPE_OVER_ERROR = 3.0     # a wavelength band is the outline's shape where its power is 3 times the error's or more
BANDS_PER_OCTAVE = 3
ERROR_BAND = (0.75, 1.5)   # the wavelengths, times the shortest shape, that hold the outline's error alone


@dataclass(frozen=True)
class OutlineError:
    """What a measured closed outline's own Fourier spectrum says of its error (`outline_error`).

    cutoff_mm: the shortest wavelength at which the outline's shape stands out of its error, where a low-pass
    keeps the shape and drops the error (the Wiener filter's crossover); mode_variance_mm2: the error's variance per
    Fourier coefficient of a normal offset, alpha_k and beta_k of sum_k alpha_k cos(2 pi k s / L) + beta_k
    sin(2 pi k s / L), as white noise; perimeter_mm: L."""

    cutoff_mm: float
    mode_variance_mm2: float
    perimeter_mm: float


def outline_error(points: np.ndarray, shortest_shape_mm: float) -> OutlineError | None:
    """The error of a measured closed outline and the cut-off wavelength that separates it from its shape.

    Wavelengths of ERROR_BAND times `shortest_shape_mm` (the shortest shape the outline can have) hold its
    error alone: the mean power of its Fourier modes there is the error's, taken as white at longer wavelengths
    (where, on outlines of known shape, it is the same or lower). Going from the longest wavelengths down in
    third-octave bands, the shortest band whose mean power is (1 + SHAPE_OVER_ERROR) times the error's or more is
    the last one that holds shape, and the cut-off is the centre of the band below it, where the order-4 Butterworth
    keeps 86 % of the shape's last band (never below shortest_shape_mm; a quarter of the perimeter when only the
    oval stands out: modes 2 and 3 kept at 91 % and more). A shape anywhere in the spectrum keeps its wavelengths,
    so a feature does not need the bands between it and the outline's oval. None when the outline has fewer than 4
    modes in the error's band (too short to tell)."""
    samples, spacing = equal_arc_samples(np.asarray(points, float))
    count = len(samples)
    perimeter = count * spacing
    coefficients = np.fft.rfft(samples - samples.mean(axis=0), axis=0)
    # amplitude^2 of cos and sin of mode k, summed over x and y: alpha_k^2 + beta_k^2 of a normal offset, since
    # the normal turns once per perimeter and shifts a mode's power by one mode
    power = 4.0 * np.sum(np.abs(coefficients) ** 2, axis=1) / count ** 2
    mode = np.arange(len(power))
    wavelength = perimeter / np.maximum(mode, 1)
    usable = (mode >= 2) & (mode < count // 2)
    shortest, longest = (factor * shortest_shape_mm for factor in ERROR_BAND)
    error_band = usable & (wavelength >= shortest) & (wavelength <= longest)
    if np.count_nonzero(error_band) < 4:
        return None
    floor = float(np.mean(power[error_band]))
    cutoff = perimeter / 4.0
    centre = perimeter / 2.0
    half_band = 2.0 ** (0.5 / BANDS_PER_OCTAVE)
    while centre >= shortest_shape_mm:
        band = usable & (wavelength > centre / half_band) & (wavelength <= centre * half_band)
        if np.any(band) and np.mean(power[band]) >= (1.0 + SHAPE_OVER_ERROR) * floor:
            cutoff = centre / half_band ** 2
        centre /= half_band ** 2
    return OutlineError(max(cutoff, shortest_shape_mm), floor / 2.0, perimeter)


def unit_normals(points: np.ndarray, closed: bool) -> np.ndarray:
    """Unit normals (k, 2) of a sampled curve, pointing to the left of its direction."""
    tangent = np.gradient(points, axis=0)
    if closed and len(points) > 2:
        tangent[0], tangent[-1] = points[1] - points[-1], points[0] - points[-2]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    return normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)


def offset_points(points: np.ndarray, closed: bool, move) -> np.ndarray:
    """The curve moved along its normals by `move` (mm, scalar or one per point); open curves keep their ends
    (the junctions other curves share)."""
    move = np.broadcast_to(np.asarray(move, float), (len(points),)).copy()
    if not closed and len(points):
        move[0] = move[-1] = 0.0
    return points + move[:, None] * unit_normals(points, closed)


def curvature(points: np.ndarray, closed: bool, sigma: float) -> np.ndarray:
    """Unsigned curvature (1/mm) at each point, from Gaussian derivatives of width sigma samples."""
    if len(points) < 5:
        return np.zeros(len(points))
    mode = "wrap" if closed else "nearest"
    sigma = max(sigma, 1.0)
    d1 = gaussian_filter1d(points, sigma, axis=0, order=1, mode=mode)
    d2 = gaussian_filter1d(points, sigma, axis=0, order=2, mode=mode)
    cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    speed = np.maximum(np.linalg.norm(d1, axis=1), 1e-12)
    return np.abs(cross) / speed**3


@dataclass
class SpacingRules:
    """Limits on the boundary edge length (mm) that do not depend on the requested size."""

    min_spacing: float
    max_turn_rad: float = np.radians(30.0)
    feature_factor: float = 2.0
    gradation: float = 0.4
    curvature_sigma: float = 3.0


def spacing_limits(curves: list[Curve], rules: SpacingRules, search_radius: float) -> list[np.ndarray]:
    """Per dense point of every curve: the largest allowed edge length from curvature and
    local feature size (graded, at least rules.min_spacing). search_radius bounds the
    feature-size search (features wider than it do not limit the spacing)."""
    kappa = [curvature(c.points, c.closed, rules.curvature_sigma) for c in curves]
    limits = [np.where(k > 0, rules.max_turn_rad / np.maximum(k, 1e-12), np.inf) for k in kappa]
    feature = _local_feature_size(curves, search_radius)
    out = []
    for curve, limit, lfs in zip(curves, limits, feature):
        h = np.minimum(limit, rules.feature_factor * lfs)
        h = np.maximum(h, rules.min_spacing)
        out.append(_grade(h, curve, rules.gradation))
    return out


def _local_feature_size(curves: list[Curve], radius: float) -> list[np.ndarray]:
    """Distance from each point to the nearest boundary point that is not its own
    neighbourhood: on another curve (away from a junction they share), or on the same
    curve but further along it than 3x the straight distance. inf when none within radius."""
    points = np.vstack([c.points for c in curves])
    owner = np.concatenate([np.full(len(c.points), i) for i, c in enumerate(curves)])
    arc = np.concatenate([c.arc_length() for c in curves])
    lengths = np.array([c.length() for c in curves])
    nan_pair = np.full((2, 2), np.nan)
    ends = np.array([nan_pair if c.closed else np.array([c.points[0], c.points[-1]]) for c in curves])
    lfs = np.full(len(points), np.inf)
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        distance = np.linalg.norm(points[i] - points[j], axis=1)
        same = owner[i] == owner[j]
        along = np.abs(arc[i] - arc[j])
        closed_owner = np.array([c.closed for c in curves])[owner[i]]
        along = np.where(same & closed_owner, np.minimum(along, lengths[owner[i]] - along), along)
        valid = np.where(same, along > 3.0 * distance, True)
        # Near a junction that two curves share they are close only because they meet there.
        ends_i, ends_j = ends[owner[i]], ends[owner[j]]
        for k in range(2):
            junction = ends_i[:, k]
            shared = ~same & np.any(np.all(np.abs(ends_j - junction[:, None, :]) < 1e-9, axis=2), axis=1)
            to_junction = np.minimum(
                np.linalg.norm(points[i] - junction, axis=1), np.linalg.norm(points[j] - junction, axis=1)
            )
            valid &= ~(shared & (to_junction < 2.0 * distance))
        np.minimum.at(lfs, i[valid], distance[valid])
        np.minimum.at(lfs, j[valid], distance[valid])
    starts = np.cumsum([0] + [len(c.points) for c in curves])
    return [lfs[starts[k] : starts[k + 1]] for k in range(len(curves))]


def _grade(h: np.ndarray, curve: Curve, gradation: float) -> np.ndarray:
    """Limit the growth of h along the curve: h_i <= h_j + gradation * |s_i - s_j|."""
    h = h.copy()
    steps = np.linalg.norm(np.diff(curve.points, axis=0), axis=1)
    if curve.closed:
        steps = np.append(steps, np.linalg.norm(curve.points[0] - curve.points[-1]))
    n = len(h)
    passes = 2 if curve.closed else 1
    for _ in range(passes):
        for k in range(1, n + (1 if curve.closed else 0)):
            a, b = (k - 1) % n, k % n
            h[b] = min(h[b], h[a] + gradation * steps[k - 1])
        for k in range(n - 1 + (1 if curve.closed else 0), 0, -1):
            a, b = k % n, (k - 1) % n
            h[b] = min(h[b], h[a] + gradation * steps[k - 1])
    return h


def resample(curve: Curve, limit: np.ndarray, edge_length: float) -> np.ndarray:
    """Vertices of the curve at local spacing min(edge_length, limit), area-corrected.

    Closed curves: (n, 2) vertices, the closing edge implied. Open curves: (n + 1, 2),
    first and last equal to the curve's end points.
    """
    points = curve.points
    h = np.minimum(limit, edge_length)
    if curve.closed:
        points = np.vstack([points, points[:1]])
        h = np.append(h, h[0])
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    # u(s) = integral of ds / h(s), trapezoidal rule.
    u = np.concatenate([[0.0], np.cumsum(steps * 0.5 * (1.0 / h[1:] + 1.0 / h[:-1]))])
    minimum = 3 if curve.closed else 2
    n_edges = max(minimum, int(round(u[-1])))
    targets = np.linspace(0.0, u[-1], n_edges + 1)
    s = np.interp(targets, u, arc)
    vertices = np.column_stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])])
    if curve.closed:
        vertices = vertices[:-1]
    else:
        vertices[0], vertices[-1] = curve.points[0], curve.points[-1]
    return _preserve_area(vertices, curve.closed)


def _preserve_area(vertices: np.ndarray, closed: bool) -> np.ndarray:
    """Move interior vertices away from their centre of curvature by (h1^2 + h2^2) kappa / 24."""
    if len(vertices) < 3:
        return vertices
    if closed:
        previous, following = np.roll(vertices, 1, axis=0), np.roll(vertices, -1, axis=0)
        inner = slice(None)
    else:
        previous, following = vertices[:-2], vertices[2:]
        inner = slice(1, -1)
    centre = vertices[inner]
    h1 = np.linalg.norm(centre - previous, axis=1)
    h2 = np.linalg.norm(following - centre, axis=1)
    weighted = (h2[:, None] * previous + h1[:, None] * following) / (h1 + h2)[:, None]
    laplacian = weighted - centre  # = h1 h2 kappa_vector / 2
    shift = -laplacian * ((h1**2 + h2**2) / (12.0 * h1 * h2))[:, None]
    out = vertices.copy()
    out[inner] = centre + shift
    return out
