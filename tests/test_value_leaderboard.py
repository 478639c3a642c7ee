"""Value-lookahead entries on the leaderboard: a `query` entry reads the simulator's next human states, so
it must say `privileged: true`, is evaluated only where that knowledge exists (not on reactive replay),
is labelled privileged in every table, and its worker cannot act with another lookahead than it declares."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from crowdbench.algos.checkpoint import save_checkpoint
from crowdbench.algos.value import ValueModel
from crowdbench.cli import compose
from crowdbench.leaderboard import run
from crowdbench.leaderboard.submission import SubmissionError, make_submission, read_submission
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS
from tests.test_entries import add_orca


def value_checkpoint(path: Path, lookahead: str, net: str = "cadrl") -> dict:
    cfg = OmegaConf.to_container(compose(["env=crowdnav", "algo=value", f"algo.net={net}",
                                          f"algo.lookahead={lookahead}"]), resolve=True)
    model = ValueModel(OmegaConf.create(cfg["algo"]), OmegaConf.create(cfg["env"]), cfg["encoder"])
    save_checkpoint(path, {"config": cfg, "actor": model.net.state_dict(), "frames": 0})
    return cfg


def value_entry(root: Path, name: str, lookahead: str, trained: str = "query", extra: str = "",
                net: str = "cadrl", entry: str = "CADRL") -> Path:
    """A value submission whose checkpoint acts with ``trained`` (and CADRL's network); its yaml says
    ``lookahead`` and ``net`` (+ ``extra``)."""
    d = root / "submissions" / name
    d.mkdir(parents=True)
    cfg = value_checkpoint(d / "checkpoint.pt", trained)
    priv = "privileged: true\n" if lookahead == "query" else ""
    (d / "submission.yaml").write_text(
        f"name: {name}\nkind: learned\nentry: {entry} (value, {lookahead})\nencoder: {cfg['encoder']['name']}\n"
        f"algo: value\nlookahead: {lookahead}\nnet: {net}\n{priv}track: crowdnav-circle5\nauthors: [t]\n{extra}")
    return d


@pytest.mark.parametrize("yaml_text, field", [
    ("algo: value\nnet: sarl\n", "lookahead"),                                  # a value entry names its model
    ("algo: value\nnet: sarl\nlookahead: query\n", "privileged"),               # query reads the simulator
    ("algo: value\nnet: sarl\nlookahead: cv\nprivileged: true\n", "privileged"),  # cv knows nothing hidden
    ("algo: value\nnet: sarl\nlookahead: oracle\nprivileged: true\n", "lookahead"),
    ("algo: td3\nlookahead: cv\n", "lookahead"),                     # only value entries act by lookahead
    ("algo: td3\nprivileged: true\n", "privileged"),
    ("algo: value\nlookahead: cv\n", "net"),                          # a value entry names its network
    ("algo: value\nlookahead: cv\nnet: transformer\n", "net"),
    ("algo: td3\nnet: sarl\n", "net"),                               # only value entries have one
])
def test_privilege_must_be_declared_exactly(tmp_path, yaml_text, field):
    d = tmp_path / "x"
    d.mkdir()
    (d / "checkpoint.pt").write_bytes(b"unread")
    (d / "submission.yaml").write_text(f"name: x\nkind: learned\nencoder: mlp\nauthors: [t]\n{yaml_text}")
    with pytest.raises(SubmissionError) as e:
        read_submission(d)
    assert e.value.field == field


def test_privileged_entries_fit_only_tracks_whose_humans_ignore_the_robot():
    fits = {t: TRACKS[t].fits("learned", privileged=True) for t in TRACK_ORDER}
    assert fits == {t: TRACKS[t].fits("oracle") for t in TRACK_ORDER}
    assert not fits["v2-orca"] and not fits["v2-sfm"] and fits["v1"] and fits["crowdnav-circle5"]
    robot = [t for t in TRACK_ORDER if TRACKS[t].evaluator.name != "selfplay"]
    assert all(TRACKS[t].fits("learned") for t in robot)  # cv and actor entries: every robot track
    # the self-play tracks take the entries trained in self-play, not the robot's (docs/selfplay.md)
    assert not any(TRACKS[t].fits("learned", trained_on="crowdnav-circle5") for t in TRACK_ORDER if t not in robot)


def test_make_submission_declares_the_lookahead_and_its_privilege(tmp_path):
    for look in ("query", "cv"):
        run_dir = tmp_path / f"run_{look}"
        run_dir.mkdir()
        value_checkpoint(run_dir / "checkpoint.pt", look)
        sub = make_submission(run_dir, f"cadrl_value_{look}_s0", "CADRL (value)", ["t"], [], root=tmp_path / "lb")
        data = yaml.safe_load((sub / "submission.yaml").read_text())
        assert data["algo"] == "value" and data["lookahead"] == look and data["net"] == "cadrl"
        assert data.get("privileged", False) is (look == "query")
        assert data["track"] == "crowdnav-circle5"


@pytest.mark.slow
def test_a_query_entry_is_evaluated_privileged_and_labelled_so(tmp_path):
    """Through the harness and its worker on CrowdNav circle 5: results marked privileged, the row labelled
    so in the track table; a worker whose checkpoint acts with another model than its yaml is refused."""
    root = tmp_path / "lb"
    add_orca(root)
    value_entry(root, "q", "query")
    value_entry(root, "c", "cv", trained="cv")
    value_entry(root, "liar", "cv", trained="query")  # says cv, acts with the simulator's next states
    value_entry(root, "sarl_liar", "cv", trained="cv", net="sarl", entry="SARL")  # says SARL, is CADRL
    logs: list[str] = []
    code = run(root, episodes=3, tracks=["crowdnav-circle5"], log=logs.append)
    assert code == 1  # the liars are refused
    res = json.loads((root / "results" / "q" / "crowdnav-circle5.json").read_text())
    assert res["privileged"] is True and res["lookahead"] == "query"
    cv = json.loads((root / "results" / "c" / "crowdnav-circle5.json").read_text())
    assert "privileged" not in cv and cv["lookahead"] == "cv"
    assert not (root / "results" / "liar").exists()
    assert any("liar" in line and "lookahead" in line for line in logs), logs
    assert any("sarl_liar" in line and "net" in line and "'cadrl'" in line for line in logs), logs
    board = (root / "TRACKS.md").read_text()
    assert "CADRL (value, query) (PRIVILEGED)" in board and "CADRL (value, cv) (PRIVILEGED)" not in board


def test_the_submissions_tables_name_the_value_network_that_acts():
    """SARL's rows read `encoder gatedgcn` (the config's unused default); a value entry names its network,
    and `net: encoder` is the encoder with a value head."""
    from crowdbench.leaderboard.entries import model_of

    assert model_of({"encoder": "gatedgcn", "algo": "value", "net": "sarl"}) == "sarl"
    assert model_of({"encoder": "gatedgcn", "algo": "value", "net": "encoder"}) == "gatedgcn"
    assert model_of({"encoder": "rgl", "algo": "td3"}) == "rgl"
    assert model_of({"policy": "orca"}) == "orca"


def test_a_row_above_the_privileged_oracle_is_reported():
    """The oracle claims the task's upper bound where it is privileged: a learned row above it there is named;
    on reactive replay (no oracle) nothing is compared."""
    from crowdbench.leaderboard.track_tables import above_the_oracle

    def result(kind, entry, success, track="crowdnav-circle5", privileged=False):
        r = {"meta": {"kind": kind, "entry": entry, "submission": f"{entry}_{success}"},
             "scenes": {"circle_n5": {"success_rate": {"mean": success, "ci95": [success, success]}}},
             "submission": {"track": track}}
        return {**r, "privileged": True} if privileged or kind == "oracle" else r

    board = {"crowdnav-circle5": [result("oracle", "Oracle", 0.874), result("learned", "SARL", 0.99, privileged=True),
                                  result("learned", "SARL", 0.98, privileged=True), result("learned", "TD3", 0.8)]}
    assert above_the_oracle(board) == ["crowdnav-circle5: SARL (PRIVILEGED) 0.985 > the oracle's 0.874"]
    board["crowdnav-circle5"][0]["scenes"]["circle_n5"]["success_rate"]["mean"] = 1.0
    assert above_the_oracle(board) == []


def test_a_value_runs_recorded_recipe_keeps_its_rl_budget():
    """`crowdbench submit` records the overrides that made a run: algo=value's max_minutes is the length of
    its deep V-learning (part of the recipe); a TD3 run's wall-time cap is not."""
    from crowdbench.cli_submit import training_overrides

    value = OmegaConf.to_container(compose(["experiment=value_crowdnav"]), resolve=True)
    assert "algo.max_minutes=7" in training_overrides(value)
    td3 = OmegaConf.to_container(compose(["train.max_minutes=5"]), resolve=True)
    assert not any("max_minutes" in o for o in training_overrides(td3))


def test_table_i_in_the_docs_is_the_leaderboards(monkeypatch):
    """docs/value.md's Table I and other-track blocks are what benchmarks/table_i.py makes of the committed
    TRACKS.md; a published cell outside the harness's interval is marked, one inside is not."""
    import importlib

    root = Path(__file__).resolve().parent.parent
    monkeypatch.syspath_prepend(str(root / "benchmarks"))  # the scripts import each other by their file names
    table_i = importlib.import_module("table_i")
    row = {"success": "0.853 [0.758, 0.927]", "collision": "0.004 [0.000, 0.009]", "nav time s": "13.39 [12.04, 14.22]"}
    assert table_i.cell(row, "success", 0.78) == "0.853 [0.758, 0.927]"  # 0.78 rounds into [0.758, 0.927]
    assert table_i.cell(row, "collision", 0.22).endswith(" ✗")
    assert table_i.cell(row, "collision", 0.01) == row["collision"]  # 0.01 stands for [0.005, 0.015]
    text = (root / "leaderboard" / "TRACKS.md").read_text()
    doc = (root / "docs" / "value.md").read_text()
    expected = table_i.replace_block(doc, "table-i", table_i.table_i(table_i.track_rows(text, "crowdnav-circle5")))
    expected = table_i.replace_block(expected, "value-tracks", table_i.other_tracks(text))
    assert doc == expected, "docs/value.md: run python benchmarks/table_i.py --write docs/value.md"
