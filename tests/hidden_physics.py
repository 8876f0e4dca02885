"""Physics outside the catalog, written into a truth's deck directly: how a case is made whose residual no catalog
effect explains (`study.make_phantom_case(edit_deck=...)`)."""

from __future__ import annotations

from orchestrator.regions import display_angle_deg

OEDEMA_SECTOR_DEG = (210.0, 300.0)     # display angles (counter-clockwise, 90 at the top of the image)


def oedema(deck_text: str, mesh, dv: float = 0.15) -> str:
    """Swelling of the fat in one angular sector, brought in by the deck's last step (Laplace's law has one; the
    explicit band's last step is the one after the band is on the leg)."""
    centre = mesh.nodes[mesh.skin_loop].mean(axis=0)
    fat = mesh.element_sets()["FAT"]
    angle = display_angle_deg(mesh.nodes[mesh.elements[fat][:, :3]].mean(axis=1), centre)
    ids = fat[(angle > OEDEMA_SECTOR_DEG[0]) & (angle < OEDEMA_SECTOR_DEG[1])] + 1
    elset = "*ELSET, ELSET=OEDEMA\n" + "\n".join(", ".join(map(str, ids[k:k + 12])) for k in range(0, len(ids), 12))
    deck_text = deck_text.replace("*BOUNDARY\n", elset + "\n*BOUNDARY\n", 1)
    before, after = deck_text.rsplit("*NODE FILE", 1)
    return f"{before}*VOLUME CHANGE, ELSET=OEDEMA\n{dv}\n*NODE FILE{after}"
