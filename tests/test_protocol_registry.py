"""The protocol registry (crowdbench/protocols/): a protocol registered from here runs through
``crowdbench eval``, the training probe and the leaderboard's harness with no other file edited; unknown
names are one-line errors naming the valid ones; no module outside the package asks which protocol it has."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest
import torch
from test_leaderboard import add_straight

from crowdbench import protocols
from crowdbench.algos.actors import build_actor
from crowdbench.app import make_probe
from crowdbench.cli import compose, main
from crowdbench.envs.factory import WORLDS
from crowdbench.leaderboard import run
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS, trained_track
from crowdbench.protocols import ProtocolError, Track
from crowdbench.protocols.replay import ReplayProtocol

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "crowdbench"


class HotelReplay(ReplayProtocol):
    """Protocol v1 restricted to one scene, with its own track, table title and probe keys."""

    name = "replay_hotel"
    scenes = ("hotel",)
    tracks = (Track("v1-hotel", "Replay (protocol v1) on hotel only", "replay_hotel"),)

    def selects(self, env_cfg) -> bool:
        return False  # only by name: +env.protocol=replay_hotel

    def format_table(self, results: dict) -> str:
        return "hotel-only replay\n" + super().format_table(results)

    def probe(self, cfg):
        inner = super().probe(cfg)
        return lambda actor: {f"hotel_only_{k}": v for k, v in inner(actor).items()}


@pytest.fixture
def hotel():
    with protocols.registered(HotelReplay()) as p:
        yield p
    assert "replay_hotel" not in protocols.names() and "v1-hotel" not in TRACKS


EVAL = ["policy=straight", "+env.protocol=replay_hotel", "eval.scenes=[hotel]", "eval.episodes=3"]


def test_a_registered_protocol_runs_through_crowdbench_eval(hotel, tmp_path, capsys):
    assert main(["eval", *EVAL, f"out={tmp_path / 'mine'}"]) == 0
    assert capsys.readouterr().out.startswith("hotel-only replay\n")  # its table, not protocol v1's
    mine = json.loads((tmp_path / "mine" / "results.json").read_text())
    assert main(["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=3", f"out={tmp_path / 'v1'}"]) == 0
    v1 = json.loads((tmp_path / "v1" / "results.json").read_text())
    assert mine["scenes"] == v1["scenes"] and mine["protocol"] == "v1"  # the same episodes and loop
    capsys.readouterr()
    # its scenes are its own: eth has a v1 list, not one of this protocol
    assert main(["eval", *EVAL[:2], "eval.scenes=[eth]", f"out={tmp_path / 'eth'}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "eth has no protocol episode list" in err and "evaluation scenes: hotel" in err


def test_a_registered_protocol_gives_the_training_probe(hotel):
    torch.manual_seed(0)
    actor = build_actor("td3", {"name": "mlp", "dim": 8, "hidden": [16], "max_humans": 40}, 1.0, squash="radial")
    probe = ["train.probe_scene=hotel", "train.probe_episodes=3"]
    mine = make_probe(compose(["+env.protocol=replay_hotel", *probe]))(actor)
    v1 = make_probe(compose(probe))(actor)
    assert set(mine) == {"hotel_only_probe_hotel_success", "hotel_only_probe_hotel_collision"}
    assert mine == {f"hotel_only_{k}": v for k, v in v1.items()}


def test_a_registered_protocol_is_a_leaderboard_track(hotel, tmp_path):
    assert list(TRACK_ORDER)[-1] == "v1-hotel" and TRACKS["v1-hotel"].label == "v1"
    root = tmp_path / "lb"
    add_straight(root)
    log: list[str] = []
    assert run(root, tracks=["v1-hotel"], episodes=3, scenes=["hotel"], log=log.append) == 0, log
    res = json.loads((root / "results" / "straight" / "v1-hotel.json").read_text())
    assert res["harness"]["track"] == "v1-hotel" and len(res["episode_outcomes"]["hotel"]) == 3
    assert main(["eval", *EVAL, f"out={tmp_path / 'e'}"]) == 0  # the harness's numbers are crowdbench eval's
    assert res["scenes"] == json.loads((tmp_path / "e" / "results.json").read_text())["scenes"]
    board = (root / "TRACKS.md").read_text()
    assert "Replay (protocol v1) on hotel only" in board and "straight" in board.split("on hotel only")[1]
    assert run(root, check=True, tracks=["v1-hotel"], episodes=3, scenes=["hotel"], log=log.append) == 0, log


def test_unknown_names_are_one_line_errors_naming_the_valid_ones(tmp_path, capsys):
    with pytest.raises(ProtocolError) as e:
        protocols.get("nope")
    assert str(e.value) == "unknown protocol 'nope'; valid: replay, reactive_replay, crowdnav, selfplay"
    assert main(["eval", "policy=straight", "+env.protocol=nope", f"out={tmp_path}"]) == 2
    err = capsys.readouterr().err
    assert err == "crowdbench: error: unknown protocol 'nope'; valid: replay, reactive_replay, crowdnav, selfplay\n"
    assert main(["eval", "policy=straight", "+env.protocol=crowdnav", f"out={tmp_path}"]) == 2  # env=replay's world
    assert capsys.readouterr().err == "crowdbench: error: env.protocol=crowdnav runs in env.name=crowdnav, not replay\n"
    with pytest.raises(ProtocolError, match="'replay' is empty or taken"):
        protocols.register(HotelReplay.__base__())


def test_every_builtin_protocol_round_trips_through_the_registry():
    configs = {"replay": [], "reactive_replay": ["env.humans=reactive_replay"], "crowdnav": ["env=crowdnav"],
               "selfplay": ["env=selfplay"]}
    assert protocols.names() == list(configs)
    for name, overrides in configs.items():
        p = protocols.get(name)
        assert p.name == name and p.world in WORLDS
        assert protocols.of_config(compose(overrides).env) is p
        assert protocols.of_config(compose([*overrides, f"+env.protocol={name}"]).env) is p
        for track in p.tracks:
            assert TRACKS[track.name] is track and track.evaluator is p
            env = compose(list(track.config_overrides)).env  # the baselines' config of the track is the track's
            # (a protocol with a home, self-play: every run trained in it is at home on all its tracks)
            assert protocols.of_config(env) is p and trained_track({"env": dict(env)}) == (p.home or track.name)
            assert track.is_home(trained_track({"env": dict(env)}))
    assert list(TRACK_ORDER) == ["v1", "v2-orca", "v2-sfm", "crowdnav-circle5", "crowdnav-circle20", "crowdnav-square5",
                                 *(f"selfplay-{s}{n}" for s in ("circle", "square") for n in (4, 8, 16, 32)),
                                 "selfplay-circle8-orca4"]


# an env name compared or used as a key: env_name(...) ==, .name == "replay", {"selfplay": ...}, is_selfplay
WORLD = r"(replay|reactive_replay|selfplay|crowdnav)"
DISPATCH = re.compile(rf"env_name\([^)]*\)\s*[!=]=|is_selfplay|\bname\s*[!=]=\s*\"{WORLD}\"|\"{WORLD}\":\s*run_")
# what may still name a world outside the package: an algorithm that needs CrowdNav's reward (value), the
# single-robot Gymnasium API refusing self-play, a checkpoint format upgrade of replay configs
ALLOWED = {"algos/value_train.py", "envs/registry.py", "algos/checkpoint.py"}


def test_no_module_outside_the_protocols_dispatches_on_the_env_name():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel.startswith("protocols/") or rel in ALLOWED:
            continue
        found += [f"{rel}:{i}: {line.strip()}" for i, line in enumerate(path.read_text().splitlines(), 1)
                  if DISPATCH.search(line)]
    assert not found, "\n".join(found)
    assert "crowdbench.protocols" not in {n.module for n in ast.walk(ast.parse((PACKAGE / "envs" / "factory.py")
                                                                                .read_text()))
                                          if isinstance(n, ast.ImportFrom)}


def test_the_files_that_add_a_protocol_are_listed_and_exist():
    """docs/architecture.md's "How to add a protocol" names files that exist, the module and the registration."""
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text.split("## How to add a protocol", 1)[1].split("\n## ", 1)[0]
    named = set(re.findall(r"`((?:crowdbench|tests|docs)/[\w/.]+\.(?:py|md))`", section))
    assert {"crowdbench/protocols/__init__.py", "crowdbench/metric_table.py", "tests/test_layers.py"} <= named
    assert all((REPO / f).is_file() for f in named), sorted(f for f in named if not (REPO / f).is_file())
