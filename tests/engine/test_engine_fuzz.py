"""Mutated verification decks (`fuzz_decks.py`, fixed seed): calfit-fe never crashes or hangs, every rejection
(exit 2) names the file and the line, and any other failure (exit 4) says which deck and why. `make fuzz` runs
100,000 inputs; this runs 2,000."""

import re

import pytest
from fuzz_decks import fuzz, mutate

from orchestrator.engine.locate import find_engine

INPUTS = 2000


@pytest.fixture(scope="module")
def summary():
    return fuzz(str(find_engine()), INPUTS, seed=2026, workers=2)


def test_no_input_crashes_or_hangs_the_engine(summary):
    assert summary.inputs == INPUTS
    assert not summary.crashes and not summary.hangs, summary.line()


def test_every_rejection_names_its_line(summary):
    assert summary.codes[2] > INPUTS // 2 and not summary.unlocated, [o.message for o in summary.unlocated[:5]]


def test_no_input_ends_in_an_unexplained_failure(summary):
    """Exit 4 (e.g. a deck whose mutated *BOUNDARY leaves a rigid-body motion: singular tangent) must still say
    which deck and why."""
    unexplained = [o for o in summary.failures if not re.match(r"\S+\.inp: \S.{20,}", o.message)]
    assert not unexplained, [f"{o.mutation}: {o.message}" for o in unexplained[:5]]


def test_the_mutations_are_reproducible():
    import random

    text = "*NODE\n1, 0.0, 0.0\n2, 1.0, 0.0\n*ELEMENT, TYPE=CPE3, ELSET=E\n1, 1, 2, 3\n"
    assert [mutate(text, random.Random(f"7-{k}")) for k in range(50)] == \
        [mutate(text, random.Random(f"7-{k}")) for k in range(50)]
