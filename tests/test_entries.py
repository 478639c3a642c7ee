"""Who may share a row: H2 (a learned submission joined the straight-to-goal row, or ORCA's, by copying
its `entry`), M12 (lookalike labels: five rows that all read "Straight to goal"), L3 (names that
differ only by case)."""

from __future__ import annotations

from pathlib import Path

import pytest

from crowdbench.leaderboard import run
from crowdbench.leaderboard.entries import entry_problems
from crowdbench.leaderboard.render import group_results
from crowdbench.leaderboard.submission import SubmissionError, read_submission
from tests.test_isolation import add_straight

FAST = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}


def learned(root: Path, name: str, entry: str, encoder: str = "mlp", algo: str = "td3",
            experiment: str = "leaderboard", seed: int = 0) -> Path:
    d = root / "submissions" / name
    d.mkdir(parents=True)
    (d / "submission.yaml").write_text(
        f"name: {name}\nkind: learned\nentry: \"{entry}\"\nencoder: {encoder}\nalgo: {algo}\nseed: {seed}\n"
        f"experiment: {experiment}\noverrides: [experiment={experiment}, seed={seed}]\nauthors: [mallory]\n",
        encoding="utf-8")
    (d / "checkpoint.pt").write_bytes(b"never read: a refused submission gets no worker")
    return d


def add_orca(root: Path) -> None:
    d = root / "submissions" / "orca"
    d.mkdir(parents=True)
    (d / "submission.yaml").write_text("name: orca\nkind: baseline\nentry: ORCA\npolicy: orca\nauthors: [crowdbench]\n")


def problems(root: Path) -> dict[str, str]:
    subs = [read_submission(d) for d in sorted((root / "submissions").iterdir())]
    return {k: str(v) for k, v in entry_problems(subs).items()}


def test_a_learned_submission_cannot_join_a_baseline_row(tmp_path):
    """H2: `entry: Straight to goal` turned the row into `3 | 0.533 ± 0.462`; `0_orca_clone` with
    `entry: ORCA` moved ORCA into the learned section. Both are refused in one line; the rows stay."""
    clean = tmp_path / "clean"
    add_straight(clean)
    add_orca(clean)
    assert run(clean, log=lambda m: None, **FAST) == 0
    root = tmp_path / "spoof"
    add_straight(root)
    add_orca(root)
    learned(root, "a_spoof", "Straight to goal")
    learned(root, "0_orca_clone", "ORCA")
    log: list[str] = []
    assert run(root, log=log.append, **FAST) == 1
    errors = [m for m in log if "error" in m]
    assert len(errors) == 2 and all("field 'entry'" in m and "\n" not in m for m in errors), errors
    assert any("a_spoof" in m and "baseline 'straight'" in m for m in errors)
    assert any("0_orca_clone" in m and "baseline 'orca'" in m for m in errors)
    for name in ("straight", "orca"):
        assert (root / "results" / name / "results.json").read_bytes() == \
            (clean / "results" / name / "results.json").read_bytes()
    readme = (root / "README.md").read_text()
    table = readme.split("## Rejected")[0]
    assert table.count("Straight to goal") == (clean / "README.md").read_text().split("## Rejected")[0].count(
        "Straight to goal")
    assert "a\\_spoof" not in table and "a_spoof" not in table


@pytest.mark.parametrize("label", ["Straight\u200b to goal", "\u200fStraight to goal\u200e", "Straight to go\u00adal",
                                   "Straight t\u043e goal", "straight to goal", "Ｓtraight to goal"])
def test_lookalike_labels_are_refused(tmp_path, label):
    """M12: zero-width space, direction marks, soft hyphen (Unicode Cf: refused by the schema), a
    Cyrillic о, another case or a full-width letter (the same label after normalisation)."""
    add_straight(tmp_path)
    learned(tmp_path, "look", label)
    try:
        found = problems(tmp_path)
    except SubmissionError as e:
        assert e.field == "entry" and "invisible or direction characters" in str(e)
        return
    assert list(found) == ["look"] and "field 'entry'" in found["look"], found


def test_seeds_share_an_entry_only_with_one_recipe(tmp_path):
    learned(tmp_path, "m_s0", "My method")
    learned(tmp_path, "m_s1", "My method", seed=1)
    learned(tmp_path, "m_s2", "My method", seed=2)
    assert problems(tmp_path) == {}
    learned(tmp_path, "0_enc", "My method", encoder="gcn")  # sorts first: still not the row's owner
    learned(tmp_path, "x_algo", "My method", algo="sac")
    learned(tmp_path, "y_recipe", "My method", experiment="reactive")
    learned(tmp_path, "z_look", "My  m\u0435thod")  # Cyrillic е, same recipe: a lookalike of the label
    found = problems(tmp_path)
    assert sorted(found) == ["0_enc", "x_algo", "y_recipe", "z_look"], found
    assert "encoder 'mlp'" in found["0_enc"] and "encoder 'gcn'" in found["0_enc"]
    assert "looks like 'My method'" in found["z_look"]


def test_one_label_on_two_tracks_is_two_rows_not_a_conflict(tmp_path):
    """The committed leaderboard shares `MP-GatedGCN-RL (TD3, gatedgcn)` across tracks with a different
    recipe on each: each track's table is its own."""
    learned(tmp_path, "g_v1", "G")
    d = learned(tmp_path, "g_reactive", "G", experiment="reactive")
    (d / "submission.yaml").write_text((d / "submission.yaml").read_text() + "track: v2-orca\n")
    assert problems(tmp_path) == {}


def test_names_differing_only_by_case_are_refused(tmp_path):
    """L3: `Straight/` and `straight/` were both evaluated; they collide on case-insensitive checkouts."""
    add_straight(tmp_path)
    d = tmp_path / "submissions" / "Straight"
    d.mkdir()
    (d / "submission.yaml").write_text("name: Straight\nkind: baseline\nentry: Other\npolicy: straight\n"
                                       "authors: [x]\n")
    found = problems(tmp_path)
    assert list(found) == ["straight"] and "only by case" in found["straight"], found


def test_cached_results_of_two_kinds_never_share_a_row():
    """Whatever the results on disk say, a baseline's row and a learned one are grouped apart."""
    res = [{"meta": {"submission": s, "kind": k, "entry": "ORCA"}} for s, k in (("0_clone", "learned"),
                                                                                  ("orca", "baseline"))]
    groups = group_results(res)
    assert [[r["meta"]["kind"] for r in g] for g in groups] == [["baseline"], ["learned"]]
