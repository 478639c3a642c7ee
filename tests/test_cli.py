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
    (["eval", "eval.bogus=1"], "unknown config key 'eval.bogus'; valid keys under 'eval': episodes, save_episodes"),
    (["eval", "nope=1"], "unknown config key 'nope'"),
    (["eval", "env=mars"], "unknown env 'mars'; valid choices: replay"),
    (["eval", "policy=teleport"], "unknown policy 'teleport'; valid: orca, straight"),
    (["eval", "eval.episodes=0"], "eval.episodes must be a positive integer"),
    (["fly"], "unknown command 'fly'"),
    (["eval", "env.time_base=0.4"], "env.time_base=0.4 conflicts with protocol v1"),
])
def test_bad_input_one_line_error(args, message, capsys, tmp_path):
    assert main(args + [f"out={tmp_path}"] if args[0] == "eval" else args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "results.json").exists()
