"""Write the identified model for ParaView: the run's mesh with displacement, stress and pressure.

    calfit paraview RUN_DIR [--out DIR]

Solves the model of identification.json (best parameters, effects) once and writes into DIR (default
RUN_DIR/paraview): model-step-N.vtu per load step, model.pvd (the steps as a time series, timestep = step
number) and model.vtu (the final state). Prints the written paths. Example:

    calfit identify CASE_DIR --out RUN_DIR
    calfit paraview RUN_DIR
    paraview RUN_DIR/paraview/model.pvd

In ParaView, Filters > Warp By Vector on displacement_mm shows the deformed leg; colour by
hydrostatic_pressure_mmHg. The mesh is the reference one in the image frame of I0 (mm, y down the rows):
"Set view direction to +Z" and rotate the view by 180 degrees to see it as the image.

Arrays (units mm, kPa):
  point data  displacement_mm (3 comp.), cauchy_stress_kPa (6 comp. xx yy zz xy yz xz),
              hydrostatic_pressure_kPa (-tr(sigma)/3), hydrostatic_pressure_mmHg
  cell data   tissue (1 fat, 2 muscle, k >= 4 muscle compartment k), cauchy_stress_kPa,
              hydrostatic_pressure_kPa, hydrostatic_pressure_mmHg, J (volume ratio)
  field data  one array per identified parameter (e.g. C10_muscle in kPa), and
              tissue_label_<NAME> = label number of each tissue (e.g. tissue_label_FAT = 1)
"""

from __future__ import annotations

import argparse

from ..report.paraview import write_paraview
from ._common import add_output_arguments, fail, folder, honours_quiet

HELP = "write the identified model (displacement, stress, pressure) as VTU/PVD files for ParaView"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder of `calfit identify`")
    parser.add_argument("--out", type=folder, metavar="DIR", help="output folder (default: RUN_DIR/paraview)")
    add_output_arguments(parser, json_help=None)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        paths = write_paraview(args.run_dir, args.out)
    except (ValueError, RuntimeError, OSError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    print("\n".join(str(path) for path in paths))
    return 0
