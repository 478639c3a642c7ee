"""``crowdbench run -m``: Hydra multirun with the basic and Ray launchers, failures, the summary, submit."""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from crowdbench.sweep import format_summary, summarise

TINY = ["train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8",
        "train.probe_every=1000000", "train.checkpoint_every=1000000", "eval.episodes=2", "eval.scenes=[hotel]"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RL_WARNINGS": "False", "RAY_AUTH_MODE": "disabled"}


def crowdbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The CLI in a fresh interpreter: Hydra's global state and Ray's stay out of the test process."""
    return subprocess.run([sys.executable, "-m", "crowdbench.cli", *args], check=False, cwd=cwd, env=ENV,
                          capture_output=True, text=True, timeout=600)


def in_process(capsys, *args: str) -> subprocess.CompletedProcess:
    """``crowdbench submit`` / ``leaderboard`` in this interpreter (neither composes with Hydra's global state):
    the 4-6 s of a fresh interpreter's imports saved per call."""
    from crowdbench.cli import main

    capsys.readouterr()
    rc = main(list(args))
    out = capsys.readouterr()
    return subprocess.CompletedProcess(["crowdbench", *args], rc, out.out, out.err)


def avg_success(run_dir: Path) -> float:
    return json.loads((run_dir / "results.json").read_text())["scenes"]["hotel"]["success_rate"]["mean"]


@pytest.fixture(scope="module")
def basic_sweep(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("basic")
    p = crowdbench("run", "-m", "seed=0,1", *TINY, "out=sweep", cwd=root)
    assert p.returncode == 0, p.stderr[-3000:]
    return root / "sweep"


@pytest.mark.slow
@pytest.mark.xdist_group("basic_sweep")  # one worker builds the module fixture once
def test_basic_launcher_writes_every_run_and_the_summary(basic_sweep):
    runs = [basic_sweep / "0", basic_sweep / "1"]
    for d in runs:
        assert (d / "checkpoint.pt").is_file() and (d / "results.json").is_file() and (d / ".hydra").is_dir()
    seeds = [yaml.safe_load((d / ".hydra" / "overrides.yaml").read_text()) for d in runs]
    assert [s[0] for s in seeds] == ["seed=0", "seed=1"]
    summary = json.loads((basic_sweep / "sweep.json").read_text())
    assert [r["status"] for r in summary["runs"]] == ["ok", "ok"] and summary["failed"] == []
    (row,) = summary["table"]  # the two runs differ only in the seed: one row
    values = [avg_success(d) for d in runs]
    assert row["finished"] == 2 and row["success_mean"] == pytest.approx(statistics.mean(values))
    assert row["success_sd"] == pytest.approx(statistics.stdev(values))


@pytest.mark.slow
@pytest.mark.xdist_group("basic_sweep")  # one worker builds the module fixture once
def test_ray_launcher_gives_the_same_runs_as_the_basic_one(basic_sweep, tmp_path):
    p = crowdbench("run", "-m", "hydra/launcher=ray", "hydra.launcher.ray.init.num_cpus=2", "seed=0,1", *TINY,
                   "out=ray_sweep", cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "Ray Launcher is launching 2 jobs" in p.stdout + p.stderr
    ray_dir = tmp_path / "ray_sweep"
    for job in ("0", "1"):  # same seed, same episodes: the launcher changes nothing in the numbers
        a = json.loads((basic_sweep / job / "results.json").read_text())["scenes"]
        b = json.loads((ray_dir / job / "results.json").read_text())["scenes"]
        assert a == b
    assert json.loads((ray_dir / "sweep.json").read_text())["table"][0]["finished"] == 2


@pytest.mark.slow
def test_a_failing_run_does_not_stop_the_others_and_is_named(tmp_path):
    p = crowdbench("run", "-m", "encoder.dim=8,0", *[t for t in TINY if not t.startswith("encoder.dim")],
                   "out=sweep", cwd=tmp_path)
    assert p.returncode == 1
    summary = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    ok, bad = summary["runs"]
    assert ok["status"] == "ok" and (tmp_path / "sweep" / "0" / "results.json").is_file()
    assert bad["status"] == "failed" and "encoder.dim=0" in bad["overrides"]
    assert [f["job"] for f in summary["failed"]] == [1]
    assert "FAILED run 1 (encoder.dim=0" in p.stdout


@pytest.mark.slow
def test_a_bad_key_fails_the_sweep_before_any_run(tmp_path):
    p = crowdbench("run", "-m", "seed=0,1", "train.no_such_key=1", "out=sweep", cwd=tmp_path)
    assert p.returncode != 0 and "no_such_key" in p.stderr
    assert not (tmp_path / "sweep" / "0").exists()


@pytest.mark.slow
@pytest.mark.xdist_group("basic_sweep")  # one worker builds the module fixture once
def test_submit_turns_each_finished_run_into_a_submission(basic_sweep, tmp_path, capsys):
    p = in_process(capsys, "submit", str(basic_sweep), "--root", str(tmp_path), "--entry", "tiny TD3")
    assert p.returncode == 0, p.stderr
    for seed in (0, 1):
        sub = yaml.safe_load((tmp_path / "submissions" / f"gatedgcn_td3_s{seed}" / "submission.yaml").read_text())
        assert sub["entry"] == "tiny TD3" and sub["seed"] == seed and f"seed={seed}" in sub["overrides"]
    assert f"crowdbench leaderboard --root {tmp_path} --only gatedgcn_td3_s0,gatedgcn_td3_s1" in p.stdout
    again = in_process(capsys, "submit", str(basic_sweep), "--root", str(tmp_path), "--entry", "tiny TD3")
    assert again.returncode == 0, again.stderr  # nothing saved is replaced or joined: a second version
    assert {"gatedgcn_td3_v2_s0", "gatedgcn_td3_v2_s1"} <= {d.name for d in (tmp_path / "submissions").iterdir()}
    sub = yaml.safe_load((tmp_path / "submissions" / "gatedgcn_td3_v2_s1" / "submission.yaml").read_text())
    assert sub["entry"] == "tiny TD3 #2"
    named = in_process(capsys, "submit", str(basic_sweep), "--name", "mine", "--root", str(tmp_path))
    assert named.returncode == 0, named.stderr
    sub = yaml.safe_load((tmp_path / "submissions" / "mine_s0" / "submission.yaml").read_text())
    assert sub["entry"] == "gatedgcn_td3 (sweep)"  # the method and the sweep: no shipped row has it


@pytest.mark.slow
@pytest.mark.xdist_group("basic_sweep")  # one worker builds the module fixture once
def test_submit_of_a_plain_sweep_then_the_leaderboard(basic_sweep, tmp_path, capsys):
    """No --entry: names and labels from the sweep, never those of shipped submissions."""
    shipped = tmp_path / "submissions" / "gatedgcn_td3_s0"
    shipped.mkdir(parents=True)  # a name the defaults would take
    (shipped / "submission.yaml").write_text("name: gatedgcn_td3_s0\nentry: gatedgcn_td3 (sweep)\n")
    p = in_process(capsys, "submit", str(basic_sweep), "--root", str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert (shipped / "submission.yaml").read_text().startswith("name: gatedgcn_td3_s0\nentry")  # untouched
    subs = {n: yaml.safe_load((tmp_path / "submissions" / n / "submission.yaml").read_text())
            for n in ("gatedgcn_td3_v2_s0", "gatedgcn_td3_v2_s1")}
    assert {s["entry"] for s in subs.values()} == {"gatedgcn_td3 (sweep) #2"}  # one row, both seeds
    command = p.stdout.split("evaluate them with: ")[1].split()
    assert command[:4] == ["crowdbench", "leaderboard", "--root", str(tmp_path)]
    shutil.rmtree(shipped)  # not a real submission: the leaderboard would reject it
    board = in_process(capsys, *command[1:], "--episodes", "1", "--scenes", "hotel", "--tracks", "v1")
    assert board.returncode == 0, board.stderr[-2000:]
    assert "gatedgcn_td3 (sweep) #2" in (tmp_path / "README.md").read_text()
    assert (tmp_path / "results" / "gatedgcn_td3_v2_s1" / "results.json").is_file()


def test_submit_names_each_configuration_of_a_sweep_apart():
    from crowdbench.cli_submit import slug, varied

    common = {"train.total_frames=256", "seed=0"}
    assert varied(["encoder.dim=8", "train.total_frames=256", "seed=1", "encoder=gcn"], common) == ["encoder.dim=8"]
    assert slug(["encoder.dim=8", "eval.scenes=[hotel,eth]"]) == "dim8_scenes_hotel_eth"


def test_summary_groups_seeds_and_reports_unfinished_runs(tmp_path):
    runs = [("0", ["method=a", "seed=0"], 0.5), ("1", ["method=a", "seed=1"], 0.7), ("2", ["method=b", "seed=0"], 0.9)]
    for job, over, success in runs:
        (tmp_path / job).mkdir()
        (tmp_path / job / "status.json").write_text(json.dumps(
            {"job": int(job), "overrides": over, "status": "ok", "success": success, "dangers": 1.0}))
    (tmp_path / "3" / ".hydra").mkdir(parents=True)  # killed before it wrote a status
    (tmp_path / "3" / ".hydra" / "overrides.yaml").write_text("- method=b\n- seed=1\n")
    s = summarise(tmp_path)
    a, b = s["table"]
    assert (a["config"], a["finished"], a["runs"]) == ("method=a", 2, 2)
    assert a["success_mean"] == pytest.approx(0.6) and a["success_sd"] == pytest.approx(0.1414213562)
    assert (b["config"], b["finished"], b["runs"], b["success_mean"]) == ("method=b", 1, 2, 0.9)
    assert s["failed"] == [{"job": 3, "overrides": ["method=b", "seed=1"],
                            "error": "the run ended without a status (killed?)"}]
    assert "0.600 ± 0.141" in format_summary(s) and "FAILED run 3" in format_summary(s)


@pytest.mark.parametrize("address", [None, "auto", "127.0.0.1:6379"])
def test_ray_launcher_gives_local_cluster_settings_only_without_an_address(address):
    """ray.init refuses object_store_memory when joining a cluster (the README's `init.address=auto`)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import crowdbench.sweep  # noqa: F401 - registers the launcher config's resolver
    from crowdbench.cli import CONFIG_DIR

    over = ["hydra/launcher=ray"] + ([f"hydra.launcher.ray.init.address={address}"] if address else [])
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        cfg = compose(config_name="config", overrides=over, return_hydra_config=True)
    init = OmegaConf.to_container(cfg.hydra.launcher.ray.init, resolve=True)
    assert init["object_store_memory"] == (None if address else 100_000_000)
