"""The tissues' labels and names, the same in every stage.

A label map (labels.png, a segmentation) holds 0 background, 1 fat (with the skin), 2 muscle, 3 bone and 4, 5, ...
muscle compartments, up to LAST_COMPARTMENT (a larger label means no tissue: 255 is a binary mask's foreground).
The mesh's element sets are FAT, MUSCLE and COMPARTMENT4, 5, ...; a material's constants are named by the tissue
in lower case (C10_fat, Kv_muscle). Places are always named by tissue, never by a label number.
"""

from __future__ import annotations

BACKGROUND, FAT, MUSCLE, BONE = 0, 1, 2, 3
FIRST_COMPARTMENT = 4
LAST_COMPARTMENT = 31
FAT_SET = "FAT"
MUSCLE_SET = "MUSCLE"
COMPARTMENT_PREFIX = "COMPARTMENT"


def tissue_of_label(label: int) -> str:
    """The tissue a label of a label map shows, in words: fat, muscle (a compartment too), bone or outside the leg."""
    if label == FAT:
        return "fat"
    if label == MUSCLE or label >= FIRST_COMPARTMENT:
        return "muscle"
    return "bone" if label == BONE else "outside the leg"


def element_set_of_label(label: int) -> str:
    """The mesh's element set of a soft tissue's label (1 fat, 2 muscle, >= 4 compartments)."""
    if label == FAT:
        return FAT_SET
    if label == MUSCLE:
        return MUSCLE_SET
    if label >= FIRST_COMPARTMENT:
        return f"{COMPARTMENT_PREFIX}{label}"
    raise ValueError(f"label {label} is not a soft tissue (1 fat, 2 muscle, >= 4 compartments)")


def parameter_tissue(element_set: str) -> str:
    """The tissue's name in a parameter's name (C10_fat, Kv_compartment4): the element set in lower case."""
    return element_set.lower()
