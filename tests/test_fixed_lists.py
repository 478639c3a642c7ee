"""Finding 13: protocol lists are checked against fixed hashes, not only against their own spec."""

from __future__ import annotations

import json

from crowdbench.cli import main
from crowdbench.envs import protocol
from crowdbench.leaderboard import run
from crowdbench.protocols import lists as fixed_lists


def _forge(tmp_path, monkeypatch):
    """hotel's v1 list regenerated, consistently, with another seed."""
    forged = protocol.generate_episodes("hotel", protocol.ProtocolSpec(seed=2027))
    (tmp_path / "hotel.json").write_text(json.dumps(forged, indent=1) + "\n")
    monkeypatch.setattr(protocol, "protocol_path", lambda s: tmp_path / f"{protocol.check_scene(s)}.json")
    return forged


def _straight_only(root):
    d = root / "submissions" / "straight"
    d.mkdir(parents=True)
    (d / "submission.yaml").write_text("name: straight\nkind: baseline\npolicy: straight\nauthors: [a]\n")
    return root


def test_the_shipped_lists_are_the_published_ones():
    for version, scenes in fixed_lists.REPLAY.items():
        fixed_lists.check_replay(version, list(scenes))
        assert sorted(scenes) == sorted(protocol.EVAL_SCENES)


def test_a_consistently_regenerated_list_is_refused_by_eval(tmp_path, monkeypatch, capsys):
    forged = _forge(tmp_path, monkeypatch)
    assert protocol.load_episodes("hotel") == forged  # its own spec accepts it: the hole this closes
    out = tmp_path / "out"
    assert main(["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=2", f"out={out}"]) == 2
    err = capsys.readouterr().err.strip()
    assert "hotel.json: sha256" in err and "is not protocol v1's published list" in err and "\n" not in err
    assert not (out / "results.json").exists()


def test_a_consistently_regenerated_list_is_refused_by_the_leaderboard(tmp_path, monkeypatch):
    (tmp_path / "lists").mkdir()
    _forge(tmp_path / "lists", monkeypatch)
    root = _straight_only(tmp_path / "lb")
    log: list[str] = []
    assert run(root, log=log.append, episodes=2, scenes=["hotel"], tracks=["v1"]) == 1
    assert any("is not protocol v1's published list" in m for m in log)
    assert not (root / "results").exists() and not (root / "README.md").exists()


def test_a_crowdnav_case_list_that_changed_rejects_the_track(tmp_path, monkeypatch):
    monkeypatch.setitem(fixed_lists.CROWDNAV, "circle_n5", "0" * 64)
    root = _straight_only(tmp_path / "lb")
    log: list[str] = []
    assert run(root, log=log.append, episodes=2, scenes=["hotel"], tracks=["crowdnav-circle5"]) == 1
    (line,) = [m for m in log if "error" in m]
    assert "CrowdNav setting circle_n5: case list digest" in line and "(track crowdnav-circle5)" in line
    assert not (root / "results" / "straight" / "crowdnav-circle5.json").exists()
