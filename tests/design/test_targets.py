"""TARGET.toml and the standards (orchestrator/design/targets.py, standards.py): what a valid file holds, and each
mistake or contradiction refused with one sentence naming the file, the table and the fix. No engine."""

from __future__ import annotations

import pytest

from orchestrator.core.errors import CaseError
from orchestrator.design.standards import CLASSES, compression_class
from orchestrator.design.targets import read_targets

VALID = """
[design]
tension_range_N_per_mm = [0.05, 0.6]
slice_height = "B"

[[target]]
height = "B"
class = "RAL II"

[[target]]
landmark = "deep_veins"
min_kPa = 2.0

[[target]]
region = "tibial_crest"
max_mmHg = 40
"""


def _write(tmp_path, text):
    path = tmp_path / "TARGET.toml"
    path.write_text(text)
    return path


def test_a_valid_file_gives_each_target_in_mmHg_and_a_class_its_range_and_source(tmp_path):
    targets = read_targets(_write(tmp_path, VALID))
    klass, veins, crest = targets.targets
    assert (klass.kind, klass.height, klass.min_mmHg, klass.max_mmHg, klass.aim_mmHg) == ("skin", "B", 23, 32, 27.5)
    assert "RAL-GZ 387/1" in klass.source
    assert veins.kind == "landmark" and veins.min_mmHg == pytest.approx(15.0012, abs=1e-3) and veins.max_mmHg is None
    assert crest.kind == "region" and crest.where == "tibial_crest" and crest.max_mmHg == 40
    assert targets.graduated   # a class asks the standard's graduation by default
    assert targets.design.tension_range_N_per_mm == [0.05, 0.6]


def test_the_classes_of_the_three_standards_and_their_names():
    assert compression_class("RAL II").max_mmHg == 32 and compression_class("ral 2").min_mmHg == 23
    assert (compression_class("French II").min_mmHg, compression_class("FR II").max_mmHg) == (15, 20)
    assert (compression_class("British class II").min_mmHg, compression_class("BS 2").max_mmHg) == (18, 24)
    assert compression_class("RAL IV").max_mmHg is None
    assert all(grade.source for grade in CLASSES.values())
    with pytest.raises(KeyError, match="RAL I, RAL II"):
        compression_class("RAL V")


@pytest.mark.parametrize("text, words", [
    (VALID + '\n[[target]]\nlandmark = "deep_veins"\nmax_mmHg = 12\n',
     ["[[target]] 2", "[[target]] 4", "contradict", "loosen or remove one"]),
    (VALID + '\n[[target]]\nheight = "B"\nmax_mmHg = 20\n', ["[[target]] 1", "[[target]] 4", "contradict"]),
    (VALID + '\n[[target]]\nregion = "anywhere"\nmax_mmHg = 20\n',
     ["[[target]] 1", "[[target]] 4", "maximum anywhere", "raise the maximum"]),
    (VALID + '\n[[target]]\nheight = "C"\nmin_mmHg = 35\n',
     ["[[target]] 4", "C at least 35", "B at most 32", "graduated = false"]),
    ('[[target]]\nlandmark = "deep_veins"\nmin_mmHg = 30\nmax_mmHg = 20\n', ["[[target]] number 1", "minimum below"]),
    ('[[target]]\nlandmark = "deep_veins"\nmin_mmHg = 15\nminimum = 3\n', ["unknown key 'minimum'", "min_mmHg"]),
    ('[design]\ntension_range_N_per_mm = [0.5, 0.1]\n[[target]]\nheight = "B"\nclass = "RAL II"\n',
     ["[design]", "lowest < highest"]),
    ('[[target]]\nheight = "B"\nclass = "RAL VII"\n', ["[[target]] number 1", "RAL VII", "RAL II"]),
    ('[[target]]\nlandmark = "deep_veins"\n', ["[[target]] number 1", "gives no pressure", "min_mmHg"]),
    ('[[target]]\nregion = "tibial_crest"\nmin_mmHg = 10\n', ["minimum over a region", "takes a maximum"]),
    ('[[target]]\nlandmark = "deep_veins"\nmin_mmHg = 15\nmin_kPa = 2\n', ["one unit"]),
    ('[[target]]\nheight = "C"\nclass = "RAL II"\n', ["at C", "height = \\\"B\\\""]),
    ('[design]\nharmonics = 1\n', ["has no [[target]] table", "min_mmHg = 15"]),
])
def test_each_mistake_is_one_sentence_naming_the_file_the_table_and_the_fix(tmp_path, text, words):
    with pytest.raises(CaseError) as raised:
        read_targets(_write(tmp_path, text))
    message = str(raised.value)
    assert message.startswith(str(tmp_path / "TARGET.toml") + ": ") and message.endswith(".")
    assert message.count("; ") >= 1 and "\n" not in message
    for word in words:
        assert word.replace('\\"', '"') in message, message


def test_graduation_off_lets_a_proximal_minimum_stand(tmp_path):
    text = VALID.replace('slice_height = "B"', 'slice_height = "B"\ngraduated = false') + \
        '\n[[target]]\nheight = "C"\nmin_mmHg = 35\n'
    assert not read_targets(_write(tmp_path, text)).graduated


def test_a_missing_or_broken_file_names_itself(tmp_path):
    with pytest.raises(CaseError, match="does not exist"):
        read_targets(tmp_path / "nothing.toml")
    with pytest.raises(CaseError, match="is not TOML"):
        read_targets(_write(tmp_path, "[[target]\n"))
