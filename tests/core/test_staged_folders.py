"""core.files.staged_folders: folders replaced whole or left as they were."""

from pathlib import Path

import pytest

from orchestrator.core.files import staged_folders


def _contents(folder: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(folder.iterdir())}


def test_both_folders_replaced_and_nothing_left_beside_them(tmp_path):
    old = tmp_path / "case"
    old.mkdir()
    (old / "stale.txt").write_text("old")
    with staged_folders(tmp_path / "truth", old) as (truth, case):
        (truth / "truth.json").write_text("{}")
        (case / "case.toml").write_text("x")
    assert _contents(tmp_path / "truth") == {"truth.json": "{}"}
    assert _contents(old) == {"case.toml": "x"}           # the old folder's files are gone with it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case", "truth"]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_an_interrupted_block_leaves_the_old_folders_and_no_staging(tmp_path, error):
    old = tmp_path / "case"
    old.mkdir()
    (old / "case.toml").write_text("old")
    with pytest.raises(error):
        with staged_folders(old, tmp_path / "new" / "truth") as (case, truth):
            (case / "case.toml").write_text("half")
            raise error()
    assert _contents(old) == {"case.toml": "old"}
    assert not (tmp_path / "new" / "truth").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case", "new"]
    assert list((tmp_path / "new").iterdir()) == []
