"""``crowdbench viz`` on malformed or oversized episode records: one line naming the field, fast."""

from __future__ import annotations

import json
import resource

import pytest

from crowdbench.cli import main
from crowdbench.envs.protocol import ProtocolSpec


@pytest.fixture(scope="module")
def a_record(tmp_path_factory) -> dict:
    """A genuine record: the straight-to-goal baseline's first hotel episode."""
    out = tmp_path_factory.mktemp("ev")
    assert main(["eval", "policy=straight", "eval.scenes=[hotel]", "eval.episodes=1", "eval.save_episodes=true",
                 f"out={out}"]) == 0
    return json.loads((out / "episodes.jsonl").read_text().splitlines()[0])


def viz(tmp_path, record: dict, capsys) -> tuple[int, str]:
    (tmp_path / "episodes.jsonl").write_text(json.dumps(record) + "\n")
    capsys.readouterr()
    rc = main(["viz", str(tmp_path / "episodes.jsonl"), "--out", str(tmp_path / "x.png")])
    return rc, capsys.readouterr().err


def test_a_genuine_record_draws(a_record, tmp_path, capsys):
    assert viz(tmp_path, a_record, capsys)[0] == 0 and (tmp_path / "x.png").stat().st_size > 0


@pytest.mark.parametrize("field, value", [("dt", 0), ("dt", -0.25), ("dt", True), ("robot_xy", []),
                                          ("robot_xy", [[0.0, 1.0, 2.0]]), ("robot_xy", [["a", 1]]),
                                          ("start", [1.0]), ("goal", None), ("start_time_s", float("inf"))])
def test_a_malformed_field_is_one_line_naming_it(a_record, tmp_path, capsys, field, value):
    """L10: ``dt: 0`` gave ``OverflowError``, ``robot_xy: []`` an ``IndexError``."""
    rc, err = viz(tmp_path, {**a_record, field: value}, capsys)
    assert rc == 2 and err.count("\n") == 1 and field in err and "Traceback" not in err, err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.slow
def test_a_path_longer_than_the_time_limit_is_refused_quickly(a_record, tmp_path, capsys):
    """M16: a 2 M-point path ran > 300 s and 3 GB before it was killed."""
    long = {**a_record, "robot_xy": [a_record["robot_xy"][0]] * 2_000_001}
    before = resource.getrusage(resource.RUSAGE_SELF).ru_utime
    rc, err = viz(tmp_path, long, capsys)
    assert rc == 2 and "robot_xy" in err and "time limit" in err and err.count("\n") == 1
    assert resource.getrusage(resource.RUSAGE_SELF).ru_utime - before < 30  # (reading ~40 MB of JSON)
    limit = ProtocolSpec().time_limit  # the record's own results.json says so: the protocol's limit
    (tmp_path / "results.json").write_text(json.dumps({"sim_config": {"time_limit": limit, "time_base": "true"}}))
    rc, err = viz(tmp_path, {**a_record, "robot_xy": [a_record["robot_xy"][0]] * (limit + 2)}, capsys)
    assert rc == 2 and f"({limit})" in err
    assert viz(tmp_path, {**a_record, "robot_xy": [a_record["robot_xy"][0]] * (limit + 1)}, capsys)[0] == 0
