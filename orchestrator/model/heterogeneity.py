"""A tissue whose stiffness is not one number, without labels beyond fat and muscle: material groups.

A calf's muscle is four compartments of different muscles, its fat is thicker and looser at the back; a
segmentation into fat, muscle and bone knows none of it. Here every tissue element set (FAT, MUSCLE,
COMPARTMENTk) is cut into groups by where its elements lie: `SECTORS` angular sectors of 15 degrees about the
leg's centre (display angles, as `regions` names them) and depth bands (the fat in one, the muscle in
`MUSCLE_BANDS` bands of equal element count by distance to the skin). Each group gets its own material: the
tissue's constants, every modulus (C10 and Kv alike: a stiffer region keeps its tissue's Poisson ratio) multiplied by

    exp( sum_m c_m phi_m(group) + sum_patches p [group in patch] + ln r [group in a region] ),

- `heterogeneity` (a catalog effect): c_m for the modes phi = cos theta, sin theta, cos 2 theta, sin 2 theta and
  the depth d (-1 at the muscle's outside, +1 at its inside) in the muscle, cos theta and sin theta in the fat
  (a thin layer: looser at the back than at the front, nothing finer that a stiff patch would not mimic): a
  smooth field, as the first harmonics of the garment tension are for the pressure;
  du/dc_m = sum_g C10_g phi_m(g) du/dC10_g;
- patches (`patch_effect`): one factor exp(p) on a set of groups, the local stiffness change the diagnosis
  proposes where the catalog explains nothing; du/dp = sum_(g in patch) C10_g du/dC10_g;
- regions (`region_effect`, for the phantom's truth): a stiffness ratio in an angular sector of one tissue,
  cut on the element centroids of whatever mesh carries it (not the groups of the fit);
- cuts (`cut_effect`): one factor exp(p) on the part of a tissue beyond a straight line, cut on the element
  centroids: a compartment whose boundary the images do not show. The calf's compartments are bounded by
  nearly straight sheets (the interosseous membrane between tibia and fibula, the intermuscular septa from the
  fibula to the fascia); a septum too thin for the slice is not in the image, and what differs on its two sides is
  a stiffness step along a line, which neither the smooth field nor a sector patch (a wedge from the leg's centre)
  draws. The line is given by the display angle of its normal, pointing into the changed part, and its distance
  from the leg's centre along it; the mesh groups it crosses are split in two, so that the smooth field, patches
  and the local probe keep working on either side of it.

The exponential keeps every C10 positive for any parameter value; at zero the derivative is the mode itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..meshing.garment import polygon_centroid
from ..meshing.mesh import muscle_sets
from .regions import IMAGE_SIDES, QUARTERS, display_angle_deg

SECTORS = 24
PATCH_MAX_DEG = 90.0   # the widest local change the diagnosis proposes
MUSCLE_BANDS = 3
MODES = ("cos1", "sin1", "cos2", "sin2", "depth")
FAT_MODES = ("cos1", "sin1")
KINDS = ("fat", "muscle")
SECTOR_DEG = 360.0 / SECTORS
PATCH_PREFIX = "patch:"
REGION_PREFIX = "region:"
CUT_PREFIX = "cut:"
GROUP_PREFIX = "G_"
GROUPED_EFFECTS = ("heterogeneity", "local")


def tissue_kind(element_set: str) -> str:
    return "fat" if element_set == "FAT" else "muscle"


@dataclass(frozen=True)
class Group:
    """Elements of one tissue set in one sector and depth band."""

    name: str
    tissue_set: str
    elements: np.ndarray
    sector: int
    band: int
    angle_deg: float      # display angle of the middle of the group's sector
    depth: float          # -1 (next to the skin) .. +1 (deepest) within the tissue; 0 with one band
    area_mm2: float
    depth_range_mm: tuple[float, float]   # distance of its element centroids to the skin
    region: str = ""      # the region effect that made it (truth cases), "" for mesh groups
    cuts: tuple[str, ...] = ()   # the cut effects whose changed part holds the group
    parent: str = ""      # the mesh group a cut split it from ("" when not split: its own name)

    @property
    def mesh_group(self) -> str:
        """The name of the sector-and-band group it belongs to, whatever cuts split it (what patches name)."""
        return self.parent or self.name

    @property
    def kind(self) -> str:
        return tissue_kind(self.tissue_set)

    def mode(self, name: str) -> float:
        angle = np.radians(self.angle_deg)
        return {"cos1": np.cos(angle), "sin1": np.sin(angle), "cos2": np.cos(2 * angle), "sin2": np.sin(2 * angle),
                "depth": self.depth}[name]


def stiffness_field_kpa(model, theta, frame) -> dict[str, dict[str, float]]:
    """A model's C10 where its groups carry their own materials (heterogeneity, a patch), in kPa, area-weighted over
    each tissue ("all") and over each quarter of it about the leg (`regions.LegFrame.quarter`: anterior, lateral,
    posterior, medial): the numbers to hold against a tissue's constant, which the field's reference C10_<tissue>
    is not (a muscle whose anterior third is three times stiffer has no C10 of its own). Empty without groups."""
    constants = model.deck_state(theta).constants
    sums: dict[str, dict[str, list[float]]] = {}
    for group in model.groups:
        c10 = constants.get(group.name, {}).get("C10")
        if c10 is None:
            continue
        for key in ("all", frame.quarter(group.angle_deg)):
            total = sums.setdefault(group.kind, {}).setdefault(key, [0.0, 0.0])
            total[0] += group.area_mm2 * c10 * 1000.0   # the deck's constants are in MPa
            total[1] += group.area_mm2
    order = ("all",) + QUARTERS + IMAGE_SIDES
    return {kind: {key: parts[key][0] / parts[key][1] for key in order if key in parts} for kind, parts in sums.items()}


def stiffness_field_text(field: dict[str, dict[str, float]]) -> str:
    """"muscle 12.6 kPa (anterior 27.0, lateral 12.1, posterior 11.0, medial 12.3), fat 4.1 (...)"."""
    return ", ".join(f"{kind} {parts['all']:.3g} kPa ("
                     + ", ".join(f"{key} {value:.3g}" for key, value in parts.items() if key != "all") + ")"
                     for kind, parts in sorted(field.items(), key=lambda item: item[0] != "muscle"))


def element_geometry(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per element: centroid (mm), display angle about the leg centre (deg), distance to the skin (mm), area.
    The leg centre is the centroid of the area inside the skin (bones included), as `regions.LegFrame` takes it
    from the labels, so that the groups' sectors are the sectors the diagnosis names."""
    corners = mesh.nodes[mesh.elements[:, :3]]
    centroid = corners.mean(axis=1)
    edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    area = 0.5 * np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0])
    skin = mesh.nodes[mesh.skin_loop]
    angle = display_angle_deg(centroid, polygon_centroid(skin))
    a, b = skin, np.roll(skin, -1, axis=0)
    segment = b - a
    t = np.clip(np.einsum("ekd,kd->ek", centroid[:, None, :] - a[None], segment) / np.sum(segment ** 2, axis=1), 0.0, 1.0)
    nearest = a[None] + t[..., None] * segment[None]
    depth = np.min(np.linalg.norm(centroid[:, None, :] - nearest, axis=2), axis=1)
    return centroid, angle, depth, area


def mesh_groups(mesh, tissue_sets: dict[str, np.ndarray], cuts: Sequence[str] = ()) -> list[Group]:
    """The groups of every tissue set (module text), empty ones left out; names like G_MUSCLE_S03B1. The depth
    bands are cut over all the sets of a kind (the muscle compartments together), so that a band means the same
    depth in every compartment. Each cut (`cut_name`) splits the groups of its tissue that it crosses: the part
    beyond its line is named with a suffix C<k> (k its place in `cuts`), the rest keeps the group's name."""
    centroid, angle, depth, area = element_geometry(mesh)
    centre = leg_centre_mm(mesh)
    beyond = {name: parse_cut(name).beyond(centroid, centre) for name in cuts}
    sector = np.minimum((angle / SECTOR_DEG).astype(int), SECTORS - 1)
    band, unit_depth = np.zeros(len(depth), int), np.zeros(len(depth))
    for kind in KINDS:
        members = np.concatenate([np.asarray(ids, int) for name, ids in tissue_sets.items() if tissue_kind(name) == kind]
                                 or [np.zeros(0, int)])
        if len(members) == 0 or kind == "fat":
            continue
        edges = np.quantile(depth[members], np.linspace(0.0, 1.0, MUSCLE_BANDS + 1)[1:-1])
        band[members] = np.searchsorted(edges, depth[members])
        low, high = depth[members].min(), depth[members].max()
        unit_depth[members] = 2.0 * (depth[members] - low) / max(high - low, 1e-12) - 1.0
    groups = []
    for tissue_set, members in tissue_sets.items():
        members = np.asarray(members)
        bands = 1 if tissue_kind(tissue_set) == "fat" else MUSCLE_BANDS
        mine = [c for c in cuts if parse_cut(c).kind == tissue_kind(tissue_set)]
        for s in range(SECTORS):
            for b in range(bands):
                chosen = members[(sector[members] == s) & (band[members] == b)]
                if len(chosen) == 0:
                    continue
                unit = float(np.average(unit_depth[chosen], weights=area[chosen]))
                name = f"{GROUP_PREFIX}{tissue_set}_S{s:02d}B{b}"
                inside = np.stack([beyond[c][chosen] for c in mine], axis=1) if mine else np.zeros((len(chosen), 0), bool)
                for pattern in sorted({tuple(row) for row in inside}):
                    part = chosen[np.all(inside == np.array(pattern, bool), axis=1)]
                    suffix = "".join(f"C{cuts.index(c)}" for c, hit in zip(mine, pattern) if hit)
                    groups.append(Group(name + suffix, tissue_set, part, s, b, float((s + 0.5) * SECTOR_DEG), unit,
                                        float(area[part].sum()), (float(depth[part].min()), float(depth[part].max())),
                                        cuts=tuple(c for c, hit in zip(mine, pattern) if hit),
                                        parent=name if suffix else ""))
    return groups


def leg_centre_mm(mesh) -> np.ndarray:
    """The centroid of the area inside the skin, bones included: the centre of the sectors and of the cuts."""
    return polygon_centroid(mesh.nodes[mesh.skin_loop])


def region_groups(mesh, tissue_sets: dict[str, np.ndarray], regions: dict[str, "Region"]) -> list[Group]:
    """Each tissue set cut by the regions (truth patches, by effect name): a region's elements, and the rest."""
    _, angle, depth, area = element_geometry(mesh)
    groups = []
    for tissue_set, members in tissue_sets.items():
        members = np.asarray(members)
        taken = np.zeros(len(members), bool)
        for k, (name, region) in enumerate(regions.items()):
            if region.kind != tissue_kind(tissue_set):
                continue
            inside = region.contains(angle[members]) & ~taken
            taken |= inside
            if inside.any():
                chosen = members[inside]
                groups.append(Group(f"{GROUP_PREFIX}{tissue_set}_R{k}", tissue_set, chosen, -1, -1, region.centre_deg,
                                    0.0, float(area[chosen].sum()), (float(depth[chosen].min()), float(depth[chosen].max())),
                                    name))
        if (~taken).any():
            chosen = members[~taken]
            groups.append(Group(f"{GROUP_PREFIX}{tissue_set}_REST", tissue_set, chosen, -1, -1, 0.0, 0.0,
                                float(area[chosen].sum()), (float(depth[chosen].min()), float(depth[chosen].max()))))
    return groups


@dataclass(frozen=True)
class Region:
    """An angular sector of one tissue (display angles, counter-clockwise from start to end)."""

    kind: str
    start_deg: float
    end_deg: float

    @property
    def width_deg(self) -> float:
        return (self.end_deg - self.start_deg) % 360.0

    @property
    def centre_deg(self) -> float:
        return (self.start_deg + self.width_deg / 2.0) % 360.0

    def contains(self, angle_deg: np.ndarray) -> np.ndarray:
        return ((np.asarray(angle_deg) - self.start_deg) % 360.0) < self.width_deg


def region_name(kind: str, start_deg: float, end_deg: float) -> str:
    return f"{REGION_PREFIX}{kind}:{start_deg:g}:{end_deg:g}"


def parse_region(name: str) -> Region:
    try:
        _, kind, start, end = name.split(":")
        region = Region(kind, float(start), float(end))
    except ValueError:
        raise ValueError(f"a region effect reads region:<fat|muscle>:<start deg>:<end deg>, not {name!r}") from None
    if kind not in KINDS:
        raise ValueError(f"a region's tissue is fat or muscle, not {kind!r} (in {name!r})")
    if not 0.0 < region.width_deg < 360.0:
        raise ValueError(f"a region spans between 0 and 360 degrees: {name!r}")
    return region


@dataclass(frozen=True)
class Cut:
    """The part of one tissue beyond a straight line: its normal's display angle (counter-clockwise from +x on the
    displayed image, y down; the normal points into the changed part) and the line's signed distance from the leg's
    centre along that normal."""

    kind: str
    normal_deg: float
    offset_mm: float

    def beyond(self, points_mm: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
        angle = np.radians(self.normal_deg)
        normal = np.array([np.cos(angle), -np.sin(angle)])   # display angles: y down
        return (np.asarray(points_mm, float).reshape(-1, 2) - centre_mm) @ normal > self.offset_mm


def cut_share(mesh, name: str) -> float:
    """The share of its tissue's area (every set of that kind) that a cut's line leaves beyond it."""
    cut = parse_cut(name)
    centroid, _, _, area = element_geometry(mesh)
    members = np.concatenate([np.asarray(ids, int) for set_name, ids in tissue_element_sets(mesh).items()
                              if tissue_kind(set_name) == cut.kind] or [np.zeros(0, int)])
    total = float(area[members].sum())
    beyond = cut.beyond(centroid[members], leg_centre_mm(mesh))
    return float(area[members][beyond].sum()) / total if total > 0 else 0.0


def tissue_element_sets(mesh) -> dict[str, np.ndarray]:
    """The mesh's element sets of soft tissue, FAT and the muscle's (MUSCLE or its compartments): what groups cut."""
    sets = mesh.element_sets()
    return {name: ids for name, ids in sets.items() if name == "FAT" or name in muscle_sets(list(sets))}


def is_cut(name: str) -> bool:
    return name.startswith(CUT_PREFIX)


def cut_name(kind: str, normal_deg: float, offset_mm: float) -> str:
    return f"{CUT_PREFIX}{kind}:{normal_deg:g}:{offset_mm:g}"


def parse_cut(name: str) -> Cut:
    try:
        _, kind, normal, offset = name.split(":")
        cut = Cut(kind, float(normal) % 360.0, float(offset))
    except ValueError:
        raise ValueError(f"a cut effect reads cut:<fat|muscle>:<normal deg>:<offset mm>, not {name!r}") from None
    if kind not in KINDS:
        raise ValueError(f"a cut's tissue is fat or muscle, not {kind!r} (in {name!r})")
    if not np.isfinite(cut.offset_mm):
        raise ValueError(f"a cut's offset is a number of millimetres: {name!r}")
    return cut


def patch_name(groups: list[str]) -> str:
    return PATCH_PREFIX + "+".join(sorted(groups))


def patch_groups(name: str) -> list[str]:
    return name[len(PATCH_PREFIX):].split("+")


def is_group(element_set: str) -> bool:
    return element_set.startswith(GROUP_PREFIX)


def groups_for(mesh, effect_names) -> list[Group]:
    """The groups a model with these effects (fitted and fixed) needs: the regions' when the truth has regions,
    the mesh groups when an effect works on them (heterogeneity, patches, the diagnosis' local probe), else none."""
    names = list(effect_names)
    regions = {n: parse_region(n) for n in names if n.startswith(REGION_PREFIX)}
    cuts = [n for n in names if n.startswith(CUT_PREFIX)]
    grouped = [n for n in names if n in GROUPED_EFFECTS or n.startswith(PATCH_PREFIX)] + cuts
    if len(cuts) > 1:
        raise ValueError(f"one cut per model: {cuts}")
    if regions and grouped:
        raise ValueError(f"region effects {sorted(regions)} cut the tissues differently from {grouped}: use one or the other")
    tissue_sets = tissue_element_sets(mesh)
    if regions:
        return region_groups(mesh, tissue_sets, regions)
    return mesh_groups(mesh, tissue_sets, cuts) if grouped else []


def patch_candidates(groups: list[Group], max_sectors: int = int(PATCH_MAX_DEG // (360.0 / SECTORS))) -> list[tuple[list[int], int, int]]:
    """Places a local stiffness change may take: within one tissue kind (across muscle compartments), 1 to
    max_sectors contiguous sectors and a contiguous run of depth bands. Returns (group indices, first sector,
    number of sectors), each set once."""
    cells: dict[tuple[str, int, int], list[int]] = {}
    for k, g in enumerate(groups):
        if g.sector >= 0:
            cells.setdefault((g.kind, g.sector, g.band), []).append(k)
    found, seen = [], set()
    for kind in dict.fromkeys(g.kind for g in groups if g.sector >= 0):
        bands = 1 if kind == "fat" else MUSCLE_BANDS
        runs = [range(low, high) for low in range(bands) for high in range(low + 1, bands + 1)]
        for start in range(SECTORS):
            for width in range(1, max_sectors + 1):
                for run in runs:
                    members = [k for key in ((kind, (start + w) % SECTORS, b) for w in range(width) for b in run)
                               for k in cells.get(key, [])]
                    if members and frozenset(members) not in seen:
                        seen.add(frozenset(members))
                        found.append((members, start, width))
    return found


def group_elsets_text(groups: list[Group]) -> str:
    """*ELSET definitions of the groups, for the mesh include."""
    lines = []
    for group in groups:
        ids = np.asarray(group.elements) + 1
        lines.append(f"*ELSET, ELSET={group.name}")
        lines += [", ".join(str(v) for v in ids[k:k + 16]) for k in range(0, len(ids), 16)]
    return "\n".join(lines) + "\n"
