"""Quality triangulation of a set of interface curves with a requested element count.

Method. The curves (each interface once, see curves.py) are resampled to an edge
length h and handed to Shewchuk's Triangle as one planar straight-line graph, each
curve's segments carrying the curve's marker. A first, unrefined constrained
Delaunay triangulation splits the plane into faces (connected triangles not
separated by a segment); each face is labelled by an area-weighted vote of a
`classify` function (points -> region key) and checked against the region keys
that its bounding curves declare. Tissue faces become Triangle regions (attribute
= tissue label); background and bone faces become holes. The second run refines
with a minimum angle (`q`) and a maximum area (`a`). The maximum area a is the one
unknown: it is adjusted by a secant iteration on log(count) vs log(a) until the
number of tissue triangles is within `count_tolerance` of the request, the boundary
edge length following it as h = sqrt(4 a' / sqrt(3)), a' = BOUNDARY_AREA_RATIO * a
(the mean area of Triangle's elements is about that fraction of the bound).

From the refined triangulation, segment markers give the skin faces (curves
between a tissue and the background), the bone node sets (curves between a tissue
and bone k) and the interface node sets. Region keys: 0 background, tissue labels
1, 2, 4, 5, ..., bone k -> BONE_KEY_OFFSET + k (k = 1 the largest bone).

Source: J. R. Shewchuk, "Triangle: engineering a 2D quality mesh generator and
Delaunay triangulator", 1996 (the `triangle` Python package wraps it).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import triangle

from ..core.errors import MeshingError
from ..core.tissues import element_set_of_label
from .curves import Curve, SpacingRules, resample, spacing_limits
from .mesh import FACE_MIDSIDE, Mesh, add_midside_nodes, face_edges, signed_areas

BONE_KEY_OFFSET = 1000
BOUNDARY_AREA_RATIO = 0.55
MARKER_OFFSET = 2  # Triangle reserves markers 0 and 1


def is_tissue(key: int) -> bool:
    return key == 1 or key == 2 or 4 <= key < BONE_KEY_OFFSET


def bone_name(key: int) -> str:
    return f"BONE{key - BONE_KEY_OFFSET}"


def mesh_curves(
    curves: list[Curve],
    classify: Callable[[np.ndarray], np.ndarray],
    n_elements: int,
    order: int = 1,
    min_angle_deg: float = 25.0,
    rules: SpacingRules | None = None,
    count_tolerance: float = 0.02,
    max_iterations: int = 20,
    accept_closest: bool = False,
) -> Mesh:
    """Conforming T3 (order 1) or T6 (order 2) mesh of the tissue faces bounded by `curves`,
    with about n_elements elements. If no mesh within 10% of the request is found (the
    boundary detail and the quality bound set a minimum count), raise MeshingError, or
    return the closest mesh found when accept_closest is true."""
    if order not in (1, 2):
        raise ValueError(f"order must be 1 (CPE3) or 2 (CPE6), not {order}")
    if n_elements < 10:
        raise ValueError(f"n_elements must be at least 10, not {n_elements}")
    rules = rules or SpacingRules(min_spacing=1e-3)
    tissue_area = _tissue_area(curves, classify)
    first_area = tissue_area / n_elements
    limits = spacing_limits(curves, rules, search_radius=3.0 * _edge_length(first_area) / rules.feature_factor)

    history: list[tuple[float, int, dict]] = []  # every run
    secant: list[tuple[float, int, dict]] = []  # runs with the current boundary limits
    max_area = first_area
    # relax scales the boundary limits: up when they alone give too many elements (a larger max_area no longer
    # lowers the count), down when they alone give too few (max_area 1.5x smaller, the count the same), bisecting
    # between the last too-fine and too-coarse values once both are known (fine images: dense boundary detail)
    relax, too_fine, too_coarse = 1.0, None, None
    for _ in range(max_iterations):
        relaxed = [np.maximum(limit * relax, rules.min_spacing) for limit in limits]
        result = _refine(curves, classify, relaxed, max_area, min_angle_deg)
        count = len(result["triangles"])
        history.append((max_area, count, result))
        secant.append(history[-1])
        if abs(count - n_elements) <= count_tolerance * n_elements:
            break
        if len(secant) >= 2 and count > n_elements and max_area > secant[-2][0] and count >= 0.98 * secant[-2][1]:
            too_fine = relax
            relax = relax * 1.3 if too_coarse is None else float(np.sqrt(relax * too_coarse))
            secant = secant[-1:]
        elif count < n_elements and max_area * 1.5 < secant[0][0] and count <= 1.01 * secant[0][1]:
            too_coarse = relax
            relax = relax / 1.3 if too_fine is None else float(np.sqrt(relax * too_fine))
            secant = secant[-1:]
        max_area = _next_area(secant, n_elements)
    best_area, best_count, best = min(history, key=lambda t: abs(t[1] - n_elements))
    if abs(best_count - n_elements) > 0.1 * n_elements and not accept_closest:
        raise MeshingError(
            f"could not mesh with {n_elements} elements (closest: {best_count} with maximum area "
            f"{best_area:.4g} mm^2); the boundary detail needs a different element count"
        )
    return _build_mesh(best, curves, order)


def _edge_length(area: float) -> float:
    return float(np.sqrt(4.0 * BOUNDARY_AREA_RATIO * area / np.sqrt(3.0)))


def _next_area(tried: list[tuple[float, int, dict]], target: int) -> float:
    """Secant step on log(count) = c - slope * log(area), slope clamped to [0.5, 2]."""
    area, count, _ = tried[-1]
    slope = 1.0
    if len(tried) >= 2:
        previous_area, previous_count, _ = tried[-2]
        if previous_area != area and previous_count != count and previous_count > 0:
            slope = -np.log(count / previous_count) / np.log(area / previous_area)
            slope = float(np.clip(slope, 0.5, 2.0))
    return float(area * (max(count, 1) / target) ** (1.0 / slope))


def _tissue_area(curves: list[Curve], classify) -> float:
    """Area of the tissue faces of the dense curves (unrefined triangulation)."""
    vertices, segments, markers = _graph([c.points for c in curves], curves)
    raw = triangle.triangulate({"vertices": vertices, "segments": segments, "segment_markers": markers}, "pQ")
    labels = _face_labels(raw, classify, curves)
    areas = np.abs(signed_areas(raw["vertices"], raw["triangles"]))
    return float(sum(areas[members].sum() for members, key in labels if is_tissue(key)))


def _graph(polylines: list[np.ndarray], curves: list[Curve]):
    """Merge polylines into one vertex list (shared end points once) with marked segments."""
    index_of: dict[tuple[float, float], int] = {}
    vertices: list[np.ndarray] = []
    segments, markers = [], []

    def vertex(point: np.ndarray) -> int:
        key = (round(float(point[0]), 9), round(float(point[1]), 9))
        if key not in index_of:
            index_of[key] = len(vertices)
            vertices.append(point)
        return index_of[key]

    for number, (polyline, curve) in enumerate(zip(polylines, curves)):
        if curve.closed:
            start = len(vertices)
            vertices.extend(polyline)
            ids = np.arange(start, start + len(polyline))
            pairs = np.column_stack([ids, np.roll(ids, -1)])
        else:
            first, last = vertex(polyline[0]), vertex(polyline[-1])
            start = len(vertices)
            vertices.extend(polyline[1:-1])
            ids = np.concatenate([[first], np.arange(start, start + len(polyline) - 2), [last]])
            pairs = np.column_stack([ids[:-1], ids[1:]])
        segments.append(pairs)
        markers.append(np.full(len(pairs), number + MARKER_OFFSET))
    return (
        np.asarray(vertices, dtype=float),
        np.vstack(segments).astype(np.int32),
        np.concatenate(markers)[:, None].astype(np.int32),
    )


def _edge_keys(edges: np.ndarray, n_vertices: int) -> np.ndarray:
    edges = np.sort(edges, axis=-1).astype(np.int64)
    return edges[..., 0] * n_vertices + edges[..., 1]


def _edge_markers(triangles: np.ndarray, segments: np.ndarray, segment_markers: np.ndarray, n_vertices: int):
    """(m, 3) marker of each element face (0 when the face is not on a segment)."""
    face_keys = _edge_keys(face_edges(triangles), n_vertices)
    segment_keys = _edge_keys(segments, n_vertices)
    order = np.argsort(segment_keys)
    sorted_keys = segment_keys[order]
    position = np.clip(np.searchsorted(sorted_keys, face_keys), 0, len(sorted_keys) - 1)
    found = sorted_keys[position] == face_keys
    return np.where(found, segment_markers.ravel()[order][position], 0)


def _face_labels(raw: dict, classify, curves: list[Curve]) -> list[tuple[np.ndarray, int]]:
    """Faces of an unrefined triangulation and their region keys, checked against the curves."""
    tris, verts = raw["triangles"], raw["vertices"]
    n = len(verts)
    markers = _edge_markers(tris, raw["segments"], raw["segment_markers"], n)
    keys = _edge_keys(face_edges(tris), n).ravel()
    owner = np.repeat(np.arange(len(tris)), 3)
    order = np.argsort(keys, kind="stable")
    shared = np.flatnonzero(keys[order][1:] == keys[order][:-1])
    a, b = owner[order][shared], owner[order][shared + 1]
    open_edge = markers.ravel()[order][shared] == 0
    parent = np.arange(len(tris))

    def find(x):
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for u, v in zip(a[open_edge].tolist(), b[open_edge].tolist()):
        ru, rv = find(u), find(v)
        if ru != rv:
            parent[ru] = rv
    roots = np.array([find(t) for t in range(len(tris))])
    centroids = verts[tris].mean(axis=1)
    areas = np.abs(signed_areas(verts, tris))
    point_keys = np.asarray(classify(centroids)).astype(np.int64)
    faces = []
    face_key = np.empty(len(tris), dtype=np.int64)
    for root in np.unique(roots):
        members = np.flatnonzero(roots == root)
        candidates, where = np.unique(point_keys[members], return_inverse=True)
        key = int(candidates[np.argmax(np.bincount(where, weights=areas[members]))])
        face_key[members] = key
        faces.append((members, key))
    # Each segment must separate the two regions its curve was built between.
    face_marker = markers.ravel()[order][shared]
    for u, v, marker in zip(a.tolist(), b.tolist(), face_marker.tolist()):
        if marker:
            sides = set(curves[marker - MARKER_OFFSET].sides)
            if {int(face_key[u]), int(face_key[v])} != sides:
                raise MeshingError(
                    f"curve {marker - MARKER_OFFSET} should separate regions {sorted(sides)} but its "
                    f"faces are {int(face_key[u])} and {int(face_key[v])}; the curves cross or the "
                    "region image is inconsistent"
                )
    return faces


def _refine(curves, classify, limits, max_area: float, min_angle_deg: float) -> dict:
    polylines = [resample(c, limit, _edge_length(max_area)) for c, limit in zip(curves, limits)]
    vertices, segments, markers = _graph(polylines, curves)
    graph = {"vertices": vertices, "segments": segments, "segment_markers": markers}
    raw = triangle.triangulate(graph, "pQ")
    regions, holes = [], []
    for members, key in _face_labels(raw, classify, curves):
        tris = raw["triangles"][members]
        largest = tris[np.argmax(np.abs(signed_areas(raw["vertices"], tris)))]
        seed = raw["vertices"][largest].mean(axis=0)
        if is_tissue(key):
            regions.append([seed[0], seed[1], float(key), 0.0])
        else:
            holes.append(seed)
    if not regions:
        raise MeshingError("no tissue region found inside the curves")
    graph["regions"] = np.array(regions)
    if holes:
        graph["holes"] = np.array(holes)
    return triangle.triangulate(graph, f"pq{min_angle_deg:g}a{max_area:.10g}AQ")


def _build_mesh(refined: dict, curves: list[Curve], order: int) -> Mesh:
    vertices, triangles = refined["vertices"], refined["triangles"].astype(np.int64)
    regions = np.rint(refined["triangle_attributes"][:, 0]).astype(np.int64)
    inverted = signed_areas(vertices, triangles) < 0
    triangles[inverted] = triangles[inverted][:, [0, 2, 1]]
    used = np.unique(triangles)
    renumber = np.full(len(vertices), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    nodes, triangles = vertices[used], renumber[triangles]
    segments = renumber[refined["segments"].astype(np.int64)]
    keep = np.all(segments >= 0, axis=1)
    markers = _edge_markers(triangles, segments[keep], refined["segment_markers"][keep], len(nodes))

    elements = triangles
    if order == 2:
        nodes, elements = add_midside_nodes(nodes, triangles)

    def face_nodes(mask: np.ndarray) -> np.ndarray:
        element, face = np.nonzero(mask)
        corner_pairs = face_edges(elements)[element, face]
        parts = [corner_pairs.ravel()]
        if order == 2:
            parts.append(elements[element, FACE_MIDSIDE[face]])
        return np.unique(np.concatenate(parts))

    curve_sides = {number + MARKER_OFFSET: tuple(int(k) for k in c.sides) for number, c in enumerate(curves)}
    node_sets: dict[str, np.ndarray] = {}
    bone_keys = sorted({k for sides in curve_sides.values() for k in sides if k >= BONE_KEY_OFFSET})
    for key in bone_keys:
        on_bone = np.isin(markers, [m for m, sides in curve_sides.items() if key in sides])
        if np.any(on_bone):
            node_sets[bone_name(key)] = face_nodes(on_bone)
    if bone_keys:
        node_sets["BONES"] = np.unique(np.concatenate([node_sets[bone_name(k)] for k in bone_keys]))
    skin_markers = [m for m, sides in curve_sides.items() if 0 in sides]
    on_skin = np.isin(markers, skin_markers)
    if np.any(on_skin):
        node_sets["SKIN_NODES"] = face_nodes(on_skin)
    tissue_pairs = sorted({tuple(sorted(s)) for s in curve_sides.values() if is_tissue(s[0]) and is_tissue(s[1])})
    for pair in tissue_pairs:
        on_interface = np.isin(markers, [m for m, s in curve_sides.items() if tuple(sorted(s)) == pair])
        if np.any(on_interface):
            node_sets[f"{element_set_of_label(pair[0])}_{element_set_of_label(pair[1])}"] = face_nodes(on_interface)

    skin_element, skin_face = np.nonzero(on_skin)
    skin_faces = np.column_stack([skin_element, skin_face + 1]).astype(np.int64)
    skin_loop = _skin_loop(elements, skin_faces, order) if len(skin_faces) else np.zeros(0, dtype=np.int64)
    return Mesh(nodes, elements, regions, node_sets, skin_faces, skin_loop)


def _skin_loop(elements: np.ndarray, skin_faces: np.ndarray, order: int) -> np.ndarray:
    """Skin nodes in closed-polyline order, following the face direction (tissue on the left)."""
    edges = face_edges(elements)[skin_faces[:, 0], skin_faces[:, 1] - 1]
    midside = elements[skin_faces[:, 0], FACE_MIDSIDE[skin_faces[:, 1] - 1]] if order == 2 else None
    following = {int(a): k for k, a in enumerate(edges[:, 0])}
    if len(following) != len(edges):
        raise MeshingError("the skin is not a simple closed curve (a node starts two skin faces)")
    loop, k = [], 0
    for _ in range(len(edges)):
        loop.append(int(edges[k, 0]))
        if midside is not None:
            loop.append(int(midside[k]))
        k = following.get(int(edges[k, 1]), -1)
        if k == 0:
            break
        if k < 0:
            raise MeshingError("the skin is not a closed curve")
    if k != 0 or (len(loop) != len(edges) * (2 if midside is not None else 1)):
        raise MeshingError("the skin consists of several closed curves; mesh one leg at a time")
    return np.array(loop, dtype=np.int64)
