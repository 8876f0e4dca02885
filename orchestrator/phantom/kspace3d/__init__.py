"""The third phantom: a 3D calf whose truth is solved in 3D by CalculiX and imaged as an MR scanner images it.

The first two phantoms draw a 2D slice and deform it by a plane-strain field. A scanner does not draw pixels: it
acquires a band-limited part of k-space through a slice some millimetres thick of a 3D leg, with the fat displaced
along the readout by the chemical shift and a coil profile fixed to the scanner, and the leg may tilt or slide
along its axis between the sessions (docs/design.md, "Images that calfit did not make"). This package makes such images
independently of any other program's renderer:

- `leg3d`: the second phantom's section (`mri.LegGeometry`) carried along the leg by an invertible map (taper,
  twist, drift, the fat's change with height); exact labels and landmarks at any height;
- `appearance3d`: water and fat signals, every feature a function of the 3D material point (septa as sheets,
  intramuscular fat streaks elongated along the leg, vessels along it), on `noise3d`'s lattice gradient noise;
- `mechanics3d`: the truth, the leg segment meshed with C3D15 wedges and solved by CalculiX (`ccx`), with its
  3D interpolation and its check against calfit's plane-strain engine;
- `acquisition`: the slice profile, the coil, the chemical shift, the acquired matrix, the vendor filter, the
  noise and the magnitude; the leg's rigid motion between sessions;
- `case`: case folders (one slice, or a volume of DICOM series) with their truth kept apart.
"""

from .acquisition import AcquiredImage, DisplacementGrid, LegMotion, Scanner
from .appearance3d import Appearance3D, KspaceContrast
from .case import (
                          KspacePhantom,
                          build_phantom,
                          make_kspace_case,
                          solve_truth,
                          write_kspace_volume_case,
)
from .ccx import CcxError
from .leg3d import Leg3D, LegAlongHeight
from .mechanics3d import (
                          GarmentLoad,
                          HiddenEffects3D,
                          Layering,
                          LegMesh3D,
                          LegSolution3D,
                          leg_mesh_3d,
                          plane_strain_difference,
                          section_mesh,
                          solve_leg3d,
)

__all__ = ["AcquiredImage", "Appearance3D", "CcxError", "DisplacementGrid", "GarmentLoad", "HiddenEffects3D",
           "KspaceContrast", "KspacePhantom", "Layering", "Leg3D", "LegAlongHeight", "LegMesh3D", "LegMotion",
           "LegSolution3D", "Scanner", "build_phantom", "leg_mesh_3d", "make_kspace_case", "plane_strain_difference",
           "section_mesh", "solve_leg3d", "solve_truth", "write_kspace_volume_case"]
