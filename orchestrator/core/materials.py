"""The strain-energy law of each tissue of the leg, its parameters and its deck material.

The first paper (Avril et al.) gives fat and muscle the compressible neo-Hookean law of its eq. 2, W =
C10 (I1bar - 3) + Kv [(J^2 - 1)/2 - ln J] (`avril`); the second (Bouten and Drapier, sec. 3.2 and Table 1)
gives every tissue a Mooney-Rivlin law of two or three terms, W = C10 (I1bar - 3) + C01 (I2bar - 3) +
C20 (I1bar - 3)^2 + (J - 1)^2 / D1, almost or fully incompressible. `TissueLaw` is one tissue's choice
(case.toml `[model.<tissue>]`, docs/case-folder.md), `LAWS` the laws calfit fits:

| law                  | parameters (kPa)        | engine law (solver_cpp/README.md)                  |
|----------------------|-------------------------|----------------------------------------------------|
| `avril`              | C10, Kv                 | AVRIL (C10, KV[, C20])                             |
| `neo_hooke`          | C10, Kv                 | NEO HOOKE (C10, D1)                                |
| `mooney_rivlin`      | C10, C01, Kv (+ C20)    | MOONEY-RIVLIN (C10, C01, D1); three terms: POLYNOMIAL N=2 with C11 = C02 = 0 |
| `reduced_polynomial` | C10, C20 (+ C30), Kv    | REDUCED POLYNOMIAL N=2, 3 (D2 = D3 = 0)            |

Every law is parametrised by the bulk modulus Kv in kPa, the same for all laws at small strain: Avril's
volumetric term is Kv (J - 1)^2 + O((J - 1)^3) and CalculiX's is (J - 1)^2 / D1, so D1 = 1 / Kv (MPa^-1 when
Kv is in MPa). `incompressible` writes D1 = 0 (no Kv parameter; the elements must then be u/p, CPE6H). The
`stiffening` effect adds C20 to a law without it: avril writes it as its third constant, neo_hooke becomes
the reduced polynomial of order 2, the two-term Mooney-Rivlin the three-term one.

Parameter names are `<constant>_<tissue>` (`C01_muscle`, `Kv_fat`, `C10_compartment4`). C10, C01 and Kv are
positive and move in ln theta; C20 and C30 may be negative (the second paper's fat has C20 = -0.04 kPa) and
move in steps of their `scale` (`forward.ParameterSpace.linear`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

from .errors import MaterialError
from .units import KPA_PER_MPA

LAWS = ("avril", "neo_hooke", "mooney_rivlin", "reduced_polynomial")
CONSTANT_ORDER = ("C10", "C01", "C20", "C30", "Kv")   # parameter order of a model: by constant, then by tissue
LINEAR_CONSTANTS = ("C20", "C30")                       # may be negative: additive steps, not ln theta
TISSUE_SETS = {"fat": "FAT", "muscle": "MUSCLE"}         # tissue name -> element set; compartmentK -> COMPARTMENTK
COMPARTMENT_TISSUE = "compartment"

# Avril et al. Table 2 central values (kPa): the fits' usual start of the first paper's law.
AVRIL_START_KPA = {"fat": {"C10": 4.5, "Kv": 106.0}, "muscle": {"C10": 11.2, "Kv": 69.5}}
# Box of the fits and of the Monte-Carlo draws (kPa) of the first paper's law: around the spread of Avril et al.
# Table 1, widened; a compartment with its own law takes the muscle's.
AVRIL_BOUNDS_KPA = {"fat": {"C10": (1.0, 20.0), "Kv": (30.0, 250.0)}, "muscle": {"C10": (3.0, 30.0), "Kv": (20.0, 200.0)}}
# The other laws: Bouten and Drapier Table 1 has C10 0.9-1.4 kPa and C01 0.4-1.0 kPa, the first paper C10 of
# 1.5-16 kPa; the boxes hold both.
OTHER_BOUNDS_KPA = {"C10": (0.1, 30.0), "C01": (0.05, 30.0), "C20": (-5.0, 50.0), "C30": (-5.0, 50.0)}
HIGHER_ORDER_SCALE_KPA = 0.5   # the optimizers' unit step of C20, C30


@dataclass(frozen=True)
class TissueLaw:
    """One tissue's law (module text): `terms` is 2 or 3 for mooney_rivlin (the third is C20) and the order N (2
    or 3) of reduced_polynomial; `fixed` holds constants not fitted (kPa), `bounds` the box of fitted ones,
    `start` their start (kPa)."""

    law: str = "avril"
    terms: int | None = None
    incompressible: bool = False
    fixed: Mapping[str, float] = field(default_factory=dict)
    bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    start: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        if self.law not in LAWS:
            raise MaterialError(f"unknown law {self.law!r}: calfit fits {', '.join(LAWS)}")
        allowed_terms = (2, 3) if self.law in ("mooney_rivlin", "reduced_polynomial") else ()
        if self.terms is not None and self.terms not in allowed_terms:
            raise MaterialError(f"terms = {self.terms} is not an option of {self.law}: "
                                + ("write 2 or 3" if allowed_terms else "this law has no terms option"))
        if self.incompressible and self.law == "avril":
            raise MaterialError("the avril law's bulk term is a penalty (Avril et al. eq. 2): write law = "
                                "\"neo_hooke\" or \"mooney_rivlin\" for an incompressible tissue")
        constants = set(self.constants)
        for role, names in (("fixed", self.fixed), ("bounds", self.bounds), ("start", self.start)):
            unknown = sorted(set(names) - constants)
            if unknown:
                raise MaterialError(f"{role} names {unknown[0]}, which {self.law}"
                                    f"{' (incompressible)' if self.incompressible else ''} has not: it has "
                                    f"{', '.join(self.constants)}")
        for name, value in self.fixed.items():
            if name not in LINEAR_CONSTANTS and not float(value) > 0.0:
                raise MaterialError(f"the fixed {name} must be positive, got {value}")
        for name, (lower, upper) in self.bounds.items():
            if not (lower < upper and (name in LINEAR_CONSTANTS or lower > 0.0)):
                raise MaterialError(f"bounds of {name} must satisfy {'' if name in LINEAR_CONSTANTS else '0 < '}"
                                    f"lower < upper, got [{lower}, {upper}]")

    @property
    def order(self) -> int:
        """Terms of the law's polynomial in I1bar: 3 for a reduced polynomial N = 3, 2 with C20, else 1."""
        if self.law == "reduced_polynomial":
            return self.terms or 2
        return 2 if self.law == "mooney_rivlin" and self.terms == 3 else 1

    @property
    def constants(self) -> tuple[str, ...]:
        """The law's constants in CONSTANT_ORDER (Kv unless incompressible)."""
        names = ["C10"] + (["C01"] if self.law == "mooney_rivlin" else []) + ["C20", "C30"][:self.order - 1]
        return tuple(names + ([] if self.incompressible else ["Kv"]))

    @property
    def free(self) -> tuple[str, ...]:
        return tuple(name for name in self.constants if name not in self.fixed)

    def has_c20(self) -> bool:
        return "C20" in self.constants


AVRIL = TissueLaw()


def tissue_set(tissue: str) -> str:
    """The element set of a tissue name of case.toml: fat -> FAT, muscle -> MUSCLE, compartment4 -> COMPARTMENT4."""
    if tissue in TISSUE_SETS:
        return TISSUE_SETS[tissue]
    if tissue.startswith(COMPARTMENT_TISSUE) and tissue[len(COMPARTMENT_TISSUE):].isdigit():
        return tissue.upper()
    raise MaterialError(f"unknown tissue {tissue!r}: write fat, muscle or compartment<label> (label >= 4 of "
                        "labels.png)")


def default_start(tissue: str, law: TissueLaw, constant: str) -> float:
    """The start of a fitted constant (kPa) when case.toml gives none: the first paper's Table 2 central values,
    the neo-Hookean shear modulus shared equally by C10 and C01 in a Mooney-Rivlin law, higher orders at 0."""
    if constant in law.start:
        return float(law.start[constant])
    table = AVRIL_START_KPA["fat" if tissue == "fat" else "muscle"]
    if constant in LINEAR_CONSTANTS:
        return 0.0
    if constant == "Kv":
        return table["Kv"]
    return table["C10"] / 2.0 if law.law == "mooney_rivlin" else table["C10"]


def default_bounds(tissue: str, law: TissueLaw, constant: str) -> tuple[float, float]:
    if constant in law.bounds:
        lower, upper = law.bounds[constant]
        return float(lower), float(upper)
    if constant == "Kv" or law.law == "avril":
        return AVRIL_BOUNDS_KPA["fat" if tissue == "fat" else "muscle"][constant]
    return OTHER_BOUNDS_KPA[constant]


def deck_material(law: TissueLaw, constants_MPa: Mapping[str, float], stiffening: bool = False) -> tuple[str, tuple]:
    """(the *HYPERELASTIC option, its data-line constants) of a tissue whose constants (MPa, named as in
    CONSTANT_ORDER; C20 also from the `stiffening` effect) are given. stiffening: C20 is written even at 0
    (a model that fits it keeps one law while C20 passes 0)."""
    c = dict(constants_MPa)
    d1 = 0.0 if law.incompressible else 1.0 / c["Kv"]
    c20 = c.get("C20", 0.0)
    if law.law == "avril":
        return "AVRIL", (c["C10"], c["Kv"], c20) if stiffening else (c["C10"], c["Kv"])
    if law.law == "neo_hooke":
        return ("REDUCED POLYNOMIAL, N=2", (c["C10"], c20, d1, 0.0)) if stiffening else ("NEO HOOKE", (c["C10"], d1))
    if law.law == "mooney_rivlin":
        if law.order == 2 or stiffening:
            return "POLYNOMIAL, N=2", (c["C10"], c["C01"], c20, 0.0, 0.0, d1, 0.0)
        return "MOONEY-RIVLIN", (c["C10"], c["C01"], d1)
    n = law.order
    return f"REDUCED POLYNOMIAL, N={n}", (c["C10"], c20, *([c["C30"]] if n == 3 else []), d1, *([0.0] * (n - 1)))


def engine_constant(law: TissueLaw, constant: str, constants_MPa: Mapping[str, float]) -> tuple[str, float]:
    """(the engine's name of the deck constant a parameter sets, d(deck constant)/d(parameter in kPa)): the
    *SENSITIVITY line's constant and its chain-rule factor. Kv is KV of AVRIL and D1 = 1/Kv of the others."""
    if constant != "Kv":
        return constant, 1.0 / KPA_PER_MPA
    if law.law == "avril":
        return "KV", 1.0 / KPA_PER_MPA
    kv = constants_MPa["Kv"]
    return "D1", -1.0 / (kv * kv * KPA_PER_MPA)


def sum_only_pairs(tissue_laws: dict[str, TissueLaw]) -> list[tuple[str, str]]:
    """The parameter pairs (C10_<tissue>, C01_<tissue>) that act only through their sum: both free in the
    Mooney-Rivlin law of an incompressible tissue (`law_notes`). The displacements cannot separate them, whatever
    the data; a finite-difference Jacobian (friction) or the u/p element's weak J = 1 leave them a small singular
    value that is not information."""
    return [(f"C10_{tissue}", f"C01_{tissue}") for tissue, law in tissue_laws.items()
            if _mooney_rivlin_pair_free(law) and law.incompressible]


def _mooney_rivlin_pair_free(law: TissueLaw) -> bool:
    """A Mooney-Rivlin law whose C10 and C01 are both fitted."""
    return law.law == "mooney_rivlin" and {"C10", "C01"} <= set(law.free)


def law_notes(tissue: str, law: TissueLaw) -> list[str]:
    """What the displacements of a slice cannot tell of a tissue's law, said before the fit (the setup lines). In
    plane strain (lambda_3 = 1) an incompressible tissue has I2 = lambda1^2 lambda2^2 + lambda1^2 + lambda2^2 =
    1 + lambda1^2 + lambda2^2 = I1, so C10 and C01 act only through their sum (and nearly so when D1 is small)."""
    if not _mooney_rivlin_pair_free(law):
        return []
    how = "only" if law.incompressible else "almost only"
    return [f"{tissue}: in plane strain an {'' if law.incompressible else 'almost '}incompressible tissue has "
            f"I1bar = I2bar, so C10_{tissue} and C01_{tissue} act {how} through their sum: their intervals will "
            f"say so; fix one of them ([model.{tissue}] fixed) to identify the other"]


ELEMENTS = {"CPE3": 1, "CPE6": 2, "CPE6H": 2}   # element -> order of the mesh


GARMENTS = ("laplace", "explicit")
