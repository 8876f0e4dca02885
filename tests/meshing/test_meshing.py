"""Tests of orchestrator.meshing: label image and analytic leg slice to a conforming mesh.

What is checked, on label images made here (a two-bone annulus-like leg on
anisotropic pixels, and a leg with muscle compartments and triple junctions) and on
the analytic leg slice: element counts within 10% of the request, minimum angle of
at least 20 degrees, tissue areas within 2% of the pixel areas, conformity (each
interior edge shared by exactly two elements, no hanging node, Euler's relation),
positive orientation in deck coordinates, bone node sets on the bone pixel edges,
skin faces on the outer boundary and outward, T6 mid-side nodes at edge midpoints,
the deck include and VTU read back by meshio, the deck's loads and sets, and (when
ccx is installed) CalculiX running the leg-slice deck with T3 and T6 elements.
"""

from __future__ import annotations

import shutil
import subprocess

import meshio
import numpy as np
import pytest
from scipy.spatial import cKDTree
from skimage.measure import find_contours

from orchestrator.core.tissues import element_set_of_label
from orchestrator.meshing import (
    DEFAULT_PRESSURE_MPA,
    Mesh,
    corner_angles_deg,
    leg_slice_deck,
    leg_slice_geometry,
    leg_slice_mesh,
    leg_slice_mesh_for_dof,
    mesh_from_labels,
    read_include,
    region_image,
)
from orchestrator.meshing.labels import interface_curves
from orchestrator.meshing.mesh import FACE_CORNERS, FACE_MIDSIDE

ANISOTROPIC_PIXEL = (0.4, 0.5)  # row, column (mm)
TISSUE_LABELS = {"FAT": 1, "MUSCLE": 2, "COMPARTMENT4": 4, "COMPARTMENT5": 5}


def pixel_centres(shape, pixel_size):
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (cols + 0.5) * pixel_size[1], (rows + 0.5) * pixel_size[0]


def two_bone_leg_labels(pixel_size=ANISOTROPIC_PIXEL) -> np.ndarray:
    """Elliptical leg 110 x 95 mm, fat 3-9 mm thick, a 22 mm and a 12 mm bone."""
    x, y = pixel_centres((int(110 / pixel_size[0]), int(130 / pixel_size[1])), pixel_size)
    r_outer = np.hypot((x - 65) / 55, (y - 55) / 47.5)
    r_fascia = np.hypot((x - 65) / 50, (y - 57) / 42)
    labels = np.zeros(x.shape, dtype=np.uint8)
    labels[r_outer <= 1] = 1
    labels[r_fascia <= 1] = 2
    labels[np.hypot(x - 75, y - 35) <= 11] = 3
    labels[np.hypot(x - 42, y - 55) <= 6] = 3
    return labels


def compartment_leg_labels(pixel_size=(0.5, 0.5)) -> np.ndarray:
    """The analytic leg rasterised, its posterior muscle split in compartments 4 and 5:
    fat / muscle / compartment and muscle / compartment / compartment triple junctions."""
    labels = leg_slice_geometry().label_image(pixel_size[0])
    x, y = pixel_centres(labels.shape, pixel_size)
    muscle = labels == 2
    labels[muscle & (y > 80) & (x < 75)] = 4
    labels[muscle & (y > 80) & (x >= 75)] = 5
    return labels


@pytest.fixture(scope="module")
def two_bone_labels():
    return two_bone_leg_labels()


@pytest.fixture(scope="module")
def compartment_labels():
    return compartment_leg_labels()


@pytest.fixture(scope="module")
def label_meshes(two_bone_labels, compartment_labels):
    """(name, labels, pixel size, requested count, mesh) for each label case."""
    cases = [
        ("two-bone T3 400", two_bone_labels, ANISOTROPIC_PIXEL, 400, 1),
        ("two-bone T6 5500", two_bone_labels, ANISOTROPIC_PIXEL, 5500, 2),
        ("compartments T3 1500", compartment_labels, (0.5, 0.5), 1500, 1),
        ("compartments T6 400", compartment_labels, (0.5, 0.5), 400, 2),
    ]
    return [
        (name, labels, size, n, mesh_from_labels(labels, size, n_elements=n, order=order))
        for name, labels, size, n, order in cases
    ]


@pytest.fixture(scope="module")
def leg_meshes():
    return [(n, order, leg_slice_mesh(n, order)) for n, order in [(400, 1), (400, 2), (5500, 2)]]


def all_meshes(label_meshes, leg_meshes):
    return [(name, mesh) for name, _, _, _, mesh in label_meshes] + [
        (f"leg slice {n} order {order}", mesh) for n, order, mesh in leg_meshes
    ]


def corner_edges(mesh: Mesh):
    """Unique corner-to-corner edges, how many elements use each, and the edge of each face."""
    faces = np.sort(mesh.elements[:, FACE_CORNERS].reshape(-1, 2), axis=1)
    edges, face_edge, uses = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
    return edges, uses, face_edge.reshape(-1, 3)


# --- counts, quality, areas --------------------------------------------------------------


def test_element_counts_are_within_ten_percent_of_the_request(label_meshes, leg_meshes):
    for name, _, _, requested, mesh in label_meshes:
        assert abs(len(mesh.elements) - requested) <= 0.1 * requested, name
    for requested, _, mesh in leg_meshes:
        assert abs(len(mesh.elements) - requested) <= 0.1 * requested


def test_minimum_angle_is_at_least_20_degrees(label_meshes, leg_meshes):
    for name, mesh in all_meshes(label_meshes, leg_meshes):
        assert corner_angles_deg(mesh.nodes, mesh.elements).min() >= 20.0, name


def test_tissue_areas_match_the_pixel_areas_within_2_percent(label_meshes):
    for name, labels, size, _, mesh in label_meshes:
        pixel_area = size[0] * size[1]
        for tissue, area in mesh.region_areas().items():
            expected = np.count_nonzero(labels == TISSUE_LABELS[tissue]) * pixel_area
            assert area == pytest.approx(expected, rel=0.02), (name, tissue)


def test_every_tissue_label_gets_its_element_set(label_meshes):
    for name, labels, _, _, mesh in label_meshes:
        present = {t for t, label in TISSUE_LABELS.items() if np.any(labels == label)}
        assert set(mesh.element_sets()) == present, name


# --- conformity and orientation ----------------------------------------------------------


def test_mesh_is_conforming(label_meshes, leg_meshes):
    for name, mesh in all_meshes(label_meshes, leg_meshes):
        edges, uses, _ = corner_edges(mesh)
        assert set(np.unique(uses)) <= {1, 2}, name
        # Euler: V - E + F = 1 - holes for a connected domain (here: one hole per bone).
        n_corners = len(np.unique(mesh.elements[:, :3]))
        holes = sum(1 for key in mesh.node_sets if key.startswith("BONE") and key != "BONES")
        assert n_corners - len(edges) + len(mesh.elements) == 1 - holes, name
        # No hanging node: no corner lies inside an edge it is not an end of.
        corners = mesh.nodes[np.unique(mesh.elements[:, :3])]
        tree = cKDTree(corners)
        a, b = mesh.nodes[edges[:, 0]], mesh.nodes[edges[:, 1]]
        half = 0.5 * np.linalg.norm(b - a, axis=1)
        for k, near in enumerate(tree.query_ball_point(0.5 * (a + b), half * 0.999)):
            direction = (b[k] - a[k]) / (2 * half[k])
            offsets = corners[near] - a[k]
            off_line = np.abs(offsets[:, 0] * direction[1] - offsets[:, 1] * direction[0])
            assert np.all(off_line > 1e-6 * half[k]), name


def test_tissue_interface_node_sets_hold_the_edges_between_tissues(label_meshes, leg_meshes):
    """Each edge shared by elements of two tissues has both ends in that pair's node set
    (e.g. FAT_MUSCLE), and each such set's corner nodes are exactly those edges' ends."""
    for name, mesh in all_meshes(label_meshes, leg_meshes):
        edges, uses, face_edge = corner_edges(mesh)
        owner_regions = np.zeros((len(edges), 2), dtype=int)
        filled = np.zeros(len(edges), dtype=int)
        for element, row in enumerate(face_edge):
            for edge in row:
                owner_regions[edge, filled[edge]] = mesh.element_regions[element]
                filled[edge] += 1
        mixed = (uses == 2) & (owner_regions[:, 0] != owner_regions[:, 1])
        assert np.any(mixed), name
        expected: dict[str, set] = {}
        for edge in np.flatnonzero(mixed):
            low, high = sorted(owner_regions[edge])
            key = f"{element_set_of_label(int(low))}_{element_set_of_label(int(high))}"
            expected.setdefault(key, set()).update(edges[edge].tolist())
        corner_nodes = set(np.unique(mesh.elements[:, :3]).tolist())
        for key, nodes in expected.items():
            assert set(mesh.node_sets[key].tolist()) & corner_nodes == nodes, (name, key)


def test_elements_are_counter_clockwise_in_deck_coordinates(label_meshes, leg_meshes):
    for name, mesh in all_meshes(label_meshes, leg_meshes):
        assert np.all(mesh.signed_areas() > 0), name
        p = mesh.nodes[mesh.elements[:, :3]]
        cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (
            p[:, 1, 1] - p[:, 0, 1]
        )
        assert np.all(cross > 0), name


def test_t6_midside_nodes_are_edge_midpoints_in_deck_order(label_meshes, leg_meshes):
    quadratic = [(name, m) for name, m in all_meshes(label_meshes, leg_meshes) if m.order == 2]
    assert quadratic
    for name, mesh in quadratic:
        assert mesh.element_type == "CPE6"
        for (i, j), mid in zip(FACE_CORNERS, FACE_MIDSIDE):
            expected = 0.5 * (mesh.nodes[mesh.elements[:, i]] + mesh.nodes[mesh.elements[:, j]])
            np.testing.assert_allclose(mesh.nodes[mesh.elements[:, mid]], expected, atol=1e-12, err_msg=name)
        assert len(np.unique(mesh.elements)) == len(mesh.nodes), name


# --- bones and skin ----------------------------------------------------------------------


def bone_edge_points(labels: np.ndarray, pixel_size, bone_rank: int) -> np.ndarray:
    """Points (mm) every 1/20 pixel along the pixel edges between bone `bone_rank`
    (1 = largest) and the rest: the bone label edge."""
    regions = region_image(labels)
    bone = np.pad(regions == 1000 + bone_rank, 1)
    fractions = np.linspace(0.0, 1.0, 21)
    points = []
    r, c = np.nonzero(bone[1:, :] != bone[:-1, :])  # horizontal edges from corner (r, c - 1)
    for f in fractions:
        points.append(np.column_stack([(c - 1 + f) * pixel_size[1], r * pixel_size[0]]))
    r, c = np.nonzero(bone[:, 1:] != bone[:, :-1])  # vertical edges from corner (r - 1, c)
    for f in fractions:
        points.append(np.column_stack([c * pixel_size[1], (r - 1 + f) * pixel_size[0]]))
    return np.vstack(points)


def test_bone_node_sets_lie_on_the_bone_pixel_edges(label_meshes):
    for name, labels, size, _, mesh in label_meshes:
        assert {"BONE1", "BONE2", "BONES"} <= set(mesh.node_sets), name
        for rank in (1, 2):
            nodes = mesh.nodes[mesh.node_sets[f"BONE{rank}"]]
            distance, _ = cKDTree(bone_edge_points(labels, size, rank)).query(nodes)
            assert distance.max() < max(size), (name, rank)
        union = np.union1d(mesh.node_sets["BONE1"], mesh.node_sets["BONE2"])
        np.testing.assert_array_equal(mesh.node_sets["BONES"], union)


def test_boundary_is_exactly_skin_plus_bones(label_meshes, leg_meshes):
    for name, mesh in all_meshes(label_meshes, leg_meshes):
        edges, uses, face_edge = corner_edges(mesh)
        boundary_faces = {(e, k + 1) for e, k in zip(*np.nonzero(uses[face_edge] == 1))}
        skin = {tuple(face) for face in mesh.skin_faces.tolist()}
        assert skin <= boundary_faces, name
        on_bones = np.isin(mesh.elements[:, FACE_CORNERS], mesh.node_sets["BONES"]).all(axis=2)
        bone_faces = {(e, k + 1) for e, k in zip(*np.nonzero(on_bones & (uses[face_edge] == 1)))}
        assert skin | bone_faces == boundary_faces, name
        assert not skin & bone_faces, name


def test_skin_faces_point_outward_into_the_background(label_meshes):
    for name, labels, size, _, mesh in label_meshes:
        element, face = mesh.skin_faces[:, 0], mesh.skin_faces[:, 1] - 1
        pairs = mesh.elements[:, FACE_CORNERS][element, face]
        a, b = mesh.nodes[pairs[:, 0]], mesh.nodes[pairs[:, 1]]
        tangent = b - a
        outward = np.column_stack([tangent[:, 1], -tangent[:, 0]]) / np.linalg.norm(tangent, axis=1)[:, None]
        centroid = mesh.nodes[mesh.elements[element, :3]].mean(axis=1)
        midpoint = 0.5 * (a + b)
        assert np.all(np.einsum("ij,ij->i", outward, midpoint - centroid) > 0), name
        probe = midpoint + 1.5 * max(size) * outward
        rows = np.floor(probe[:, 1] / size[0]).astype(int)
        cols = np.floor(probe[:, 0] / size[1]).astype(int)
        assert np.mean(labels[rows, cols] == 0) > 0.98, name


def test_skin_loop_is_a_closed_positive_polyline_along_the_skin_faces(label_meshes, leg_meshes):
    for name, mesh in all_meshes(label_meshes, leg_meshes):
        loop = mesh.skin_loop
        step = 2 if mesh.order == 2 else 1
        assert len(loop) == step * len(mesh.skin_faces), name
        assert len(np.unique(loop)) == len(loop), name
        np.testing.assert_array_equal(np.sort(loop), mesh.node_sets["SKIN_NODES"])
        corners = loop[::step]
        directed = {tuple(p) for p in mesh.elements[:, FACE_CORNERS][mesh.skin_faces[:, 0], mesh.skin_faces[:, 1] - 1].tolist()}
        assert {(int(a), int(b)) for a, b in zip(corners, np.roll(corners, -1))} == directed, name
        x, y = mesh.nodes[loop].T
        assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0, name


# --- contours ----------------------------------------------------------------------------


def test_two_region_interface_is_the_find_contours_half_level_contour():
    x, y = pixel_centres((60, 70), (1.0, 1.0))
    radius = np.hypot(x - 35, y - 30)
    labels = np.zeros(radius.shape, dtype=np.uint8)
    labels[radius < 25] = 1
    labels[radius < 20] = 2
    curves = interface_curves(region_image(labels), (1.0, 1.0), smoothing_pixels=0.0)
    fascia = [c for c in curves if set(c.sides) == {1, 2}]
    assert len(fascia) == 1 and fascia[0].closed
    (contour,) = find_contours((labels == 2).astype(float), 0.5)
    expected = np.column_stack([contour[:, 1] + 0.5, contour[:, 0] + 0.5])  # (row, col) index -> mm
    ours = {tuple(p) for p in np.round(fascia[0].points, 9).tolist()}
    theirs = {tuple(p) for p in np.round(expected, 9).tolist()}
    assert ours == theirs


def test_region_image_cleans_specks_holes_and_numbers_bones_by_size():
    x, y = pixel_centres((80, 80), (1.0, 1.0))
    labels = np.zeros((80, 80), dtype=np.uint8)
    labels[np.hypot(x - 40, y - 40) < 35] = 1
    labels[np.hypot(x - 40, y - 40) < 30] = 2
    labels[np.hypot(x - 30, y - 40) < 5] = 3  # small bone
    labels[np.hypot(x - 52, y - 40) < 8] = 3  # large bone
    labels[40, 20] = 1  # fat speck inside muscle
    labels[2:4, 2:4] = 2  # a separate island outside the leg
    labels[60, 40] = 0  # enclosed background
    regions = region_image(labels)
    assert regions[40, 20] == 2
    assert regions[2, 2] == 0
    assert regions[60, 40] == 2
    assert regions[40, 52] == 1001 and regions[40, 30] == 1002
    with pytest.raises(ValueError, match="empty"):
        region_image(np.zeros((10, 10), dtype=np.uint8))
    with pytest.raises(ValueError, match="pixel size"):
        mesh_from_labels(labels, (0.5, -1.0))


# --- output ------------------------------------------------------------------------------


def test_deck_include_round_trips_through_meshio(tmp_path, label_meshes, leg_meshes):
    cases = [label_meshes[0][4], label_meshes[3][4], leg_meshes[1][2]]
    for number, mesh in enumerate(cases):
        path = tmp_path / f"mesh{number}.inp"
        mesh.write_include(path)
        back = read_include(path)
        np.testing.assert_allclose(back.points[:, :2], mesh.nodes, rtol=1e-9, atol=1e-9)
        (block,) = back.cells
        assert block.type == ("triangle" if mesh.order == 1 else "triangle6")
        np.testing.assert_array_equal(block.data, mesh.elements)
        for name, members in mesh.node_sets.items():
            np.testing.assert_array_equal(np.sort(back.point_sets[name]), members)
        for name, members in mesh.element_sets().items():
            np.testing.assert_array_equal(np.sort(back.cell_sets[name][0]), members)
        surface = path.read_text().split("*SURFACE, NAME=SKIN, TYPE=ELEMENT\n")[1].split("*")[0].split()
        faces = np.array([[int(e.rstrip(",")), int(k[1:])] for e, k in zip(surface[::2], surface[1::2])])
        np.testing.assert_array_equal(faces, mesh.skin_faces + [1, 0])


def test_vtu_opens_in_meshio_with_regions(tmp_path, label_meshes):
    mesh = label_meshes[2][4]
    path = tmp_path / "mesh.vtu"
    mesh.write_vtu(path)
    back = meshio.read(path)
    np.testing.assert_allclose(back.points[:, :2], mesh.nodes)
    np.testing.assert_array_equal(back.cells[0].data, mesh.elements)
    np.testing.assert_array_equal(back.cell_data["region"][0], mesh.element_regions)


# --- leg slice and its deck --------------------------------------------------------------


def test_leg_slice_has_the_expected_anatomy(leg_meshes):
    _, _, mesh = leg_meshes[2]
    x, y = mesh.nodes[mesh.skin_loop].T
    assert x.max() - x.min() == pytest.approx(110.0, rel=0.03)
    assert y.max() - y.min() == pytest.approx(95.0, rel=0.03)
    tibia, fibula = (mesh.nodes[mesh.node_sets[k]] for k in ("BONE1", "BONE2"))
    assert np.ptp(tibia[:, 0]) == pytest.approx(23.0, abs=2.0)
    assert np.ptp(fibula[:, 0]) == pytest.approx(13.0, abs=0.5)
    assert tibia[:, 1].mean() < fibula[:, 1].mean()  # tibia anterior (y down)
    areas = mesh.region_areas()
    assert 0.15 < areas["FAT"] / (areas["FAT"] + areas["MUSCLE"]) < 0.35


def test_seeded_leg_slices_mesh_validly():
    for seed in (1, 2, 3):
        mesh = leg_slice_mesh(800, order=1, seed=seed)
        assert abs(len(mesh.elements) - 800) <= 80
        assert np.all(mesh.signed_areas() > 0)
        assert mesh.min_angle_deg() >= 20.0


def test_leg_slice_mesh_for_dof_hits_the_requested_size():
    for n_dof, order in [(5000, 1), (25000, 2)]:
        mesh = leg_slice_mesh_for_dof(n_dof, order)
        assert mesh.n_dof == pytest.approx(n_dof, rel=0.05)


def deck_blocks(text: str) -> dict[str, list[list[str]]]:
    """Keyword line -> its data lines (split at commas); repeated keywords concatenated."""
    blocks: dict[str, list[list[str]]] = {}
    current = None
    for line in text.splitlines():
        if line.startswith("**") or not line.strip():
            continue
        if line.startswith("*"):
            current = line.strip()
            blocks.setdefault(current, [])
        else:
            blocks[current].append([item.strip() for item in line.split(",")])
    return blocks


def test_leg_slice_deck_has_materials_sections_clamps_and_skin_pressure(tmp_path):
    mesh = leg_slice_deck(tmp_path / "leg.inp", n_elements=400, order=2)
    blocks = deck_blocks((tmp_path / "leg.inp").read_text())
    assert blocks["*INCLUDE, INPUT=leg_mesh.inp"] == []
    assert (tmp_path / "leg_mesh.inp").exists()
    assert blocks["*HYPERELASTIC, NEO HOOKE"] == [["0.0045", "9.433962264"], ["0.0112", "14.38848921"]]
    assert "*SOLID SECTION, ELSET=FAT, MATERIAL=FAT" in blocks
    assert "*SOLID SECTION, ELSET=MUSCLE, MATERIAL=MUSCLE" in blocks
    assert blocks["*BOUNDARY"] == [["BONES", "1", "2"]]
    assert blocks["*STEP, NLGEOM, INC=100"] == []
    assert blocks["*STATIC"] == [["1", "1", "0.0001", "1"]]
    loads = blocks["*DLOAD"]
    assert len(loads) == len(mesh.skin_faces)
    assert [[int(e), int(k[1:])] for e, k, _ in loads] == (mesh.skin_faces + [1, 0]).tolist()
    assert [float(p) for _, _, p in loads] == pytest.approx([20 * 0.133322387415e-3] * len(loads), rel=1e-9)
    assert DEFAULT_PRESSURE_MPA == pytest.approx(2.6664e-3, rel=1e-4)
    assert blocks["*NODE PRINT, NSET=NALL"] == [["U"]]


def test_leg_slice_deck_options(tmp_path):
    mesh = leg_slice_mesh(400, order=1)
    leg_slice_deck(tmp_path / "inline.inp", mesh=mesh, include_mesh=False, laplace_tension=0.16)
    blocks = deck_blocks((tmp_path / "inline.inp").read_text())
    assert "*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=0.16" in blocks
    assert "*DLOAD" not in blocks
    assert len(blocks["*NODE, NSET=NALL"]) == len(mesh.nodes)
    assert "*SURFACE, NAME=SKIN, TYPE=ELEMENT" in blocks
    with pytest.raises(ValueError, match="MUSCLE"):
        leg_slice_deck(tmp_path / "bad.inp", mesh=mesh, materials={"FAT": ("NEO HOOKE", (0.0045, 9.4))})


def read_ccx_displacements(path) -> np.ndarray:
    """Last displacement block of a ccx .dat file: (n, 2) u_x, u_y in node order."""
    block = path.read_text().split("displacements")[-1].splitlines()[2:]
    rows = np.array([[float(v) for v in line.split()] for line in block if line.strip()])
    order = np.argsort(rows[:, 0])
    return rows[order, 1:3]


@pytest.mark.ccx
@pytest.mark.skipif(shutil.which("ccx") is None, reason="CalculiX ccx is not installed")
@pytest.mark.parametrize("order", [1, 2])
def test_calculix_runs_the_leg_slice_deck(tmp_path, order):
    mesh = leg_slice_deck(tmp_path / "leg.inp", n_elements=400, order=order)
    run = subprocess.run(["ccx", "-i", "leg"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:]
    assert "error" not in run.stdout.lower()
    u = read_ccx_displacements(tmp_path / "leg.dat")
    assert u.shape == (len(mesh.nodes), 2)
    assert np.all(u[mesh.node_sets["BONES"]] == 0.0)
    skin = mesh.node_sets["SKIN_NODES"]
    outward = mesh.nodes[skin] - mesh.nodes.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", u[skin], outward) < 0)  # the pressure pushes the skin in
    assert 0.1 < np.abs(u).max() < 5.0  # mm: 20 mmHg on kPa-stiff tissue


@pytest.mark.slow
def test_leg_slice_at_200k_dof_is_valid():
    mesh = leg_slice_mesh_for_dof(200_000, order=2)
    assert mesh.n_dof == pytest.approx(200_000, rel=0.05)
    assert np.all(mesh.signed_areas() > 0)
    assert mesh.min_angle_deg() >= 20.0
    _, uses, _ = corner_edges(mesh)
    assert set(np.unique(uses)) <= {1, 2}


def _outline_with_error(rng, mode_variance: float, bump_mm: float = 0.0):
    """An egg-shaped outline (modes up to 3, perimeter about 300 mm) sampled at 0.25 mm, its true curvature, and
    the same outline with a white normal error of `mode_variance` per Fourier coefficient up to 3 mm wavelengths;
    bump_mm: a groove of that depth and 5 mm width on it (a real shape)."""
    count = 1200
    theta = np.linspace(0.0, 2 * np.pi, count, endpoint=False)

    def outline(offset):
        groove = bump_mm * np.exp(-((theta - 1.0) * 48.0 / 5.0) ** 2)
        radius = 48.0 + 4.0 * np.cos(2 * theta) + 1.5 * np.sin(3 * theta) - groove
        return np.column_stack([(radius + offset) * np.cos(theta), (radius + offset) * np.sin(theta)])

    true = outline(0.0)
    perimeter = np.sum(np.linalg.norm(np.diff(np.vstack([true, true[:1]]), axis=0), axis=1))
    modes = np.arange(2, int(perimeter / 3.0))
    alpha, beta = rng.normal(0.0, np.sqrt(mode_variance), (2, len(modes)))
    error = (alpha[:, None] * np.cos(np.outer(modes, theta)) + beta[:, None] * np.sin(np.outer(modes, theta))).sum(0)
    return true, outline(error)


def _turning_curvature(points: np.ndarray) -> np.ndarray:
    before, after = points - np.roll(points, 1, axis=0), np.roll(points, -1, axis=0) - points
    turn = np.arctan2(before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0], np.sum(before * after, axis=1))
    return turn / (0.5 * (np.linalg.norm(before, axis=1) + np.linalg.norm(after, axis=1)))


def _curvature_error(points: np.ndarray, true: np.ndarray) -> float:
    """RMS relative error of the curvature of `points` against the true outline's at the same polar angle."""
    angle = lambda p: np.arctan2(p[:, 1], p[:, 0])
    order = np.argsort(angle(true))
    expected = np.interp(angle(points), angle(true)[order], _turning_curvature(true)[order], period=2 * np.pi)
    return float(np.sqrt(np.mean((_turning_curvature(points) / expected - 1.0) ** 2)))


def test_the_skin_cutoff_is_where_the_outline_stands_out_of_its_measured_error():
    """An outline's own spectrum measures its error (white, per Fourier mode, from its 6-12 mm wavelengths) and puts
    the low-pass where the shape stands out of it: the curvature's error falls from what a fixed 8 mm cut-off leaves,
    and a 5 mm groove, a real shape, keeps its depth."""
    from orchestrator.meshing.curves import lowpass_closed, outline_error

    rng = np.random.default_rng(3)
    variance = 5e-6   # mm^2 per coefficient: 0.003 mm per mode, what the phantoms' and foreign skins show
    for _ in range(3):
        true, measured = _outline_with_error(rng, variance)
        error = outline_error(measured, 8.0)
        # the 6-12 mm band holds about 25 modes: the mean of their power scatters by about 20 %
        assert error is not None and 1 / 1.5 < error.mode_variance_mm2 / variance < 1.5
        assert error.cutoff_mm > 30.0
        assert _curvature_error(lowpass_closed(measured, 8.0), true) > 0.1     # what a fixed cut-off leaves
        assert _curvature_error(lowpass_closed(measured, error.cutoff_mm), true) < 0.02
    true, measured = _outline_with_error(rng, variance, bump_mm=0.5)
    error = outline_error(measured, 8.0)
    assert error.cutoff_mm < 13.0   # a band's centre, 12.0 mm here (the next one up: 15.1 mm)

    def depth(points):   # of the groove: how far the outline dips under the egg about theta = 1 rad
        theta = np.arctan2(points[:, 1], points[:, 0])
        egg = 48.0 + 4.0 * np.cos(2 * theta) + 1.5 * np.sin(3 * theta)
        return np.max((egg - np.linalg.norm(points, axis=1))[np.abs(theta - 1.0) < 0.3])

    # 92 % of the 0.5 mm kept; cut at the next band up (15.1 mm) 85 %, at the error's own cut-off (30 mm) 55 %
    assert depth(lowpass_closed(measured, error.cutoff_mm)) > 0.9 * depth(true)
    assert outline_error(measured[::40], 8.0) is None   # 30 points 10 mm apart: no mode in the error's band
