"""The command line: a real evaluation run and one-line errors for bad input."""

import json

import pytest

from crowdbench.cli import main


def test_eval_straight_writes_results(tmp_path, capsys):
    rc = main(["eval", "policy=straight", "eval.scenes=[eth,hotel]", "eval.episodes=10", f"out={tmp_path}",
               "eval.save_episodes=true"])
    assert rc == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res["scenes"]) == {"eth", "hotel"} and res["policy"] == "straight"
    assert len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 20
    assert "success" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["eval", "eval.scenes=[mars]"], "unknown scene 'mars'; valid scenes: eth, hotel"),
    (["eval", "eval.bogus=1"], "unknown config key 'eval.bogus'; valid keys under 'eval': episodes, overwrite, save_episodes"),
    (["eval", "nope=1"], "unknown config key 'nope'"),
    (["eval", "env=mars"], "unknown env 'mars'; valid choices: crowdnav, replay, selfplay"),
    (["eval", "policy=teleport"], "unknown policy 'teleport'; valid: orca, straight"),
    (["eval", "eval.episodes=0"], "eval.episodes: must be >= 1 (got 0)"),
    (["fly"], "unknown command 'fly'"),
    (["eval", "env.time_base=0.4"], "env.time_base=0.4 conflicts with protocol v1"),
    (["eval", "seed=abc"], "seed: must be an integer in [0, 2**63) (got 'abc')"),
    (["eval", "env=selfplay", "seed=-3"], "seed: must be in [0, 2**63) (got -3)"),
    (["eval", "eval.scenes=[]"], "eval.scenes: must not be empty (got [])"),
    (["eval", "eval.scenes=[students001]"], "eval.scenes: students001 has no protocol episode list"),
    (["eval", "env.frame=polar"], "env.frame: must be one of rotate, translate, world (got 'polar')"),
    (["eval", "env.v_max=-1"], "env.v_max: must be > 0 (got -1)"),
])
def test_bad_input_one_line_error(args, message, capsys, tmp_path):
    assert main(args + [f"out={tmp_path}"] if args[0] == "eval" else args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "results.json").exists()


def test_orca_parameters_from_config(tmp_path):
    """A zero safety margin (the textbook ORCA) collides more than the tuned default on students003."""
    rates = {}
    for margin in (0.0, 0.2):
        out = tmp_path / str(margin)
        assert main(["eval", "policy=orca", "eval.scenes=[students003]", "eval.episodes=60",
                     f"orca.safety_margin={margin}", f"out={out}"]) == 0
        rates[margin] = json.loads((out / "results.json").read_text())["scenes"]["students003"]["collision_rate"]["mean"]
    assert rates[0.0] > rates[0.2]


def test_default_output_dirs_started_in_one_second_differ(tmp_path, monkeypatch):
    import time

    from omegaconf import OmegaConf

    from crowdbench.app import output_dir

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(time, "strftime", lambda fmt: "20261201-170205")
    cfg = OmegaConf.create({"out": None})
    first = output_dir(cfg, "run", "td3-gatedgcn")
    first.mkdir(parents=True)
    second = output_dir(cfg, "run", "td3-gatedgcn")
    assert first.name == "run-td3-gatedgcn-20261201-170205" and second.name == "run-td3-gatedgcn-20261201-170205-2"
