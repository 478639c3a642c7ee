"""Leaderboard tracks: every entry evaluated by the harness on every track it fits (a tiny episode subset),
the per-track and transfer tables, --check per track, the trained-on track checked against the checkpoint."""

from __future__ import annotations

import json
import re

import pytest
from test_leaderboard import MLP, add_straight, learned_yaml, toy_checkpoint, write_yaml

from crowdbench.leaderboard import run
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS, trained_track

TINY = {"episodes": 2, "scenes": ["hotel"]}
ENVS = {"v1": {"v_max": 1.0, "frame": "rotate"},
        "v2-orca": {"v_max": 1.0, "frame": "rotate", "humans": "reactive_replay", "reactive": {"model": "orca"}},
        "crowdnav-circle5": {"name": "crowdnav", "scenario": "circle", "n_humans": 5, "humans": "orca",
                             "robot_visible": False, "v_max": 1.0, "frame": "rotate"}}


def add_learned(root, name: str, trained: str, claimed: str | None = None):
    claim = claimed or trained
    d = write_yaml(root, name, learned_yaml(name, extra="" if claim == "v1" else f"track: {claim}\n"))
    toy_checkpoint(d / "checkpoint.pt", MLP, env=ENVS[trained])
    return d


def board(tmp_path):
    root = tmp_path / "lb"
    add_straight(root)
    write_yaml(root, "orca", "name: orca\nkind: baseline\nentry: ORCA\npolicy: orca\nauthors: [a]\n")
    write_yaml(root, "oracle", "name: oracle\nkind: oracle\nentry: Oracle (privileged)\nprivileged: true\n"
                               "authors: [a]\n")
    for name, track in (("toy_v1", "v1"), ("toy_v2", "v2-orca"), ("toy_cn", "crowdnav-circle5")):
        add_learned(root, name, track)
    return root


def test_trained_track_of_a_config():
    assert trained_track({"env": {"name": "replay"}}) == "v1"
    assert trained_track({"env": {}}) == "v1"  # checkpoints from before env.humans existed
    assert trained_track({"env": ENVS["v2-orca"]}) == "v2-orca"
    assert trained_track({"env": {"humans": "reactive_replay", "reactive": {"model": "sfm"}}}) == "v2-sfm"
    assert trained_track({"env": ENVS["crowdnav-circle5"]}) == "crowdnav-circle5"
    assert trained_track({"env": {**ENVS["crowdnav-circle5"], "n_humans": 10}}) is None
    assert trained_track({"env": {**ENVS["crowdnav-circle5"], "robot_visible": True}}) is None
    assert trained_track({"env": {"name": "selfplay"}}) == "selfplay"  # every self-play run: its tracks


@pytest.mark.slow
def test_every_track_evaluated_tabled_and_checked(tmp_path):
    root = board(tmp_path)
    log = []
    assert run(root, log=log.append, **TINY) == 0, log
    res = root / "results"
    for sub in ("straight", "orca", "toy_v1", "toy_v2", "toy_cn"):
        for t in TRACK_ORDER:  # robot entries are not evaluated on the self-play tracks
            fits = not t.startswith("selfplay-") or not sub.startswith("toy")
            assert (res / sub / TRACKS[t].results_file).is_file() == fits, (sub, t)
    assert sorted(p.name for p in (res / "oracle").glob("*.json")) == sorted(
        ["results.json", "unavoidable.json", "crowdnav-circle5.json", "crowdnav-circle20.json",
         "crowdnav-square5.json"])  # not on reactive replay: the humans' future depends on the robot
    r = json.loads((res / "orca" / "crowdnav-circle20.json").read_text())
    assert r["protocol"] == "crowdnav-v1" and list(r["scenes"]) == ["circle_n20"] and r["harness"]["track"] == \
        "crowdnav-circle20"
    assert len(r["episode_outcomes"]["circle_n20"]) == 2
    r = json.loads((res / "toy_v2" / "v2-sfm.json").read_text())
    assert r["protocol"] == "v2" and r["humans"] == "sfm" and "crowd_offset_max_m" in r["scenes"]["hotel"]
    # v1's table holds the baselines, the oracle and the v1-trained entry only
    readme = (root / "README.md").read_text()
    assert "toy_v1" in readme and "toy_v2" not in readme and "toy_cn" not in readme
    text = (root / "TRACKS.md").read_text()
    for t in TRACK_ORDER:
        assert f"<!-- generated:track-{t}:start -->" in text
    transfer = text.split("<!-- generated:transfer:start -->")[1].split("<!-- generated:transfer:end -->")[0]
    rows = [ln for ln in transfer.splitlines() if ln.startswith("| Toy MLP |")]
    assert len(rows) == 3  # one label, three training tracks: one row each
    log.clear()
    assert run(root, check=True, log=log.append, **TINY) == 0, log
    assert "matches" in log[-1]


@pytest.mark.slow
def test_transfer_rows_bold_their_home_track(tmp_path):
    root = tmp_path / "lb"
    add_straight(root)
    for name, track in (("toy_v1", "v1"), ("toy_v2", "v2-orca")):
        d = add_learned(root, name, track)
        y = d / "submission.yaml"
        y.write_text(y.read_text().replace("entry: Toy MLP", f"entry: Toy {track}"))
    assert run(root, log=lambda m: None, **TINY) == 0
    text = (root / "TRACKS.md").read_text()
    transfer = text.split("<!-- generated:transfer:start -->")[1]
    v1_row = next(ln for ln in transfer.splitlines() if ln.startswith("| Toy v1 "))
    v2_row = next(ln for ln in transfer.splitlines() if ln.startswith("| Toy v2-orca "))
    cells = lambda row: [c.strip() for c in row.strip("|").split("|")]
    assert cells(v1_row)[3].startswith("**") and not cells(v1_row)[4].startswith("**")
    assert cells(v2_row)[4].startswith("**") and not cells(v2_row)[3].startswith("**")
    # each track's table lists the entries trained on it, not the others
    v2_block = text.split("<!-- generated:track-v2-orca:start -->")[1].split("<!-- generated:track-v2-orca:end")[0]
    assert "Toy v2-orca" in v2_block and "Toy v1 " not in v2_block
    # a hand-edited cell of one track is named by --check of that track, the other tracks still pass
    edited = re.sub(r"(\| Toy v2-orca \| v2-orca \| 1 \| )\d\.\d{3}", r"\g<1>0.999", text, count=1)
    assert edited != text
    (root / "TRACKS.md").write_text(edited)
    log = []
    assert run(root, check=True, log=log.append, tracks=["v2-orca"], **TINY) == 1
    assert "TRACKS.md (track-v2-orca)" in log[-1]
    assert run(root, check=True, log=log.append, tracks=["v1", "crowdnav-square5"], **TINY) == 0, log[-1]


@pytest.mark.slow
def test_a_claimed_track_must_match_the_checkpoint(tmp_path):
    root = tmp_path / "lb"
    add_straight(root)
    add_learned(root, "liar", "v1", claimed="v2-sfm")
    log = []
    assert run(root, log=log.append, tracks=["v1"], **TINY) == 1
    assert any("field 'track': 'v2-sfm' but the checkpoint was trained on 'v1'" in m for m in log), log
    d = write_yaml(root, "bogus", learned_yaml("bogus", extra="track: mars\n"))
    toy_checkpoint(d / "checkpoint.pt", MLP)
    log.clear()
    run(root, log=log.append, tracks=["v1"], **TINY)
    assert any("field 'track': 'mars' is not a track; valid: v1, v2-orca" in m for m in log), log


def test_unknown_track_is_one_line(tmp_path):
    root = board(tmp_path)
    log = []
    assert run(root, log=log.append, tracks=["v3"], **TINY) == 1
    assert log == ["crowdbench leaderboard: error: unknown track(s) v3; valid: " + ", ".join(TRACK_ORDER)]


@pytest.mark.parametrize("track", ["v2-orca", "crowdnav-square5"])
def test_harness_numbers_equal_a_direct_evaluation(tmp_path, track):
    """The harness builds ORCA with the track's settings (CrowdNav's ORCA on CrowdNav) and gets the numbers
    of the evaluation functions called directly."""
    from crowdbench import policies
    from crowdbench.leaderboard.tracks import evaluate_track, track_config

    root = tmp_path / "lb"
    write_yaml(root, "orca", "name: orca\nkind: baseline\nentry: ORCA\npolicy: orca\nauthors: [a]\n")
    assert run(root, log=lambda m: None, tracks=[track], **TINY) == 0
    got = json.loads((root / "results" / "orca" / TRACKS[track].results_file).read_text())
    cfg = track_config(TRACKS[track])
    assert (cfg["orca"]["safety_margin"], cfg["env"]["robot_radius"]) == \
        ((0.02, 0.3) if track.startswith("crowdnav") else (0.2, 0.2))
    want = evaluate_track(TRACKS[track], policies.build("orca", cfg), TINY["scenes"], TINY["episodes"],
                          tmp_path / "direct", {})
    assert got["scenes"] == want["scenes"]


def test_tracks_page_is_rendered_from_the_committed_results():
    """leaderboard/TRACKS.md is what the harness renders from the committed results of every track (pure
    rendering); the oracle is on no reactive-replay table, every learned entry is in the transfer table."""
    from pathlib import Path

    from crowdbench.envs.protocol import EVAL_SCENES
    from crowdbench.leaderboard.board import unevaluated
    from crowdbench.leaderboard.track_tables import above_the_oracle, render_tracks

    repo = Path(__file__).resolve().parents[1] / "leaderboard"
    by_track = {t: [] for t in TRACK_ORDER}
    for d in sorted(p for p in (repo / "results").iterdir() if p.is_dir()):
        for t in TRACK_ORDER:
            if (d / TRACKS[t].results_file).is_file():
                by_track[t].append(json.loads((d / TRACKS[t].results_file).read_text()))
    text = (repo / "TRACKS.md").read_text()
    # every learned submission on every track it fits (privileged ones: not reactive replay), or listed
    # under "Not evaluated" with the command that evaluates it
    missing = unevaluated(repo, by_track)
    assert all(r["meta"]["kind"] != "learned" or r["privileged"] is not True or TRACKS[t].privileged_ok
               for t in TRACK_ORDER for r in by_track[t] if "privileged" in r)
    assert render_tracks(by_track, list(EVAL_SCENES), None, missing, []) == text
    assert not any(r["meta"]["kind"] == "oracle" for t in ("v2-orca", "v2-sfm") for r in by_track[t])
    # the oracle is the upper bound of every track where it is privileged: no learned row above it
    assert above_the_oracle(by_track) == []
    assert "| ORCA | — | 1 | 0.426 [0.383, 0.470] | 0.570" in text  # CrowdNav's Table I row (0.43 / 0.57)
