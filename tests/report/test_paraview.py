"""`calfit paraview`: the identified model written for ParaView is the run's mesh with the engine's fields at
best.theta in mm and kPa, the pressures agree with the stress, the tissue labels with the mesh, the field data
with identification.json, and model.pvd lists step files that exist. A folder with no identification is refused
in one sentence naming `calfit identify`."""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest
from conftest import copy_run

from orchestrator.cli import main
from orchestrator.core.units import KPA_PER_MPA, MMHG_PER_KPA
from orchestrator.run.setup import load_run


@pytest.fixture(scope="module")
def identified_run(drainage_identified, tmp_path_factory):
    return copy_run(drainage_identified, tmp_path_factory.mktemp("paraview") / "run")


@pytest.fixture(scope="module")
def exported(identified_run):
    """The run, its identification and setup, and an independent solve of its model at best.theta."""
    run_dir = identified_run
    identification = json.loads((run_dir / "identification.json").read_text())
    setup = load_run(run_dir)
    model = setup.model_with(identification["effects"])
    engine = setup.solve(identification["best"]["theta"], run_dir.parent / "independent", model)
    return run_dir, identification, setup, engine


def run_cli(argv, capsys) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_vtus_hold_the_engine_fields_of_the_identified_model(exported, capsys):
    run_dir, identification, setup, engine = exported
    code, out, err = run_cli(["paraview", str(run_dir)], capsys)
    assert code == 0, err
    folder = run_dir / "paraview"
    printed = [Path(line) for line in out.splitlines()]
    assert printed == [folder / "model-step-1.vtu", folder / "model.vtu", folder / "model.pvd"]
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")]   # no temporary left behind

    n_steps = engine.n_steps
    for step, name in [(s, f"model-step-{s}.vtu") for s in range(1, n_steps + 1)] + [(n_steps, "model.vtu")]:
        grid = meshio.read(folder / name)
        reference = engine.mesh(step)

        # the run's mesh: its nodes in mm with z = 0, its quadratic triangles in deck order
        assert len(grid.points) == len(setup.mesh.nodes)
        np.testing.assert_array_equal(grid.points[:, :2], setup.mesh.nodes)
        np.testing.assert_array_equal(grid.points[:, 2], 0.0)
        assert [block.type for block in grid.cells] == ["triangle6"]
        np.testing.assert_array_equal(grid.cells[0].data, setup.mesh.elements)

        # the engine's displacement at best.theta (an independent solve), stresses converted from MPa to kPa
        displacement = grid.point_data["displacement_mm"]
        assert displacement.shape == (len(setup.mesh.nodes), 3)
        np.testing.assert_allclose(displacement, reference.point_data["displacement"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(displacement[:, :2], engine.displacement(step), rtol=0, atol=1e-12)
        stress = grid.point_data["cauchy_stress_kPa"]
        assert stress.shape == (len(setup.mesh.nodes), 6)
        np.testing.assert_allclose(stress, reference.point_data["cauchy_stress"] * KPA_PER_MPA, rtol=1e-12, atol=1e-12)

        # hydrostatic pressure = -tr(sigma)/3 of the written stress, in mmHg by the usual factor, and the engine's own
        # `pressure` (MPa) in kPa: a garment of ~20 mmHg gives kPa pressures, not thousands
        cells = {name: values[0] for name, values in grid.cell_data.items()}
        for data in (grid.point_data, cells):
            pressure, mmhg = np.ravel(data["hydrostatic_pressure_kPa"]), np.ravel(data["hydrostatic_pressure_mmHg"])
            np.testing.assert_allclose(pressure, -data["cauchy_stress_kPa"][:, :3].sum(axis=1) / 3.0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(mmhg, pressure * MMHG_PER_KPA, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.ravel(grid.point_data["hydrostatic_pressure_kPa"]),
                                   np.ravel(reference.point_data["pressure"]) * KPA_PER_MPA, rtol=0, atol=1e-9)
        assert 0.5 < np.abs(grid.point_data["hydrostatic_pressure_kPa"]).max() < 50.0

        # cell data: the mesh's element regions as tissue labels, element stresses in kPa, J as the engine's
        np.testing.assert_array_equal(np.ravel(cells["tissue"]), setup.mesh.element_regions)
        assert np.issubdtype(cells["tissue"].dtype, np.integer)
        np.testing.assert_allclose(cells["cauchy_stress_kPa"], reference.cell_data["cauchy_stress"][0] * KPA_PER_MPA,
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.ravel(cells["J"]), np.ravel(reference.cell_data["J"][0]), rtol=0, atol=1e-12)

        # field data: the identified parameters exactly, then the label number of each tissue present
        fields = {name: np.ravel(values) for name, values in grid.field_data.items()}
        for name, value in zip(identification["parameters"], identification["best"]["theta"]):
            assert fields.pop(name).tolist() == [value]
        labels = {int(region) for region in np.unique(setup.mesh.element_regions)}
        names = {1: "FAT", 2: "MUSCLE", **{k: f"COMPARTMENT{k}" for k in labels if k >= 4}}
        assert fields == {f"tissue_label_{names[k]}": np.array([k]) for k in labels}


def test_collection_lists_every_step_with_increasing_timesteps(exported, capsys):
    run_dir, _, _, engine = exported
    out_dir = run_dir.parent / "elsewhere"
    out_dir.mkdir()
    (out_dir / "notes.txt").write_text("the user's own file")
    (out_dir / "model-step-9.vtu").write_text("a step of an earlier export with more steps")
    code, out, err = run_cli(["paraview", str(run_dir), "--out", str(out_dir)], capsys)
    assert code == 0, err

    root = ET.parse(out_dir / "model.pvd").getroot()
    assert root.get("type") == "Collection"
    datasets = root.find("Collection").findall("DataSet")
    assert [d.get("file") for d in datasets] == [f"model-step-{k}.vtu" for k in range(1, engine.n_steps + 1)]
    timesteps = [float(d.get("timestep")) for d in datasets]
    assert timesteps == sorted(set(timesteps))
    assert all((out_dir / d.get("file")).is_file() for d in datasets)
    # only this export's files are replaced: the user's file stays, the stale step file goes
    assert (out_dir / "notes.txt").read_text() == "the user's own file"
    assert not (out_dir / "model-step-9.vtu").exists()
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(
        ["notes.txt", "model.pvd", "model.vtu"] + [d.get("file") for d in datasets])


def test_run_folder_without_identification_exits_2_naming_identify(identified_run, tmp_path, capsys):
    prepared = tmp_path / "prepared"
    prepared.mkdir()
    for name in ("setup.json", "setup.npz"):   # prepared (as by `calfit measure`), never identified
        shutil.copy(identified_run / name, prepared / name)
    code, out, err = run_cli(["paraview", str(prepared)], capsys)
    assert code == 2 and out == ""
    assert "calfit identify" in err and len(err.strip().splitlines()) == 1
    assert not (prepared / "paraview").exists()

    code, _, err = run_cli(["paraview", str(tmp_path / "missing")], capsys)
    assert code == 2 and "calfit identify" in err
    assert not (tmp_path / "missing").exists()
