"""case.toml's declared schema (`orchestrator.case.schema`): each mistake is one sentence naming case.toml, the
line, the table and key, what the value should be (its range and unit) and the fix; a typo is answered with the
nearest key; a volume case's [study] and tension profile are read by the same schema."""

from __future__ import annotations

import pytest
import tomllib

from orchestrator.case.schema import (
    TENSION_MAX_N_PER_MM,
    CaseToml,
    VolumeCaseToml,
    keys_of,
    parse,
)
from orchestrator.core.errors import CaseError

BASE = '[case]\nname = "m"\npixel_size_mm = [0.5, 0.5]\n\n[garment]\ntension_N_per_mm = 0.16\n'
LEVELS = ('\n[[garment.levels]]\nimage = "a.png"\ntension_N_per_mm = 0.27\n'
          '\n[[garment.levels]]\nimage = "b.png"\ntension_N_per_mm = 0.32\n')
VOLUME = ('[study]\nheights_mm = [204.0, 212.0]\n[garment]\n'
          'tension_N_per_mm = { heights_mm = [196.0, 300.0], values = [0.20, 0.14] }\n')


def _refusal(text: str, schema=CaseToml) -> str:
    with pytest.raises(CaseError) as raised:
        parse("case.toml", text, tomllib.loads(text), schema)
    message = str(raised.value)
    assert message.startswith("case.toml: ") and message.count(";") == 1 and message.endswith("."), message
    return message


def test_a_good_file_is_read_with_its_defaults():
    settings = parse("case.toml", BASE + LEVELS, tomllib.loads(BASE + LEVELS))
    assert settings.garment.tension_N_per_mm == 0.16 and settings.garment.tension_rel_uncertainty is None
    assert [level.tension_N_per_mm for level in settings.garment.levels] == [0.27, 0.32]
    assert settings.model.garment == "laplace" and settings.case.pixel_size_mm == [0.5, 0.5]


@pytest.mark.parametrize("text, fragments", [
    (BASE.replace("0.16", "1e9"), ["line 6, [garment] tension_N_per_mm = 1000000000.0",
                                   f"at most {TENSION_MAX_N_PER_MM:g}", "N/mm", "write tension_N_per_mm = 0.16"]),
    (BASE.replace("0.16", '"0.16"'), ["tension_N_per_mm = '0.16' is not a positive number"]),
    (BASE.replace("0.16", "true"), ["tension_N_per_mm = True is not a positive number"]),
    (BASE + LEVELS.replace("0.32", "9.0"), ["line 14, [[garment.levels]] number 2 tension_N_per_mm = 9.0", "at most 2"]),
    (BASE.replace("[0.5, 0.5]", "[0.5, 50.0]"), ["line 3, [case] pixel_size_mm = [0.5, 50.0]", "0.01 and 5 mm"]),
    (BASE + "tension_rel_uncertainty = 1.5\n", ["line 7", "between 0 and 1"]),
    (BASE.replace("name", "nmae"), ["line 2, [case] has an unknown key 'nmae'", "write name (the keys are name"]),
    (BASE + "[garmnet]\nx = 1\n", ["has an unknown table or key 'garmnet'", "write [garment]"]),
    (BASE + '[images]\nslice_index = 2\nslice_position_mm = 1.5\n', ["[images] gives both", "keep only one"]),
    (BASE + '[landmarks]\nveins = [1.0]\n', ["line 8, landmark 'veins' = [1.0] is not a pair of numbers",
                                            "write veins = [x_mm, y_mm]"]),
    (BASE + '[model.fat]\nlaw = "neo_hooke"\nstart = { C10 = "1" }\n', ["line 9, [model.fat] start.C10 = '1'",
                                                                       "write C10 = <value> in kPa"]),
])
def test_each_mistake_names_the_line_the_key_and_the_fix(text, fragments):
    message = _refusal(text)
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"


@pytest.mark.parametrize("text, fragment", [
    (VOLUME.replace("0.14", "14.0"), "tension_N_per_mm = {'heights_mm': [196.0, 300.0], 'values': [0.2, 14.0]}"),
    (VOLUME.replace("heights_mm = [204.0, 212.0]", "every_mm = -3.0"), "[study] every_mm = -3.0 is not a positive"),
    (VOLUME.replace("[196.0, 300.0]", "[196.0, 196.0]"), "two tensions at one height"),
    (VOLUME + "[study.x]\n", "'study' is not"),
])
def test_a_volume_case_is_read_by_the_same_schema(text, fragment):
    if fragment == "'study' is not":   # [study.x] makes [study] hold a table: an unknown key of [study]
        fragment = "[study] has an unknown key 'x'"
    assert fragment in _refusal(text, VolumeCaseToml)


def test_the_declared_keys_are_what_the_docs_list():
    keys = keys_of()
    assert keys["garment"] == {"tension_N_per_mm", "tension_rel_uncertainty", "levels"}
    assert keys["landmarks"] is None and keys["model"] is None and set(keys) == {"case", "garment", "landmarks",
                                                                                "images", "model", "acquisition"}
    assert keys["acquisition"] == {"pixel_bandwidth_Hz", "imaging_frequency_MHz", "field_strength_T", "readout"}
