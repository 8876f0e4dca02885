"""The identified model of a run, written for ParaView.

`write_paraview(RUN_DIR)` solves the run's model (its mesh and garment tension, the effects of
identification.json) once at the identified parameters (identification.json `best.theta`) and writes into
RUN_DIR/paraview (or the folder given):

    model-step-N.vtu   the state at the end of load step N of the model's deck (N = 1, 2, ...)
    model.pvd          ParaView Data collection of the step files, timestep = the step number N
    model.vtu          the final state (the last step), for a quick look without the time series

Each VTU is the reference (undeformed) mesh of the run: points in mm in the image frame of the unloaded
image I0 (x along the columns, y down the rows, z = 0), cells the engine's triangles (VTK_TRIANGLE for
CPE3, VTK_QUADRATIC_TRIANGLE for CPE6, node order as in the deck). Filters > Warp By Vector on
`displacement_mm` shows the deformed leg. ParaView's default view has y up, so the slice appears upside
down compared with the image: "Set view direction to +Z" and rotate the view by 180 degrees to see it as the
image. Units are mm and kPa (the engine computes in N, mm, MPa; stresses are converted here).

Point data (values at the mesh nodes; stresses are the engine's nodal averages of the element values):
    displacement_mm             (3 comp.) u_x, u_y, u_z in mm (u_z = 0: plane strain)
    cauchy_stress_kPa           (6 comp.) Cauchy stress xx, yy, zz, xy, yz, xz in kPa (VTK's symmetric tensor order)
    hydrostatic_pressure_kPa    -tr(sigma)/3 in kPa, from cauchy_stress_kPa (positive in compression)
    hydrostatic_pressure_mmHg   the same in mmHg (1 kPa = 7.50062 mmHg)
  with the explicit garment ([model] garment = "explicit"), the band's nodes follow the leg's, in the band's
  natural shape (Warp By Vector puts it on the leg), and
    contact_pressure_kPa        the skin/band contact pressure, kPa (on the skin and the band's inner surface)
    contact_shear_kPa           the friction shear, kPa
    contact_status              on the skin: 0 open (the band bridges or is off), 1 sticking, 2 slipping
                                (Abaqus's CSTATUS; frictionless contact slips)
    contact_slip_mm             on the skin: its tangential motion over the band since the first touch, mm
                                (with friction; 0 without)

Cell data (one value per element):
    tissue                      integer tissue label of the element: 1 fat, 2 muscle, k >= 4 muscle
                                compartment k (the mesh's element regions; 3 is bone, never meshed), 0 the
                                explicit garment's band
    cauchy_stress_kPa           (6 comp.) element average of the Cauchy stress, kPa, order as above
    hydrostatic_pressure_kPa    -tr(sigma)/3 of the element average, kPa
    hydrostatic_pressure_mmHg   the same in mmHg
    J                           volume ratio det F of the element (lambda_z det F2; 1 = no volume change)

Field data (one value each; VTK field data holds numbers, so names carry what a string would):
    <parameter name>            one array per identified parameter, named as in identification.json
                                (C10_fat, C10_muscle, Kv_fat, Kv_muscle in kPa, then the effects' parameters
                                in their own units, `unit_of` in identification.json); value = best.theta
    tissue_label_<NAME>         the label number of each tissue present, e.g. tissue_label_FAT = 1,
                                tissue_label_MUSCLE = 2, tissue_label_COMPARTMENT4 = 4
An XML comment at the top of each VTU repeats the parameters with their units for a reader of the text.

meshio (5.3) reads FieldData from a VTU but its writer leaves it out, so the VTU is written by meshio and
the FieldData element, in the form VTK's own writer uses (a child of <UnstructuredGrid>, ASCII DataArrays
with NumberOfTuples), is added with the standard library's XML. Every file is written to a hidden temporary
name in the output folder and renamed into place, model.pvd last, so a reader never sees half a file nor a
collection naming a missing step; only the files named above are replaced (and step files of an earlier
export with more steps removed), so --out may point into a folder that holds other files.
"""

from __future__ import annotations

import re
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np

from ..core.errors import RunFolderError
from ..core.files import read_json
from ..core.run_lock import holds_run_folder
from ..core.tissues import element_set_of_label
from ..core.units import KPA_PER_MPA, MMHG_PER_KPA
from ..engine.results import EngineResults
from ..run.setup import load_run

OUTPUT_FOLDER = "paraview"
COLLECTION_NAME = "model.pvd"
FINAL_NAME = "model.vtu"
STEP_NAME = "model-step-{}.vtu"
STEP_PATTERN = re.compile(r"model-step-(\d+)\.vtu")
TISSUE_LABEL_PREFIX = "tissue_label_"
VTK_CELL_TYPES = {3: "triangle", 6: "triangle6"}   # meshio names of VTK_TRIANGLE and VTK_QUADRATIC_TRIANGLE
GARMENT_LABEL = 0   # the "tissue" of the explicit garment's band cells


@holds_run_folder()
def write_paraview(run_dir: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Solve the run's identified model at best.theta and write the step VTUs, model.vtu and model.pvd into
    out_dir (default RUN_DIR/paraview); returns the written paths (steps, final state, collection)."""
    run_dir = Path(run_dir)
    # identification.json first: a run folder that is only prepared should hear that identify is missing
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    setup = load_run(run_dir)
    model = setup.model_with(identification.get("effects", ()))
    names, theta = list(identification["parameters"]), [float(v) for v in identification["best"]["theta"]]
    if names != list(model.space.names) or len(theta) != len(names):
        raise RunFolderError(f"{run_dir / 'identification.json'} lists the parameters {names} but the model of its "
                             f"effects has {list(model.space.names)}: run `calfit identify` again")
    units = list(identification.get("unit_of") or model.space.unit_of)
    field_data = {name: np.array([value]) for name, value in zip(names, theta)}
    for region in np.unique(setup.mesh.element_regions):
        field_data[TISSUE_LABEL_PREFIX + element_set_of_label(int(region))] = np.array([int(region)], np.int32)
    if model.band is not None:
        field_data[TISSUE_LABEL_PREFIX + "GARMENT"] = np.array([GARMENT_LABEL], np.int32)
    comment = ("calfit identified model of " + str(run_dir.resolve()) + "; units mm, kPa; parameters: "
               + ", ".join(f"{n} = {v!r} {u or '(no unit)'}" for n, v, u in zip(names, theta, units))
               + "; tissue labels: 1 fat, 2 muscle, >= 4 muscle compartment k")

    with tempfile.TemporaryDirectory(prefix="calfit-paraview-") as scratch:
        try:
            results = setup.solve(theta, Path(scratch), model)
            grids = {int(step["step"]): _step_grid(setup.mesh, results, int(step["step"]), model.band)
                     for step in results.summary["steps"]}
        except RuntimeError as error:   # the engine's errors (not found, failed, not converged) are RuntimeErrors
            reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise RuntimeError(f"the engine could not solve the identified model of {run_dir} at best.theta "
                               f"({reason})") from error

    out_dir = Path(out_dir) if out_dir is not None else run_dir / OUTPUT_FOLDER
    out_dir.mkdir(parents=True, exist_ok=True)
    final_step = max(grids)
    contents = {STEP_NAME.format(step): grid for step, grid in sorted(grids.items())}
    contents[FINAL_NAME] = grids[final_step]
    staged: list[tuple[Path, Path]] = []   # (temporary, final), registered before writing so a failure cleans up
    try:
        for name, grid in contents.items():
            staged.append((out_dir / f".{name}.tmp", out_dir / name))
            _write_vtu(staged[-1][0], grid, field_data, comment)
        staged.append((out_dir / f".{COLLECTION_NAME}.tmp", out_dir / COLLECTION_NAME))
        staged[-1][0].write_text(_collection_xml([(step, STEP_NAME.format(step)) for step in sorted(grids)]),
                                 encoding="utf-8")
    except BaseException:
        for temporary, _ in staged:
            temporary.unlink(missing_ok=True)
        raise
    for temporary, final in staged:   # model.pvd last: it never lists a step file not yet in place
        temporary.replace(final)
    for stale in out_dir.iterdir():
        match = STEP_PATTERN.fullmatch(stale.name)
        if match and int(match.group(1)) not in grids:
            stale.unlink(missing_ok=True)
    return [final for _, final in staged]


def _step_grid(mesh, results: EngineResults, step: int, band=None) -> meshio.Mesh:
    """The run's reference mesh (and the explicit garment's band in its natural shape, after the leg, as in the
    deck) with the engine's fields of one step, in mm and kPa (see the module text)."""
    engine = results.mesh(step)
    nodes, elements = np.asarray(mesh.nodes), np.asarray(mesh.elements)
    regions = np.asarray(mesh.element_regions, np.int32)
    if band is not None:
        elements = np.vstack([elements, np.asarray(band.elements) + len(nodes)])
        nodes = np.vstack([nodes, band.nodes])
        regions = np.concatenate([regions, np.full(len(band.elements), GARMENT_LABEL, np.int32)])
    engine_cells = [block.data for block in engine.cells]
    if len(engine.points) != len(nodes) or sum(len(c) for c in engine_cells) != len(elements):
        raise RuntimeError(f"the engine's step {step} has {len(engine.points)} nodes and "
                           f"{sum(len(c) for c in engine_cells)} elements, the run's mesh {len(nodes)} and "
                           f"{len(elements)}")
    stress_kPa = np.asarray(engine.point_data["cauchy_stress"], float) * KPA_PER_MPA
    cell_stress_kPa = np.asarray(engine.cell_data["cauchy_stress"][0], float) * KPA_PER_MPA
    pressure_kPa, cell_pressure_kPa = _hydrostatic(stress_kPa), _hydrostatic(cell_stress_kPa)
    # points from the run's mesh, not from the engine's VTU: the deck carries 10 significant digits, and
    # the export should overlay the mesh that setup.npz, the report and the image frame use
    points = np.column_stack([nodes, np.zeros(len(nodes))])
    point_data = {"displacement_mm": np.asarray(engine.point_data["displacement"], float),
                  "cauchy_stress_kPa": stress_kPa,
                  "hydrostatic_pressure_kPa": pressure_kPa,
                  "hydrostatic_pressure_mmHg": pressure_kPa * MMHG_PER_KPA}
    if band is not None:
        point_data.update({"contact_pressure_kPa": _point(engine, "contact_pressure") * KPA_PER_MPA,
                           "contact_shear_kPa": _point(engine, "contact_shear") * KPA_PER_MPA,
                           "contact_status": _point(engine, "contact_status"),
                           "contact_slip_mm": _point(engine, "contact_slip")})
    return meshio.Mesh(
        points, [(VTK_CELL_TYPES[elements.shape[1]], elements)],
        point_data=point_data,
        cell_data={"tissue": [regions],
                   "cauchy_stress_kPa": [cell_stress_kPa],
                   "hydrostatic_pressure_kPa": [cell_pressure_kPa],
                   "hydrostatic_pressure_mmHg": [cell_pressure_kPa * MMHG_PER_KPA],
                   "J": [np.asarray(engine.cell_data["J"][0], float).reshape(-1)]},
    )


def _point(engine: meshio.Mesh, name: str) -> np.ndarray:
    return np.asarray(engine.point_data[name], float).reshape(-1)


def _hydrostatic(stress: np.ndarray) -> np.ndarray:
    """-tr(sigma)/3 of (n, 6) stresses ordered xx, yy, zz, xy, yz, xz."""
    return -(stress[:, 0] + stress[:, 1] + stress[:, 2]) / 3.0


def _write_vtu(path: Path, grid: meshio.Mesh, field_data: dict[str, np.ndarray], comment: str) -> None:
    """Write grid as a VTU at path with field_data added (meshio's writer drops field data)."""
    meshio.write(path, grid, file_format="vtu")
    tree = ET.parse(path)
    root = tree.getroot()
    unstructured = root.find("UnstructuredGrid")
    fields = ET.Element("FieldData")
    for name, values in field_data.items():
        integer = np.issubdtype(values.dtype, np.integer)
        array = ET.SubElement(fields, "DataArray", type="Int32" if integer else "Float64", Name=name,
                              NumberOfTuples=str(len(values)), format="ascii")
        # repr gives the shortest text that reads back as the same double: the values survive exactly
        array.text = " ".join(str(int(v)) if integer else repr(float(v)) for v in values)
    unstructured.insert(0, fields)
    root.insert(0, ET.Comment(" " + comment.replace("--", "- -") + " "))
    tree.write(path, encoding="utf-8", xml_declaration=True)


def _collection_xml(steps: list[tuple[int, str]]) -> str:
    """A ParaView Data (.pvd) collection of the step files, the step number as timestep."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ET.SubElement(root, "Collection")
    for step, name in steps:
        ET.SubElement(collection, "DataSet", timestep=str(step), group="", part="0", file=name)
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
