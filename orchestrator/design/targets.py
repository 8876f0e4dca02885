"""TARGET.toml: what the designed garment must give, read and checked before any engine run.

    [design]
    tension_range_N_per_mm = [0.05, 0.6]   # the fabric's feasible tension per height (N/mm)
    harmonics = 0                          # 0: the same tension all round; 1 or 2: a knitted-in profile
    profile_max = 0.3                      # the largest |a_k|, |b_k| of that profile (T(t) = T (1 + sum ...))
    probability = 0.9                      # each min/max target met with at least this probability
    slice_height = "B"                     # a run folder: the height its slice is at (a study knows its own)
    graduated = true                       # the standard's fall from B to D (default: with a class target)

    [[target]]                             # one table per target
    landmark = "deep_veins"                # or height = "B", or region = "tibial_crest" | "anywhere" | a quarter
    min_mmHg = 15                          # min_, max_, value_ in mmHg or kPa; tolerance_mmHg for a value
    height = "C"                           # a study: the slice nearest that named height (default every slice)
    [[target]]
    height = "B"
    class = "RAL II"                       # a class of `standards` (RAL, FR, BS)

    [fabric]                               # optional: the fabric's tensile test
    stretch = [1.0, 1.2, 1.4, 1.6]          # circumference on the leg over the knitted one
    tension_N_per_mm = [0.0, 0.08, 0.17, 0.28]

The tables are pydantic models as case.toml's are (`case.schema`): strict, extra keys refused, each mistake one
`CaseError` naming TARGET.toml, the table, the key and the fix. Targets that no pressure field could meet together
are refused the same way: two bounds on one quantity that leave no value between them, a height's minimum above
the maximum allowed anywhere on the skin, and, with the graduation, a proximal height's minimum above a distal
height's maximum.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tomllib
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..core.errors import CaseError
from ..core.units import MMHG_PER_KPA
from .standards import HEIGHTS, compression_class

Finite = Annotated[float, Field(allow_inf_nan=False)]
Pressure = Annotated[float, Field(ge=0.0, le=300.0, allow_inf_nan=False)]
REGIONS = ("anywhere", "tibial_crest", "anterior", "lateral", "posterior", "medial")
FILE = "TARGET.toml"


class _Table(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", frozen=True, populate_by_name=True)


class DesignTable(_Table):
    tension_range_N_per_mm: Annotated[list[Annotated[float, Field(gt=0.0, le=2.0, allow_inf_nan=False)]],
                                      Field(min_length=2, max_length=2)] = [0.02, 1.0]
    harmonics: Annotated[int, Field(ge=0, le=2)] = 0
    profile_max: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.3
    probability: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.9
    tension_rel_uncertainty: Annotated[float, Field(ge=0.0, lt=1.0)] | None = None
    slice_height: Literal["B", "B1", "C", "D"] | None = None
    graduated: bool | None = None
    draws: Annotated[int, Field(ge=2, le=1000)] | None = None

    @model_validator(mode="after")
    def _range(self):
        low, high = self.tension_range_N_per_mm
        if not low < high:
            raise ValueError(f"tension_range_N_per_mm = [{low:g}, {high:g}] is not a range: give [lowest, highest] "
                             "with lowest < highest")
        return self


class TargetTable(_Table):
    name: str | None = None
    landmark: str | None = None
    height: Literal["B", "B1", "C", "D"] | None = None
    region: Literal[REGIONS] | None = None
    class_: str | None = Field(None, alias="class")
    min_mmHg: Pressure | None = None
    max_mmHg: Pressure | None = None
    value_mmHg: Pressure | None = None
    min_kPa: Pressure | None = None
    max_kPa: Pressure | None = None
    value_kPa: Pressure | None = None
    tolerance_mmHg: Annotated[float, Field(gt=0.0, le=50.0)] = 1.0


class FabricTable(_Table):
    stretch: Annotated[list[Annotated[float, Field(ge=1.0, le=5.0)]], Field(min_length=2)]
    tension_N_per_mm: Annotated[list[Annotated[float, Field(ge=0.0, le=2.0)]], Field(min_length=2)]

    @model_validator(mode="after")
    def _table(self):
        if len(self.stretch) != len(self.tension_N_per_mm):
            raise ValueError("stretch and tension_N_per_mm have different lengths: give one tension per stretch")
        if any(b <= a for a, b in zip(self.stretch, self.stretch[1:])) or \
                any(b <= a for a, b in zip(self.tension_N_per_mm, self.tension_N_per_mm[1:])):
            raise ValueError("stretch and tension_N_per_mm must both increase: list the tensile test in order of "
                             "stretch, a tension rising with it")
        return self


class TargetToml(_Table):
    design: DesignTable = DesignTable()
    target: Annotated[list[TargetTable], Field(min_length=1)]
    fabric: FabricTable | None = None


@dataclass(frozen=True)
class Target:
    """One target on one quantity: kind "landmark" (the hydrostatic pressure there, FE), "skin" (the garment's mean
    pressure on the skin at a height) or "region" (the largest skin pressure over a region); where: the landmark,
    the region; height: a named height or None (every slice; a run folder: its slice); bounds in mmHg, None open;
    aim: a value target's value (the design aims at it), else None."""

    index: int          # the [[target]] table's number, from 1
    name: str
    kind: str
    where: str | None
    height: str | None
    min_mmHg: float | None
    max_mmHg: float | None
    aim_mmHg: float | None = None
    source: str | None = None   # the standard a class comes from

    @property
    def quantity(self) -> tuple:
        return self.kind, self.where, self.height

    def met(self, value_mmHg):
        import numpy as np

        value = np.asarray(value_mmHg, float)
        ok = np.ones(value.shape, bool)
        if self.min_mmHg is not None:
            ok &= value >= self.min_mmHg
        if self.max_mmHg is not None:
            ok &= value <= self.max_mmHg
        return ok

    @property
    def bounds_text(self) -> str:
        if self.aim_mmHg is not None and self.min_mmHg is not None and self.max_mmHg is not None \
                and self.source is None:
            return f"= {self.aim_mmHg:g} ± {self.max_mmHg - self.aim_mmHg:g} mmHg"
        if self.min_mmHg is not None and self.max_mmHg is not None:
            return f"{self.min_mmHg:g}-{self.max_mmHg:g} mmHg"
        return f">= {self.min_mmHg:g} mmHg" if self.min_mmHg is not None else f"<= {self.max_mmHg:g} mmHg"


@dataclass(frozen=True)
class Targets:
    path: Path
    design: DesignTable
    targets: tuple[Target, ...]
    fabric: FabricTable | None
    graduated: bool

    @property
    def heights(self) -> set[str]:
        return {t.height for t in self.targets if t.height is not None}


def read_targets(path: str | Path) -> Targets:
    """TARGET.toml validated (module text); CaseError at the first mistake or contradiction."""
    path = Path(path)
    if not path.is_file():
        raise CaseError(path, "does not exist", f"give the path of a {FILE} (docs/design-garment.md shows one)")
    try:
        settings = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise CaseError(path, f"is not TOML ({error})", "write it as docs/design-garment.md shows") from None
    except UnicodeDecodeError:
        raise CaseError(path, "is not a text file", f"give the {FILE} text file") from None
    try:
        table = TargetToml.model_validate(settings)
    except ValidationError as error:
        raise _refusal(path, error.errors()[0]) from None
    targets = tuple(_target(path, k, entry) for k, entry in enumerate(table.target, start=1))
    has_class = any(t.source for t in targets)
    graduated = table.design.graduated if table.design.graduated is not None else has_class
    result = Targets(path, table.design, targets, table.fabric, graduated)
    check_consistent(result)
    return result


def _refusal(path: Path, error: dict) -> CaseError:
    loc = tuple(error["loc"])
    if not loc:
        return CaseError(path, "is not a table of settings", "write [design], [[target]] and [fabric] tables")
    if loc[0] == "target" and len(loc) == 1:
        return CaseError(path, "has no [[target]] table", "add one, e.g. [[target]] landmark = \"deep_veins\" "
                                                           "min_mmHg = 15")
    if loc[0] == "target" and len(loc) >= 2 and isinstance(loc[1], int):
        where, rest = f"[[target]] number {loc[1] + 1}", loc[2:]
    else:
        where, rest = f"[{loc[0]}]", loc[1:]
    key = rest[0] if rest else None
    if error["type"] == "extra_forbidden":
        known = {"[design]": DesignTable, "[fabric]": FabricTable}.get(where, TargetTable)
        names = ", ".join(field.alias or name for name, field in known.model_fields.items())
        return CaseError(path, f"{where} has an unknown key '{key}'", f"use only {names}")
    if key is None or error["type"] == "value_error":
        message = error["msg"].removeprefix("Value error, ")
        return CaseError(path, f"{where} is not valid: {message.split(': ')[0]}",
                         message.split(": ", 1)[1] if ": " in message else "see docs/design-garment.md")
    return CaseError(path, f"{where} {key} is not valid ({error['msg']})",
                     f"write {key} as docs/design-garment.md shows")


def _target(path: Path, index: int, entry: TargetTable) -> Target:
    where = f"[[target]] number {index}"
    places = [name for name, value in (("landmark", entry.landmark), ("region", entry.region)) if value]
    if len(places) > 1:
        raise CaseError(path, f"{where} names both a landmark and a region", "give one target per table")
    if not places and entry.height is None:
        raise CaseError(path, f"{where} names no place", "give landmark = ..., region = ... or height = \"B\"")
    bounds = {}
    for bound in ("min", "max", "value"):
        mmhg, kpa = getattr(entry, f"{bound}_mmHg"), getattr(entry, f"{bound}_kPa")
        if mmhg is not None and kpa is not None:
            raise CaseError(path, f"{where} gives {bound}_mmHg and {bound}_kPa", "give the pressure in one unit")
        bounds[bound] = mmhg if mmhg is not None else (kpa * MMHG_PER_KPA if kpa is not None else None)
    if entry.class_ is not None:
        if places:
            raise CaseError(path, f"{where} gives a class at a {places[0]}",
                            "a class is the skin pressure at a height: write height = \"B\" and class = ...")
        if any(value is not None for value in bounds.values()):
            raise CaseError(path, f"{where} gives a class and a pressure", "give the class or the pressure")
        try:
            grade = compression_class(entry.class_)
        except KeyError as error:
            raise CaseError(path, f"{where} class = {entry.class_!r} is not known", str(error.args[0])) from None
        height = entry.height or "B"
        if height != "B":
            raise CaseError(path, f"{where} gives class {grade.label} at {height}",
                            "the standards class a stocking by its pressure at B: write height = \"B\"")
        low, high = grade.min_mmHg, grade.max_mmHg
        aim = (low + high) / 2.0 if high is not None else None
        name = entry.name or f"{height} skin {grade.standard} {grade.name}"
        return Target(index, name, "skin", None, height, low, high, aim, grade.source)
    if all(value is None for value in bounds.values()):
        raise CaseError(path, f"{where} gives no pressure", "give min_mmHg, max_mmHg or value_mmHg (or _kPa)")
    if bounds["value"] is not None and (bounds["min"] is not None or bounds["max"] is not None):
        raise CaseError(path, f"{where} gives a value and a bound", "give value_mmHg with tolerance_mmHg, or bounds")
    low, high, aim = bounds["min"], bounds["max"], None
    if bounds["value"] is not None:
        aim = bounds["value"]
        low, high = max(0.0, aim - entry.tolerance_mmHg), aim + entry.tolerance_mmHg
    if low is not None and high is not None and low > high:
        raise CaseError(path, f"{where} asks at least {low:g} and at most {high:g} mmHg",
                        "give a minimum below the maximum")
    if entry.landmark:
        kind, place = "landmark", entry.landmark
    elif entry.region:
        kind, place = "region", entry.region
        if low is not None:
            raise CaseError(path, f"{where} gives a minimum over a region",
                            "a region takes a maximum (the skin's largest pressure there); a minimum belongs to a "
                            "height (its mean skin pressure) or a landmark")
    else:
        kind, place = "skin", None
    label = place or "skin"
    name = entry.name or " ".join(part for part in (entry.height, label) if part)
    return Target(index, name, kind, place, entry.height, low, high, aim)


def check_consistent(targets: Targets) -> None:
    """Refuse targets no pressure field can meet together (module text), with the two tables and the fix."""
    path = targets.path
    by_quantity: dict[tuple, list[Target]] = {}
    for target in targets.targets:
        by_quantity.setdefault(target.quantity, []).append(target)
    for group in by_quantity.values():
        for a in group:
            for b in group:
                if a.index < b.index and _disjoint(a, b):
                    raise CaseError(path, f"[[target]] {a.index} ({a.name} {a.bounds_text}) and [[target]] {b.index} "
                                          f"({b.name} {b.bounds_text}) contradict: no pressure meets both",
                                    "loosen or remove one of them")
    anywhere = [t for t in targets.targets if t.kind == "region" and t.where == "anywhere" and t.max_mmHg is not None]
    for cap in anywhere:
        for target in targets.targets:
            if target.kind == "skin" and target.min_mmHg is not None and target.min_mmHg > cap.max_mmHg \
                    and (cap.height is None or cap.height == target.height):
                raise CaseError(path, f"[[target]] {target.index} ({target.name} {target.bounds_text}) asks a mean "
                                      f"skin pressure above [[target]] {cap.index}'s maximum anywhere on the skin "
                                      f"({cap.max_mmHg:g} mmHg)", "a mean cannot exceed the largest value: raise "
                                                                  "the maximum or lower the minimum")
    if targets.graduated:
        skins = {t.height: t for t in targets.targets if t.kind == "skin" and t.height is not None}
        order = [h for h in HEIGHTS if h in skins]
        for i, lower in enumerate(order):
            for upper in order[i + 1:]:
                low, high = skins[upper].min_mmHg, skins[lower].max_mmHg
                if low is not None and high is not None and low > high:
                    raise CaseError(path, f"[[target]] {skins[upper].index} ({upper} at least {low:g} mmHg) is above "
                                          f"[[target]] {skins[lower].index} ({lower} at most {high:g} mmHg), and the "
                                          f"graduation asks the pressure to fall from {lower} to {upper}",
                                    "lower the proximal minimum, or write graduated = false under [design]")


def _disjoint(a: Target, b: Target) -> bool:
    low = max(v for v in (a.min_mmHg, b.min_mmHg, -1.0) if v is not None)
    high = min(v for v in (a.max_mmHg, b.max_mmHg, 1e9) if v is not None)
    return low > high
