"""The self-play leaderboard tracks: published lists regenerated against their hashes, the scaled geometry
of 32 agents, which entries the tracks take, a submission evaluated in its worker equal to `crowdbench eval`,
and the track table rendered from hand-made results."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import pytest
import torch
from test_leaderboard import learned_yaml, write_yaml

from crowdbench.algos.actors import build_actor
from crowdbench.algos.checkpoint import save_checkpoint
from crowdbench.cli import main
from crowdbench.envs.selfplay import SelfPlayConfig
from crowdbench.leaderboard import run
from crowdbench.leaderboard.track_tables import render_tracks, track_table
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS, trained_track
from crowdbench.protocols import lists
from crowdbench.protocols.selfplay_tracks import SETTINGS, generate, list_path, setting_overrides, track_name

SP_TRACKS = [track_name(s) for s, _ in SETTINGS]
GCN = {"name": "gatedgcn", "dim": 8, "layers": 1}


def _sha(data: dict) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@pytest.mark.parametrize("setting", [pytest.param(s, marks=pytest.mark.slow) if s == "square_n32" else s
                                     for s, _ in SETTINGS])
def test_a_list_regenerated_is_the_published_one(setting):
    """Drawn again from the seed, each list hashes to its published sha256, and so does the shipped file."""
    assert _sha(generate(setting)) == lists.SELFPLAY[setting]
    assert lists.canonical_sha(list_path(setting)) == lists.SELFPLAY[setting]


def test_every_track_has_a_published_list():
    assert sorted(lists.SELFPLAY) == sorted(TRACKS[t].setting for t in SP_TRACKS)
    assert SP_TRACKS == [t for t in TRACK_ORDER if t.startswith("selfplay-")]


def test_an_edited_list_stops_the_leaderboard(tmp_path, monkeypatch):
    monkeypatch.setitem(lists.SELFPLAY, "circle_n4", "0" * 64)
    root = tmp_path / "lb"
    write_yaml(root, "straight", "name: straight\nkind: baseline\npolicy: straight\nauthors: [a]\n")
    log: list[str] = []
    assert run(root, log=log.append, episodes=2, tracks=["selfplay-circle4"]) == 1
    (line,) = [m for m in log if "error" in m]
    assert "circle_n4.json: sha256" in line and "is not the published self-play list of circle_n4" in line


def test_32_agents_are_placed_on_a_square_scaled_to_fit():
    with pytest.raises(ValueError, match="env.scale_geometry=true"):
        SelfPlayConfig(n_agents=32, scenario="square")
    cfg = SelfPlayConfig(n_agents=32, scenario="square", scale_geometry=True)
    assert (cfg.square_width, cfg.time_limit) == (12.8, 160)  # the same 25 s per 8 m of side
    assert replace(cfg, jitter=0.0).square_width == 12.8  # not scaled twice
    assert SelfPlayConfig(n_agents=16, scenario="square", scale_geometry=True).square_width == 8.0  # fits as it is
    assert SelfPlayConfig(n_agents=32, scale_geometry=True).square_width == 8.0  # a circle of 32 fits
    assert json.loads(list_path("square_n32").read_text())["geometry"]["time_limit"] == 160


def test_which_entries_a_self_play_track_takes():
    for name in SP_TRACKS:
        t = TRACKS[name]
        assert t.fits("baseline") and not t.fits("oracle", True)
        assert t.fits("learned", False, "selfplay") and t.is_home("selfplay")
        # robot entries are not evaluated on it (docs/selfplay.md, "Leaderboard tracks")
        assert not any(t.fits("learned", False, o) for o in ("v1", "v2-orca", "crowdnav-circle5"))
    # a self-play entry is a robot policy: it is evaluated on the robot tracks too, as transfer
    assert all(TRACKS[t].fits("learned", False, "selfplay") and not TRACKS[t].is_home("selfplay")
               for t in TRACK_ORDER if t not in SP_TRACKS)
    assert trained_track({"env": {"name": "selfplay", "scenario": "mixed", "n_agents": 12}}) == "selfplay"


def test_a_v1_entry_is_not_listed_as_missing_on_self_play_tracks(tmp_path):
    from crowdbench.leaderboard.board import unevaluated

    write_yaml(tmp_path, "toy", learned_yaml("toy"))
    write_yaml(tmp_path, "sp", learned_yaml("sp", extra="track: selfplay\n"))
    missing = unevaluated(tmp_path, {}, SP_TRACKS)
    assert len(missing) == len(SP_TRACKS) and all(m.startswith("sp (selfplay-") for m in missing)


def _selfplay_submission(root, name="sp_toy"):
    torch.manual_seed(0)
    d = write_yaml(root, name, learned_yaml(name, encoder="gatedgcn", extra="track: selfplay\n")
                   .replace("Toy MLP", "Toy self-play"))
    actor = build_actor("td3", dict(GCN), 1.0, squash="radial")
    cfg = {"algo": {"name": "td3", "actor_squash": "radial"}, "encoder": dict(GCN),
           "env": {"name": "selfplay", "scenario": "mixed", "n_agents": 4, "v_max": 1.0, "frame": "rotate"}}
    save_checkpoint(d / "checkpoint.pt", {"config": cfg, "actor": actor.state_dict(), "frames": 0})
    return d


def test_a_submission_in_its_worker_equals_crowdbench_eval(tmp_path):
    """The harness (worker process, all agents of the batch in one call per step) and `crowdbench eval
    env=selfplay` with the track's overrides: the same per-agent and per-episode numbers."""
    root = tmp_path / "lb"
    d = _selfplay_submission(root)
    log: list[str] = []
    assert run(root, log=log.append, tracks=["selfplay-circle4"]) == 0, log
    got = json.loads((root / "results" / "sp_toy" / "selfplay-circle4.json").read_text())
    assert len(got["episode_outcomes"]["circle_n4"]) == 100 and got["lists"] == {"circle_n4": lists.SELFPLAY["circle_n4"]}
    assert main(["eval", *setting_overrides("circle_n4"), f"policy={d / 'checkpoint.pt'}", f"out={tmp_path / 'ev'}"]) == 0
    want = json.loads((tmp_path / "ev" / "results.json").read_text())["settings"]["circle_n4"]
    want = {**{k: v for k, v in want.items() if k != "episode"}, **want["episode"]}
    assert got["scenes"]["circle_n4"] == want


def _result(entry: str, kind: str, success: float, n_ok: int, track: str | None, sub: str) -> dict:
    rate = lambda m: {"mean": m, "ci95": [max(m - 0.05, 0.0), min(m + 0.02, 1.0)], "n": 400}
    mean = lambda m: {"mean": m, "ci95": [m - 0.1, m + 0.1], "n": 400, "sd": 1.0}
    scene = {"success_rate": rate(success), "collision_rate": rate(1 - success), "timeout_rate": rate(0.0),
             "nav_time_s": mean(8.5), "agent_dangers_per_agent": mean(2.0), "dangers_per_agent": mean(2.0),
             "min_agent_clearance": mean(0.1), "all_arrived_rate": rate(n_ok / 100), "any_collision_rate": rate(0.1),
             "episode_time_s": mean(9.0)}
    data = {"name": sub, "kind": kind, "entry": entry, "authors": ["a"]} | ({"track": track} if track else {})
    return {"protocol": "selfplay-v1", "meta": {"submission": sub, "kind": kind, "entry": entry},
            "scenes": {"circle_n4": scene}, "submission": data}


def test_the_track_table_rendered_from_hand_made_results():
    track = TRACKS["selfplay-circle4"]
    results = [_result("ORCA", "baseline", 0.98, 98, None, "orca"),
               _result("Self-play TD3", "learned", 0.995, 99, "selfplay", "sp_s0"),
               _result("Robot TD3", "learned", 1.0, 100, "v1", "robot")]  # trained on v1: not on this table
    lines = track_table(track, results, [])
    head = next(ln for ln in lines if ln.startswith("| # |"))
    assert head.split(" | ")[4:] == ["success", "collision", "timeout", "nav time s", "agent dangers", "dangers",
                                     "min agent clearance m", "all arrived", "any collision", "episode s |"]
    rows = [ln for ln in lines if ln.startswith(("| 1 |", "| 2 |"))]
    assert rows[0].startswith("| 1 | Self-play TD3 | selfplay | 1 | 0.995 [0.945, 1.000] | 0.005 [0.000, 0.025] |")
    assert rows[1].startswith("| 2 | ORCA | — | 1 | 0.980 [0.930, 1.000] |") and "| 0.980 [0.930, 1.000] |" in rows[1]
    assert not any("Robot TD3" in ln for ln in lines)
    assert "published list circle_n4" in "\n".join(lines) and "![selfplay-circle4, ranked]" in "\n".join(lines)
    text = render_tracks({"selfplay-circle4": results}, [], None, [], [])
    assert "<!-- generated:track-selfplay-circle4:start -->" in text and "generated:transfer" not in text


def test_the_docs_selfplay_table_is_the_leaderboards(monkeypatch):
    """docs/selfplay.md's track table is what benchmarks/selfplay_table.py makes of the committed TRACKS.md:
    one row per self-play track, ORCA and every entry trained in self-play, best learned minus ORCA."""
    import importlib
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    monkeypatch.syspath_prepend(str(root / "benchmarks"))  # the scripts import each other by their file names
    table = importlib.import_module("selfplay_table")
    text = (root / "leaderboard" / "TRACKS.md").read_text()
    lines = table.selfplay_table(text)
    assert [ln.split(" | ")[0] for ln in lines[4:]] == [f"| `{track_name(s)}`" for s, _ in SETTINGS]
    circle4 = table.track_rows(text, "selfplay-circle4")
    best = max(table.success(r) for r in circle4.values() if r["trained on"] == "selfplay")
    assert lines[4].split(" | ")[1] == circle4["ORCA"]["success"]
    assert f"| {best - table.success(circle4['ORCA']):+.3f} |" in lines[4]
    doc = (root / "docs" / "selfplay.md").read_text()
    assert doc == table.replace_block(doc, "selfplay-tracks", lines), \
        "docs/selfplay.md: run python benchmarks/selfplay_table.py --write docs/selfplay.md"
