"""The second phantom leg, drawn and rendered independently of the first (`orchestrator.phantom.render`):
its own anatomy (`anatomy`), fine structure attached to the material (`structure`: fat septa, intramuscular
fat streaks, texture) and image formation (`scanner`: partial volume by box averaging, coil bias, Rician
noise). It plugs into the same case machinery (`orchestrator.phantom.write_case`,
`orchestrator.run.setup.make_phantom_case`), so that a method can be checked on two renderers."""

from .anatomy import LegGeometry, LegShape
from .scanner import MRIContrast, MRIPhantom

__all__ = ["LegGeometry", "LegShape", "MRIContrast", "MRIPhantom"]
