"""The triangle mesh of a leg slice and its two outputs: a deck include and VTU.

`Mesh` holds what the engine needs from meshing: node positions (mm, image frame of
docs/design.md: x to the right, y downwards), linear (CPE3) or quadratic (CPE6)
triangles, a tissue id per element, node sets (bones) and the skin as element
faces. Indices are 0-based in Python and 1-based in the deck.

Orientation convention. Every element is counter-clockwise *in the (x, y)
coordinates written to the deck*: its signed area
    A = ((x2 - x1)(y3 - y1) - (x3 - x1)(y2 - y1)) / 2
is positive. Because y points down the image, such an element looks clockwise on
screen; the deck (and the engine) only ever see the numbers, so the rule is stated
on the numbers. Face k of an element joins corner k to corner k+1 (face 3: corner 3
to corner 1), as in Abaqus/CalculiX; with the orientation above the element lies to
the left of each directed face, and the outward normal of a face with direction
(tx, ty) is (ty, -tx). T6 mid-side nodes are numbered 4: 1-2, 5: 2-3, 6: 3-1.

The skin loop (`Mesh.skin_loop`) lists the skin nodes (corners and, for T6, the
mid-side nodes) in the direction of the skin faces, i.e. with the tissue on the
left: the closed polyline has positive signed area in deck coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence, TextIO

import numpy as np

from ..core.tissues import COMPARTMENT_PREFIX, MUSCLE_SET, element_set_of_label

ELEMENT_TYPES = {3: "CPE3", 6: "CPE6"}
ITEMS_PER_SET_LINE = 16  # Abaqus/CalculiX read at most 16 entries per data line
FACE_CORNERS = np.array([[0, 1], [1, 2], [2, 0]])  # face k (1-based) joins these corners
FACE_MIDSIDE = np.array([3, 4, 5])  # T6 mid-side node of face k




def muscle_sets(element_sets: Sequence[str]) -> list[str]:
    """The element sets that hold muscle: MUSCLE and every COMPARTMENTk (labels >= 4)."""
    return [name for name in element_sets if name == MUSCLE_SET or name.startswith(COMPARTMENT_PREFIX)]


def compartment_sets(element_sets: Sequence[str]) -> list[str]:
    return sorted(name for name in element_sets if name.startswith(COMPARTMENT_PREFIX))


def signed_areas(nodes: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """Signed area of each triangle from its three corners (positive = counter-clockwise)."""
    p1, p2, p3 = (nodes[elements[:, k]] for k in range(3))
    return 0.5 * ((p2[:, 0] - p1[:, 0]) * (p3[:, 1] - p1[:, 1]) - (p3[:, 0] - p1[:, 0]) * (p2[:, 1] - p1[:, 1]))


def corner_angles_deg(nodes: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """(m, 3) interior angles of each triangle at its corners, in degrees."""
    corners = nodes[elements[:, :3]]
    angles = np.empty((len(elements), 3))
    for k in range(3):
        a = corners[:, (k + 1) % 3] - corners[:, k]
        b = corners[:, (k + 2) % 3] - corners[:, k]
        cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        angles[:, k] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return angles


def face_edges(elements: np.ndarray) -> np.ndarray:
    """(m, 3, 2) corner node pairs of faces S1..S3 of every element, in face direction."""
    return elements[:, FACE_CORNERS]


def add_midside_nodes(nodes: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Promote T3 to T6: one new node at the midpoint of every edge, shared by its two elements.

    Returns (nodes, elements) with elements (m, 6) in the order corner 1..3, then the
    mid-side nodes of edges 1-2, 2-3, 3-1. The new nodes lie on the straight edges,
    also on curved boundaries (the boundary stays the polygon of the T3 mesh).
    """
    edges = np.sort(face_edges(triangles).reshape(-1, 2), axis=1)
    unique_edges, edge_of_face = np.unique(edges, axis=0, return_inverse=True)
    midpoints = 0.5 * (nodes[unique_edges[:, 0]] + nodes[unique_edges[:, 1]])
    midside = len(nodes) + edge_of_face.reshape(-1, 3)
    return np.vstack([nodes, midpoints]), np.hstack([triangles, midside])


@dataclass
class Mesh:
    """A conforming plane triangle mesh of the soft tissues of one slice.

    nodes            (n, 2) float, mm, image frame (x right, y down)
    elements         (m, 3) for CPE3 or (m, 6) for CPE6, 0-based node indices
    element_regions  (m,) tissue label of each element (1 fat, 2 muscle, >= 4 compartments)
    node_sets        name -> sorted 0-based node indices (BONE1, BONE2, ..., BONES, SKIN_NODES, ...)
    skin_faces       (k, 2) int: (0-based element index, face number 1..3) of the outer skin
    skin_loop        skin node indices in closed-polyline order (tissue on the left)
    """

    nodes: np.ndarray
    elements: np.ndarray
    element_regions: np.ndarray
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    skin_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    skin_loop: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def element_type(self) -> str:
        return ELEMENT_TYPES[self.elements.shape[1]]

    @property
    def order(self) -> int:
        return 1 if self.elements.shape[1] == 3 else 2

    @property
    def n_dof(self) -> int:
        return 2 * len(self.nodes)

    def element_sets(self) -> dict[str, np.ndarray]:
        """Tissue name -> 0-based element indices (FAT, MUSCLE, COMPARTMENT4, ...)."""
        return {
            element_set_of_label(int(region)): np.flatnonzero(self.element_regions == region)
            for region in np.unique(self.element_regions)
        }

    def signed_areas(self) -> np.ndarray:
        return signed_areas(self.nodes, self.elements)

    def min_angle_deg(self) -> float:
        return float(corner_angles_deg(self.nodes, self.elements).min())

    def region_areas(self) -> dict[str, float]:
        """Tissue name -> area in mm^2 (from the straight-sided corner triangles)."""
        areas = self.signed_areas()
        return {name: float(areas[ids].sum()) for name, ids in self.element_sets().items()}

    def skin_points(self) -> np.ndarray:
        """Positions of the skin loop nodes, (k, 2) mm, in loop order."""
        return self.nodes[self.skin_loop]

    # --- output -------------------------------------------------------------------------

    def write_include(self, target: str | Path | TextIO) -> None:
        """Write *NODE, *ELEMENT, *ELSET, *NSET and *SURFACE blocks (1-based ids).

        The node block also defines NSET=NALL (all nodes), handy for *NODE PRINT.
        Numbers are written with 10 significant digits.
        """
        if isinstance(target, (str, Path)):
            with open(target, "w") as stream:
                self._write_include(stream)
        else:
            self._write_include(target)

    def include_text(self) -> str:
        from io import StringIO

        buffer = StringIO()
        self._write_include(buffer)
        return buffer.getvalue()

    def _write_include(self, out: TextIO) -> None:
        out.write("** calfit mesh: %d nodes, %d %s elements, mm\n" % (len(self.nodes), len(self.elements), self.element_type))
        out.write("*NODE, NSET=NALL\n")
        ids = np.arange(1, len(self.nodes) + 1)
        out.write("".join("%d, %.10g, %.10g\n" % (i, x, y) for i, (x, y) in zip(ids, self.nodes.tolist())))
        out.write(f"*ELEMENT, TYPE={self.element_type}, ELSET=EALL\n")
        row_format = "%d" + ", %d" * self.elements.shape[1] + "\n"
        numbered = np.hstack([np.arange(1, len(self.elements) + 1)[:, None], self.elements + 1])
        out.write("".join(row_format % tuple(row) for row in numbered.tolist()))
        for name, members in self.element_sets().items():
            out.write(f"*ELSET, ELSET={name}\n")
            out.write(_id_lines(members + 1))
        for name, members in self.node_sets.items():
            out.write(f"*NSET, NSET={name}\n")
            out.write(_id_lines(np.asarray(members) + 1))
        if len(self.skin_faces):
            out.write("*SURFACE, NAME=SKIN, TYPE=ELEMENT\n")
            out.write("".join("%d, S%d\n" % (e + 1, k) for e, k in self.skin_faces.tolist()))

    def to_meshio(self):
        """meshio.Mesh with z = 0 appended, cell data `region`, point and cell sets."""
        import meshio

        cell_type = "triangle" if self.order == 1 else "triangle6"
        points = np.hstack([self.nodes, np.zeros((len(self.nodes), 1))])
        return meshio.Mesh(
            points,
            [(cell_type, self.elements)],
            cell_data={"region": [self.element_regions.astype(np.int32)]},
            point_sets={name: np.asarray(ids) for name, ids in self.node_sets.items()},
            cell_sets={name: [ids] for name, ids in self.element_sets().items()},
        )

    def write_vtu(self, path: str | Path) -> None:
        self.to_meshio().write(str(path), file_format="vtu")


def _id_lines(ids: np.ndarray) -> str:
    ids = np.asarray(ids, dtype=np.int64)
    lines = []
    for start in range(0, len(ids), ITEMS_PER_SET_LINE):
        lines.append(", ".join(str(i) for i in ids[start : start + ITEMS_PER_SET_LINE].tolist()))
    return "\n".join(lines) + "\n" if lines else ""


def read_include(path: str | Path):
    """Read a deck or mesh include back with meshio's Abaqus reader (nodes, elements, sets).

    meshio 5.3 maps CPE6 to triangle6 but has no entry for the 3-node plane-strain
    triangle CPE3; it is added (as "triangle", the node layout of CPS3) before reading.
    """
    import meshio
    from meshio.abaqus import _abaqus

    _abaqus.abaqus_to_meshio_type.setdefault("CPE3", "triangle")
    return meshio.read(str(path), file_format="abaqus")
