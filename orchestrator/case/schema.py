"""case.toml, declared once: every table and key a case's settings may hold, its type, unit and range, and the one
sentence each mistake gets, for a slice case (`CaseToml`, read by `folder.read_case`) and a volume case
(`VolumeCaseToml`, its [study] table, read by `study.volume_cases`).

Each table is a pydantic model: strict (a number is a TOML number, never the string "0.16", and true is not 1),
extra keys forbidden, every key a `key(...)` field carrying beside its type and range what it is in words and an
example. `parse` validates the whole file and turns pydantic's first error into one `CaseError` naming the file,
the line, the table and key, what the value should be (its range and unit) and the fix:

    case.toml: line 6, [garment] tension_N_per_mm = 1000000000.0 is not a positive number of N/mm of at most 2
    (0.16 N/mm is about 20 mmHg on a calf, 2 N/mm over 250 mmHg); write tension_N_per_mm = 0.16, the garment's
    force per unit width.

An unknown key is named with the nearest known one (difflib). pydantic rather than a table of keys written by
hand: the tables nest ([[garment.levels]], [model.<tissue>] tables of constants, the volume case's tension
profile), and its locations, strict types, ranges and forbidden extras are what such a table would have to
re-implement; the rules that tie two keys (friction needs the explicit garment, an incompressible tissue the u/p
elements, one way of choosing a slice) are the models' validators, raising `Refusal` with their own sentence. So
every rule that can be judged from case.toml alone is here; what needs the images (a landmark inside the image, a
level's file, the pixel size a header gives) is checked by `folder.read_case` with the ranges declared here.
"""

from __future__ import annotations

import difflib
import re
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    StringConstraints,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)

from ..core.errors import CaseError, MaterialError
from ..core.materials import ELEMENTS, GARMENTS, LAWS, tissue_set

# The ranges of the physical values, refused where case.toml (or an image header) is read.
TENSION_MAX_N_PER_MM = 2.0      # p = T / r: on a calf of 55 mm radius, 0.16 N/mm is 22 mmHg, 2 N/mm 270 mmHg
PIXEL_SIZE_RANGE_MM = (0.01, 5.0)   # an MRI slice's pixels: 0.1-2 mm; a value in cm or m is 10 or 1000 times off
FRICTION_MAX = 2.0
TENSION_TEXT = (f"a positive number of N/mm of at most {TENSION_MAX_N_PER_MM:g} (0.16 N/mm is about 20 mmHg on a "
                f"calf, {TENSION_MAX_N_PER_MM:g} N/mm over 250 mmHg)")
PIXEL_SIZE_TEXT = f"between {PIXEL_SIZE_RANGE_MM[0]:g} and {PIXEL_SIZE_RANGE_MM[1]:g} mm"


class Refusal(ValueError):
    """A rule of a table's validator broken, in the words of a `CaseError`: what is wrong, the fix, and the key
    whose line the message names (None: the table's header) in the table it names (None: the validator's own)."""

    def __init__(self, problem: str, fix: str, key: str | None = None, table: str | None = None):
        super().__init__(problem)
        self.problem, self.fix, self.key, self.table = problem, fix, key, table


def key(default: Any = ..., *, meaning: str, example: str | None = None, note: str = "", fix: str | None = None,
        entry: tuple[str, str] | None = None, **constraints) -> Any:
    """A key of a table: its default (... : required) and pydantic constraints, and for the messages what a value
    should be (`meaning`, after "is not"), an example value, a note after it, or a whole `fix`; `entry`: the
    (meaning, fix) of one entry of a table of values ({name} is the entry's name)."""
    return Field(default, json_schema_extra={"meaning": meaning, "example": example, "note": note, "fix": fix,
                                             "entry": entry}, **constraints)


Finite = Annotated[float, Field(allow_inf_nan=False)]
Text = Annotated[str, StringConstraints(pattern=r"\S")]
Tension = Annotated[float, Field(gt=0.0, le=TENSION_MAX_N_PER_MM, allow_inf_nan=False)]
Pair = Annotated[list[Finite], Field(min_length=2, max_length=2)]


class Table(BaseModel):
    """A table of case.toml: strict types, no key it does not declare."""

    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)
    KEYS_TEXT: ClassVar[str | None] = None   # how "use only ..." names the keys, when not by their list


class CaseTable(Table):
    name: Text | None = key(None, meaning="a non-empty string", example='"volunteer-01"',
                            note=" (the case's name in reports, default the folder's name)")
    pixel_size_mm: Pair | None = key(
        None, meaning=f"two pixel sizes {PIXEL_SIZE_TEXT} (row, column)", example="[0.36, 0.36]",
        note=" in mm, row then column (a size in cm or m is 10 or 1000 times off)")
    @field_validator("pixel_size_mm")
    @classmethod
    def _sides_in_range(cls, value):
        # each side's range checked here, so that the message shows the pair (a constraint on the list's items
        # would show the one side alone)
        if value is not None and not all(PIXEL_SIZE_RANGE_MM[0] <= side <= PIXEL_SIZE_RANGE_MM[1] for side in value):
            raise ValueError("out of range")
        return value


class GarmentLevelTable(Table):
    image: Text = key(meaning="a file name", example='"loaded-40mmHg.png"',
                      note=", that level's loaded slice, a file of the case folder")
    tension_N_per_mm: Tension = key(meaning=TENSION_TEXT, example="0.27", note=", that garment's force per unit width")
    points: Text | None = key(None, meaning="a file name", example='"points-40mmHg.csv"',
                              note=", that level's points (points.csv format), a file of the case folder")


class GarmentTable(Table):
    tension_N_per_mm: Tension = key(meaning=TENSION_TEXT, example="0.16",
                                    note=", the garment's force per unit width, constant around the leg")
    tension_rel_uncertainty: float | None = key(
        None, meaning="a relative uncertainty between 0 and 1", example="0.10", note=" (10 %, the default)",
        ge=0.0, le=1.0, allow_inf_nan=False)
    levels: list[GarmentLevelTable] = key(
        [], meaning="an array of tables",
        fix="write each more loaded image as a [[garment.levels]] table with image and tension_N_per_mm")


class ImagesTable(Table):
    slice_index: int | None = key(None, meaning="a non-negative whole number", example="7",
                                  note=", the 0-based index of the slice in order of increasing position", ge=0)
    slice_position_mm: Finite | None = key(None, meaning="a number", example="-42.5",
                                           note=", the position of the slice along the slice normal in mm")

    @model_validator(mode="after")
    def _one_choice(self):
        if self.slice_index is not None and self.slice_position_mm is not None:
            raise Refusal("[images] gives both slice_index and slice_position_mm",
                          "keep only one of them (slice_position_mm is the safer: it picks the same place in both "
                          "series)", "slice_position_mm")
        return self


_CONSTANT_FIX = "write {name} = <value> in kPa"


class TissueTable(Table):
    law: Literal[LAWS] = key("avril", meaning="a law calfit fits", fix=f"write one of {', '.join(LAWS)}")
    terms: int | None = key(None, meaning="a whole number", fix="write terms = 2 or terms = 3")
    incompressible: bool = key(False, meaning="true or false", fix="write incompressible = true (D1 = 0) or leave it out")
    fixed: dict[str, Finite] = key({}, meaning="a table of constants", fix="write fixed = { C10 = 1.2 } (kPa)",
                                   entry=("a number", _CONSTANT_FIX))
    bounds: dict[str, Pair] = key({}, meaning="a table of constants", fix="write bounds = { C10 = [0.5, 20] } (kPa)",
                                  entry=("[lower, upper]", "write {name} = [lower, upper] in kPa"))
    start: dict[str, Finite] = key({}, meaning="a table of constants", fix="write start = { C10 = 1.2 } (kPa)",
                                   entry=("a number", _CONSTANT_FIX))


class ModelTable(Table):
    KEYS_TEXT: ClassVar[str] = "element, garment, friction and a [model.<tissue>] table per tissue"
    element: Literal[tuple(ELEMENTS)] | None = key(None, meaning="an element calfit fits",
                                                   fix=f"write one of {', '.join(repr(e) for e in ELEMENTS)}")
    garment: Literal[GARMENTS] = key("laplace", meaning="a garment model",
                                     fix='write garment = "laplace" (Laplace\'s law, the first paper) or "explicit" '
                                         "(the band of the second paper)")
    friction: float = key(0.0, meaning="a friction coefficient", fix="write a number between 0 (frictionless) and 2",
                          ge=0.0, le=FRICTION_MAX, allow_inf_nan=False)
    tissues: dict[str, TissueTable] = {}   # the [model.<tissue>] tables, gathered by _tissue_tables

    @model_validator(mode="before")
    @classmethod
    def _tissue_tables(cls, value):
        if isinstance(value, dict):
            tables = {name: table for name, table in value.items() if isinstance(table, dict)}
            value = {name: item for name, item in value.items() if name not in tables} | {"tissues": tables}
        return value

    @model_validator(mode="after")
    def _rules(self):
        if self.friction > 0.0 and self.garment != "explicit":
            raise Refusal("[model] friction needs the explicit garment (Laplace's law has no tangential traction)",
                          'add garment = "explicit" or remove friction', "friction")
        for tissue, table in self.tissues.items():
            try:
                tissue_set(tissue)
            except MaterialError:
                raise Refusal(f"[model.{tissue}] is not a tissue", "name the table [model.fat], [model.muscle] or "
                              "[model.compartment<label>] for a compartment labelled >= 4 in labels.png",
                              table=f"model.{tissue}") from None
            if table.incompressible and self.element != "CPE6H":
                raise Refusal(f"[model.{tissue}] is incompressible, which displacement elements lock on",
                              'add element = "CPE6H" (u/p elements) to [model]', "incompressible", f"model.{tissue}")
        return self


Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]


class AcquisitionTable(Table):
    """The sequence's parameters that set the fat's chemical shift (`acquisition`), for images whose files carry no
    DICOM header (PNG, TIFF, NIfTI exported from the scanner): the scanner's protocol sheet gives them."""

    pixel_bandwidth_Hz: Positive = key(meaning="a bandwidth in Hz per pixel", example="160",
                                       note=" (the protocol's receiver bandwidth per pixel, DICOM PixelBandwidth)")
    imaging_frequency_MHz: Positive | None = key(None, meaning="a frequency in MHz", example="63.87",
                                                 note=" (DICOM ImagingFrequency)")
    field_strength_T: Positive | None = key(None, meaning="a field strength in tesla", example="1.5",
                                            note=" (used when imaging_frequency_MHz is not given)")
    readout: Literal["x", "y"] | None = key(None, meaning='"x" or "y"',
                                           fix='write readout = "x" (the readout along the image\'s rows) or "y"')

    @model_validator(mode="after")
    def _a_frequency(self):
        if self.imaging_frequency_MHz is None and self.field_strength_T is None:
            raise Refusal("[acquisition] gives pixel_bandwidth_Hz but no frequency",
                          "add imaging_frequency_MHz = <MHz> or field_strength_T = <T>", "pixel_bandwidth_Hz")
        return self


class CaseToml(Table):
    """case.toml of a slice case (docs/case-folder.md)."""

    case: CaseTable = CaseTable()
    garment: GarmentTable = key(meaning="a table", fix="add [garment] with tension_N_per_mm = <force per unit width>")
    landmarks: dict[str, Pair] = key({}, meaning="a table of landmarks",
                                     entry=("a pair of numbers", "write {name} = [x_mm, y_mm]"))
    images: ImagesTable | None = None
    model: ModelTable = ModelTable()
    acquisition: AcquisitionTable | None = None


# ----------------------------------------------------------------- the volume case ([study], `study.volume_cases`)


class TensionProfile(Table):
    heights_mm: list[Finite] = key(meaning="a list of heights in mm", example="[196.0, 300.0]")
    values: list[Tension] = key(meaning=f"a list of tensions, each {TENSION_TEXT}", example="[0.20, 0.14]")

    @model_validator(mode="after")
    def _paired(self):
        if len(self.heights_mm) != len(self.values) or len(self.heights_mm) < 2:
            raise Refusal("[garment] tension_N_per_mm's heights_mm and values are not two lists of the same length "
                          "(at least 2)", _PROFILE_FIX)
        if len(set(self.heights_mm)) != len(self.heights_mm):
            raise Refusal("[garment] tension_N_per_mm gives two tensions at one height", "keep one value per height")
        return self


_PROFILE_FIX = "write tension_N_per_mm = 0.16, or { heights_mm = [196.0, 300.0], values = [0.20, 0.14] } along the leg"


class VolumeGarmentTable(Table):
    tension_N_per_mm: Annotated[Annotated[Tension, Tag("number")] | Annotated[TensionProfile, Tag("table")],
                                Discriminator(lambda value: "table" if isinstance(value, dict) else "number")] = key(
        meaning=f"{TENSION_TEXT}, nor a table of heights and values", fix=_PROFILE_FIX)
    tension_rel_uncertainty: float | None = GarmentTable.model_fields["tension_rel_uncertainty"]


class StudyTable(Table):
    heights_mm: Annotated[list[Finite], Field(min_length=1)] | None = key(
        None, meaning="a list of numbers", fix="write heights_mm = [204.0, 212.0] (mm along the slice normal)")
    every_mm: float | None = key(None, meaning="a positive number", fix="write every_mm = 10.0", gt=0.0,
                                 allow_inf_nan=False)
    compression_heights_mm: dict[str, Finite] = key(
        {}, meaning="a table of heights", fix="write compression_heights_mm = { B = 120.0, C = 280.0 } (mm)",
        entry=("a height in mm", "write compression_heights_mm = { B = 120.0, C = 280.0 } (mm)"))

    @model_validator(mode="after")
    def _one_way(self):
        if (self.heights_mm is None) == (self.every_mm is None):
            raise Refusal("[study] needs one of heights_mm and every_mm",
                          "write heights_mm = [h1, h2, ...] (slice positions in mm) or every_mm = <spacing in mm>")
        return self


Point3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]


class VolumeCaseToml(Table):
    """case.toml of a volume case (`study.volume_cases`)."""

    case: CaseTable = CaseTable()
    garment: VolumeGarmentTable = key(meaning="a table", fix="add [garment] with tension_N_per_mm: a number, or "
                                      "{ heights_mm = [...], values = [...] } along the leg")
    study: StudyTable
    landmarks: dict[str, Point3 | Annotated[list[Point3], Field(min_length=1)]] = key(
        {}, meaning="a table of landmarks", entry=("a point [x, y, height] or a line of them",
                                                   "write {name} = [x_mm, y_mm, height_mm] or {name} = [[x, y, h1], "
                                                   "[x, y, h2], ...]"))
    model: ModelTable = ModelTable()


# ----------------------------------------------------------------- reading


def parse(path, text: str, settings: dict, schema: type[Table] = CaseToml):
    """settings (case.toml's text parsed by tomllib) validated by `schema`; CaseError at the first mistake."""
    try:
        return schema.model_validate(settings)
    except ValidationError as error:
        # an unknown key first: a misspelt required key is also reported missing, and the typo is the news
        first = min(error.errors(), key=lambda entry: entry["type"] != "extra_forbidden")
        raise refusal(path, text, settings, first, schema) from None


def keys_of(schema: type[Table] = CaseToml) -> dict[str, set[str] | None]:
    """{table: its keys} (None: any name, as [landmarks] and [model]'s tissue tables), as docs/case-folder.md
    documents them."""
    tables = {}
    for name, field in schema.model_fields.items():
        model = _table_model(schema, name)
        tables[name] = None if model is None or model is ModelTable else set(model.model_fields)
    return tables


def _table_model(schema: type[Table], name: str) -> type[Table] | None:
    annotation = schema.model_fields[name].annotation
    for candidate in (annotation, *getattr(annotation, "__args__", ())):
        if isinstance(candidate, type) and issubclass(candidate, Table):
            return candidate
    return None


def refusal(path, text: str, settings: dict, error: dict, schema: type[Table]) -> CaseError:
    """The CaseError of one pydantic error (`parse`)."""
    loc, kind = tuple(error["loc"]), error["type"]
    if not loc:
        return CaseError(path, f"is not a table of settings ({kind})", "write tables in [brackets] and key = value")
    exception = (error.get("ctx") or {}).get("error")
    if isinstance(exception, Refusal):   # a rule of a table's validator, in its own words
        header = (exception.table, 0) if exception.table else _header(loc)
        return CaseError(path, _at(text, header, exception.key) + exception.problem, exception.fix)
    if len(loc) == 1 or loc[0] not in schema.model_fields:
        return _table_refusal(path, text, error, schema)
    top = loc[0]
    if top == "landmarks":
        name = str(loc[1])
        meaning, fix = schema.model_fields["landmarks"].json_schema_extra["entry"]
        return CaseError(path, _at(text, ("landmarks", 0), name) + f"landmark '{name}' = "
                         f"{_value_at(settings, ('landmarks', name))!r} is not {meaning}", fix.format(name=name))
    # which table: a [[garment.levels]] table, a [model.<tissue>] table, or the top-level one
    if top == "garment" and len(loc) >= 4 and loc[1] == "levels" and isinstance(loc[2], int):
        where, header, model, rest = f"[[garment.levels]] number {loc[2] + 1}", ("garment.levels", loc[2]), \
            GarmentLevelTable, loc[3:]
    elif top == "model" and len(loc) >= 3 and loc[1] == "tissues":
        where, header, model, rest = f"[model.{loc[2]}]", (f"model.{loc[2]}", 0), TissueTable, loc[3:]
    else:
        where, header, model, rest = f"[{top}]", (top, 0), _table_model(schema, top), loc[1:]
    name = rest[0] if rest else None
    if kind == "extra_forbidden" and len(rest) == 1:
        return CaseError(path, _at(text, header, name) + f"{where} has an unknown key '{name}'",
                         _use_only(str(name), model))
    field = model.model_fields.get(name) if isinstance(name, str) and model is not None else None
    if field is None:
        return CaseError(path, _at(text, header, None) + f"{where} is not valid ({error['msg']})",
                         f"write {where} as docs/case-folder.md shows")
    extra = field.json_schema_extra or {}
    if kind == "missing" and len(rest) == 1:
        fix = extra.get("fix") or f"add {name} = {extra.get('example')} under {where}{extra.get('note', '')}"
        return CaseError(path, _at(text, header, None) + f"{where} {name} is missing", fix)
    value = _value_at(settings, loc[:len(loc) - len(rest) + 1])
    entries = [part for part in rest[1:] if isinstance(part, str)]
    if entries and extra.get("entry"):
        meaning, fix = extra["entry"]
        shown = value.get(entries[0]) if isinstance(value, dict) else value
        return CaseError(path, _at(text, header, name) + f"{where} {name}.{entries[0]} = {shown!r} is not {meaning}",
                         fix.format(name=entries[0]))
    fix = extra.get("fix") or f"write {name} = {extra.get('example')}{extra.get('note', '')}"
    return CaseError(path, _at(text, header, name) + f"{where} {name} = {value!r} is not {extra.get('meaning')}", fix)


def _header(loc: tuple) -> tuple[str, int]:
    """The header in case.toml of the table at loc: [[garment.levels]] (which one), [model.<tissue>] or [top]."""
    if loc[:2] == ("garment", "levels") and len(loc) >= 3 and isinstance(loc[2], int):
        return "garment.levels", loc[2]
    if loc[:2] == ("model", "tissues") and len(loc) >= 3:
        return f"model.{loc[2]}", 0
    return str(loc[0]), 0


def _table_refusal(path, text, error, schema) -> CaseError:
    """An error about a whole top-level table: missing, unknown, or not a table."""
    name, kind = error["loc"][0], error["type"]
    tables = list(schema.model_fields)
    if kind == "extra_forbidden":
        close = difflib.get_close_matches(str(name), tables, n=1, cutoff=0.6)
        listed = ", ".join(f"[{t}]" for t in tables)
        return CaseError(path, _at(text, (name, 0), None, top_key=name) + f"has an unknown table or key '{name}'",
                         f"write [{close[0]}] (the tables are {listed})" if close else f"use only the tables {listed}")
    field = schema.model_fields[name]
    extra = field.json_schema_extra or {}
    if kind == "missing":
        return CaseError(path, f"has no [{name}] table", extra.get("fix") or f"add a [{name}] table")
    return CaseError(path, _at(text, (name, 0), None, top_key=name) + f"'{name}' is not a table",
                     f"write it as a [{name}] table")


def _use_only(name: str, model: type[Table]) -> str:
    keys = [k for k in model.model_fields if k != "tissues"]
    listed = model.KEYS_TEXT or ", ".join(keys)
    close = difflib.get_close_matches(name, keys, n=1, cutoff=0.6)
    return f"write {close[0]} (the keys are {listed})" if close else f"use only {listed}"


def _value_at(settings: dict, loc: tuple) -> Any:
    value = settings
    for part in loc:
        if isinstance(value, dict) and part == "tissues" and "tissues" not in value:
            continue   # [model]'s tissue tables are its own keys in case.toml
        try:
            value = value[part]
        except (KeyError, IndexError, TypeError):
            return None
    return value


_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")


def line_of(text: str, table: str, index: int = 0, key: str | None = None, top_key: str | None = None) -> int | None:
    """The 1-based line of `key` under the index-th header [table] (or [[table]]) of case.toml's text, else of that
    header; top_key: a key before any header. None where it cannot be found (a dotted or inline key)."""
    current, seen, header_line = None, {}, None
    pattern = re.compile(rf"^\s*[\"']?{re.escape(key)}[\"']?\s*=") if key else None
    for number, line in enumerate(text.splitlines(), start=1):
        match = _HEADER.match(line)
        if match:
            name = re.sub(r"[\s\"']", "", match.group(1))
            count = seen.get(name, 0)
            seen[name] = count + 1
            current = (name, count)
            if current == (table, index):
                header_line = number
            continue
        if current is None and top_key and re.match(rf"^\s*{re.escape(top_key)}\s*=", line):
            return number
        if current == (table, index) and pattern is not None and pattern.match(line):
            return number
    return header_line


def _at(text: str, header: tuple, key, top_key: str | None = None) -> str:
    """"line N, " where the mistake is, "" where it cannot be found."""
    line = line_of(text, str(header[0]), int(header[1]), str(key) if key is not None else None, top_key)
    return f"line {line}, " if line is not None else ""
