"""Experiment tracking: ``train.logger=wandb`` (offline) writes a W&B run holding the scalars and the CSV
files beside it, and resumes the same W&B run; ``crowdbench plot`` reads TensorBoard event files as it
reads CSV logs (the same curves), and names a broken event file in one line."""

import os
import re

import numpy as np
import pytest

from crowdbench.algos.train import train
from crowdbench.cli import compose, main

TINY = ["train.pretrain=null", "algo=td3", "encoder=mlp", "encoder.dim=8", "encoder.hidden=[16]", "env.batch=8",
        "train.frames_per_batch=64", "algo.warmup=64", "algo.batch_size=16", "train.utd=0.125",
        "train.checkpoint_every=128", "train.probe_every=1000000"]


def wandb_records(run_dir) -> bytes:
    files = list((run_dir / "wandb").glob("offline-run-*/run-*.wandb"))
    assert files, f"no offline W&B run in {run_dir / 'wandb'}"
    return b"".join(f.read_bytes() for f in files)


def test_wandb_offline_run_writes_its_files(tmp_path, monkeypatch, capsys):
    pytest.importorskip("wandb", reason="train.logger=wandb needs the wandb package (pip install wandb)")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))  # W&B's own settings and cache stay in the test's directory
    monkeypatch.setenv("WANDB_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "config"))
    run = tmp_path / "run"
    stats = train(compose([*TINY, "train.total_frames=128", "train.logger=wandb"]), run, progress=True)
    assert stats["frames"] == 128
    out = capsys.readouterr().out
    run_id = (run / "wandb" / "crowdbench-run-id").read_text().strip()
    assert re.search(rf"wandb: run {run_id} \(offline\) in {re.escape(str(run / 'wandb'))}", out), out
    dirs = list((run / "wandb").glob(f"offline-run-*-{run_id}"))
    assert len(dirs) == 1 and (dirs[0] / f"run-{run_id}.wandb").stat().st_size > 0
    data = wandb_records(run)
    for name in (b"loss_critic", b"updates", b"wall_time_s", b"encoder", b"total_frames"):  # scalars, config
        assert name in data, name
    csv = (run / "logs" / "scalars" / "updates.csv").read_text().splitlines()  # the CSV files as with csv
    assert [int(float(line.split(",")[0])) for line in csv] == [64, 128]

    train(compose([*TINY, "train.total_frames=256", "train.logger=wandb"]), run, resume=True, progress=False)
    assert (run / "wandb" / "crowdbench-run-id").read_text().strip() == run_id  # the same W&B run continues
    # W&B names a run's directory offline-run-<second>-<id>, and adds -1, -2, ... when a resumed run starts
    # within the same second as the one before it
    ours = re.compile(rf"offline-run-\d{{8}}_\d{{6}}-{run_id}(-\d+)?")
    assert len(list((run / "wandb").glob(f"offline-run-*-{run_id}*"))) >= 2
    assert [d.name for d in (run / "wandb").glob("offline-run-*") if not ours.fullmatch(d.name)] == []
    assert int(float((run / "logs" / "scalars" / "updates.csv").read_text().splitlines()[-1].split(",")[0])) == 256


def test_wandb_missing_package_is_one_line(tmp_path, monkeypatch, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "wandb", None)  # `import wandb` raises ImportError
    rc = main(["run", *TINY, "train.total_frames=64", "train.logger=wandb", f"out={tmp_path / 'run'}"])
    err = capsys.readouterr().err
    assert rc == 2 and "train.logger=wandb needs the wandb package" in err and err.count("\n") == 1, err


def tensorboard_run(root, name, steps, values):
    from torchrl.record.loggers.tensorboard import TensorboardLogger

    logger = TensorboardLogger(exp_name="tensorboard", log_dir=str(root / name))
    for s, v in zip(steps, values, strict=True):
        logger.log_scalar("success_rate", v, step=s)
        logger.log_scalar("loss_critic", 1.0 / (1 + s), step=s)
    logger.experiment.close()
    return root / name


def test_plot_reads_tensorboard_logs(tmp_path, capsys):
    pytest.importorskip("tensorboard", reason="reading TensorBoard logs needs the tensorboard package")
    from crowdbench.viz.curves import read_scalars
    from tests.test_viz import fake_run, non_trivial_png

    run = tensorboard_run(tmp_path, "tb", [64, 128, 192], [0.0, 0.25, 0.5])
    logs = read_scalars(run)
    assert logs["success_rate"].tolist() == [[64, 0.0], [128, 0.25], [192, 0.5]]
    # a resumed run writes a second event file repeating steps after its checkpoint: the latest value wins
    tensorboard_run(tmp_path, "tb", [192, 256], [0.75, 1.0])
    assert read_scalars(run)["success_rate"].tolist() == [[64, 0.0], [128, 0.25], [192, 0.75], [256, 1.0]]
    csv = fake_run(tmp_path, "csv", 0, [64, 128, 192, 256], [0.0, 0.25, 0.75, 1.0])
    assert np.array_equal(read_scalars(csv)["success_rate"], read_scalars(run)["success_rate"])
    assert main(["plot", str(run), str(csv), "--out", str(tmp_path / "both.png")]) == 0
    non_trivial_png(tmp_path / "both.png")


def test_plot_trained_tensorboard_run(tmp_path):
    """A real `train.logger=tensorboard` run: the same scalars as the CSV logger writes."""
    pytest.importorskip("tensorboard", reason="train.logger=tensorboard needs the tensorboard package")
    from crowdbench.viz.curves import read_scalars

    train(compose([*TINY, "train.total_frames=128", "train.logger=tensorboard"]), tmp_path / "tb", progress=False)
    train(compose([*TINY, "train.total_frames=128"]), tmp_path / "csv", progress=False)
    tb, csv = read_scalars(tmp_path / "tb"), read_scalars(tmp_path / "csv")
    assert set(tb) == set(csv) and tb["updates"].tolist() == csv["updates"].tolist()
    assert main(["plot", str(tmp_path / "tb"), "--out", str(tmp_path / "tb.png")]) == 0


def test_plot_broken_event_file_is_one_line(tmp_path, capsys):
    pytest.importorskip("tensorboard", reason="reading TensorBoard logs needs the tensorboard package")
    bad = tmp_path / "run" / "tensorboard" / "events.out.tfevents.1.host.1.0"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(os.urandom(64))
    assert main(["plot", str(tmp_path / "run"), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and err.count("\n") == 1, err
