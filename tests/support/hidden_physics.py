"""Hidden physics in a phantom case and what its diagnosis must show: physics outside the catalog, written into a
truth's deck directly (how a case is made whose residual no catalog effect explains,
`study.make_phantom_case(edit_deck=...)`), and the checks of a diagnosis of a hidden catalog effect or of none."""

from __future__ import annotations

from orchestrator.model.regions import display_angle_deg

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


def identified_and_diagnosed(case, run, label: str, model_tables: str = "") -> dict:
    """`calfit identify` from the images (the case's [model] tables appended first) then `calfit diagnose`; the
    ranking, the refits and the verdict printed under `label`."""
    from orchestrator.run.stages import run_diagnose, run_identify

    if model_tables:
        with open(case / "case.toml", "a") as toml:
            toml.write(model_tables)
    identified = run_identify(case, run, workers=2, progress=False)
    assert identified["data"]["source"] == "dic"
    diagnosis = run_diagnose(run, workers=2, progress=False)
    print(label, f"{diagnosis['before']['misfit_over_floor']:.2f} x floor;",
          [(s["effect"], round(s["statistic"], 1), f"{s['p_value']:.1e}") for s in diagnosis["ranking"][:5]],
          [(f["effects"], round(f["misfit_over_floor"], 3),
            f["own_floor"] and round(f["own_floor"]["misfit_over_floor"], 3)) for f in diagnosis["refits"]],
          f"{diagnosis['engine_runs']} runs;", diagnosis["verdict"])
    return diagnosis


def assert_found_or_nothing(name: str, diagnosis: dict) -> None:
    """A control shows nothing significant at about 1 x the floor; a hidden effect lacks fit clearly, is ranked
    first, significant, and its refit reaches 1.2 x the floor."""
    if name == "control":
        assert not any(score["significant"] for score in diagnosis["ranking"]), diagnosis["verdict"]
        assert 0.8 < diagnosis["misfit"] / diagnosis["noise_floor"] < 1.2
        return
    assert diagnosis["lack_of_fit_p"] < 1e-6
    best = diagnosis["ranking"][0]
    assert best["effect"] == name and best["significant"], diagnosis["verdict"]
    refitted = next(fit for fit in diagnosis["refits"] if fit["effects"] == [name])
    # against the floor with the skin's uncertainty at the refit's parameters, when the images estimated it
    ratio = (refitted["own_floor"] or refitted)["misfit_over_floor"]
    assert ratio <= 1.2 and diagnosis["explained"], diagnosis["verdict"]
