"""The compression classes of the hosiery standards and the graduation they ask along the leg.

The class of a stocking is its pressure on the skin at B, the ankle's narrowest girth, at rest (supine); the
standards differ in their ranges and in the device they measure with, not in the place. The ranges below, in mmHg
at B:

- RAL-GZ 387/1 (Germany; RAL Deutsches Institut fuer Guetesicherung und Kennzeichnung, "Medizinische
  Kompressionsstruempfe, Guetesicherung RAL-GZ 387/1", January 2008, Abb. 1, as the Guetezeichengemeinschaft
  Medizinische Kompressionsstruempfe e.V. publishes it): I 18-21, II 23-32, III 34-46, IV 49 and more. The same
  document asks a continuous fall of the pressure from the ankle upwards (the "Druckgradient"), and its measuring
  points are B (ankle), B1 (where the Achilles tendon becomes the calf muscle), C (the calf's widest girth), D (below
  the knee); below the knee the pressure is at most 70 % of B's (the RAL measuring points as eurocom e.V., the
  manufacturers' association, summarises them).
- The French classes (ASQUAL's certification of medical compression hosiery, after AFNOR NF G30-102 B, 1986):
  I 10-15, II 15-20, III 20-36, IV above 36.
- The British classes (BS 6612:1985, "Specification for graduated compression hosiery", and the UK Drug Tariff's
  specification 40 that follows it): I 14-17, II 18-24, III 25-35.

The three standards measure with different devices (HOSY, the French IFTH tester, the HATRA tester), so one
stocking may fall in classes of different numbers: the names below keep the standard's name with the class. The
French and British ranges are quoted from the secondary sources that tabulate them beside RAL's (manufacturers'
and the UK hosiery suppliers' tables); check a clinical design against the standard's own text.
"""

from __future__ import annotations

from dataclasses import dataclass

HEIGHTS = ("B", "B1", "C", "D")        # distal to proximal
BELOW_KNEE_SHARE_MAX = 0.70            # RAL-GZ 387/1: at D at most 70 % of the pressure at B


@dataclass(frozen=True)
class CompressionClass:
    standard: str
    name: str
    min_mmHg: float
    max_mmHg: float | None      # None: open above
    source: str

    @property
    def label(self) -> str:
        high = f"{self.max_mmHg:g}" if self.max_mmHg is not None else "and more"
        return f"{self.standard} {self.name} ({self.min_mmHg:g}-{high} mmHg at B)" if self.max_mmHg is not None \
            else f"{self.standard} {self.name} ({self.min_mmHg:g} mmHg {high} at B)"


_RAL = "RAL-GZ 387/1:2008, Abb. 1"
_FR = "ASQUAL / AFNOR NF G30-102 B (1986)"
_BS = "BS 6612:1985 (UK Drug Tariff specification 40)"
CLASSES = {
    f"{standard} {name}": CompressionClass(standard, name, low, high, source)
    for standard, source, table in (
        ("RAL", _RAL, (("I", 18.0, 21.0), ("II", 23.0, 32.0), ("III", 34.0, 46.0), ("IV", 49.0, None))),
        ("FR", _FR, (("I", 10.0, 15.0), ("II", 15.0, 20.0), ("III", 20.0, 36.0), ("IV", 36.0, None))),
        ("BS", _BS, (("I", 14.0, 17.0), ("II", 18.0, 24.0), ("III", 25.0, 35.0))),
    )
    for name, low, high in table
}
ALIASES = {"FRENCH": "FR", "AFNOR": "FR", "ASQUAL": "FR", "BRITISH": "BS", "UK": "BS", "BS6612": "BS",
           "RAL-GZ": "RAL", "RAL-GZ 387": "RAL", "RALGZ387": "RAL", "1": "I", "2": "II", "3": "III", "4": "IV"}


def compression_class(text: str) -> CompressionClass:
    """The class named "RAL II", "FR 2", "BS III", "British II", ...; KeyError naming the classes known."""
    parts = text.strip().upper().replace("CLASS", " ").split()
    if len(parts) >= 2:
        standard = ALIASES.get(" ".join(parts[:-1]), " ".join(parts[:-1]))
        name = ALIASES.get(parts[-1], parts[-1])
        found = CLASSES.get(f"{standard} {name}")
        if found is not None:
            return found
    raise KeyError(f"{text!r} is not a class calfit knows; give one of {', '.join(CLASSES)}")


def graduation_caps() -> dict[str, tuple[str, float]]:
    """height -> (the height below it, the largest share of that height's pressure allowed): the steady fall of
    RAL-GZ 387/1 from B upwards, and D at most 70 % of B."""
    return {"B1": ("B", 1.0), "C": ("B1", 1.0), "D": ("C", 1.0)}
