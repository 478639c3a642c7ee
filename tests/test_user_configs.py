"""A project's own configs in ./configs/ (found from the current directory, after the packaged defaults)."""

from __future__ import annotations

import json
from pathlib import Path

from crowdbench.cli import compose, main

ROOT = Path(__file__).resolve().parents[1]
TINY = ["train.pretrain=null", "train.total_frames=128", "train.frames_per_batch=64", "algo.warmup=64", "encoder.dim=8",
        "train.probe_every=1000000", "train.checkpoint_every=1000000", "eval.episodes=1", "eval.scenes=[hotel]"]


def test_user_experiment_is_picked_up_by_run(tmp_path, monkeypatch, capsys):
    (tmp_path / "configs" / "experiment").mkdir(parents=True)
    (tmp_path / "configs" / "experiment" / "mine.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /encoder: gcn\nalgo:\n  gamma: 0.95\nseed: 7\n")
    monkeypatch.chdir(tmp_path)
    cfg = compose(["+experiment=mine"])
    assert (cfg.encoder.name, cfg.algo.gamma, cfg.seed) == ("gcn", 0.95, 7)
    assert main(["run", "+experiment=mine", *TINY, "out=run"]) == 0
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    assert list(res["scenes"]) == ["hotel"]
    assert (tmp_path / "run" / "checkpoint.pt").is_file()


def test_user_experiment_is_not_found_elsewhere(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # no ./configs here
    assert main(["run", "experiment=mine", *TINY]) == 2
    assert "unknown experiment 'mine'" in capsys.readouterr().err


def test_the_repository_example_composes(monkeypatch):
    monkeypatch.chdir(ROOT)
    cfg = compose(["experiment=gatedgcn_warmstart"])
    assert (cfg.encoder.name, cfg.algo.name, cfg.train.pretrain) == ("gatedgcn", "td3", "orca")
    assert cfg.submission.experiment == "gatedgcn_warmstart"
