"""Training end to end: every algo x encoder, checkpoints, resume after a kill, bad input."""

import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from crowdbench.algos import registry as algo_registry
from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint, policy_from_checkpoint
from crowdbench.algos.train import train
from crowdbench.cli import compose, main
from crowdbench.protocols.replay import evaluate

TINY = ["train.pretrain=null", "env.batch=8", "train.frames_per_batch=64", "algo.warmup=128", "algo.batch_size=16", "train.utd=0.125",
        "train.checkpoint_every=128"]
SMALL_ENCODER = {"gatedgcn": ["encoder.dim=16"], "gcn": ["encoder.dim=16"], "mlp": ["encoder.dim=16",
                                                                                    "encoder.hidden=[32]"]}
SMALL_GCN_TD3 = ["algo=td3", "encoder=gcn", *TINY, *SMALL_ENCODER["gcn"]]  # the resume / overwrite tests' run


def read_log(run, name):
    path = run / "logs" / "scalars" / f"{name}.csv"
    return [(int(float(a)), float(b)) for a, b in (line.split(",") for line in path.read_text().splitlines())]


@pytest.mark.parametrize("algo", ["td3", "ddpg", "sac"])
@pytest.mark.parametrize("encoder", ["gatedgcn", "gcn", "mlp"])
def test_each_algo_encoder_trains_and_checkpoints(algo, encoder, tmp_path):
    cfg = compose([f"algo={algo}", f"encoder={encoder}", "train.total_frames=320", *TINY, *SMALL_ENCODER[encoder]])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["frames"] == 320 and stats["updates"] > 0
    state = load_checkpoint(tmp_path / "checkpoint.pt")  # weights_only=True inside
    assert state["frames"] == 320 and state["config"]["algo"]["name"] == algo
    losses = read_log(tmp_path, "loss_critic")
    assert losses and all(torch.isfinite(torch.tensor(v)) for _, v in losses)
    policy = policy_from_checkpoint(tmp_path / "checkpoint.pt")
    res = evaluate(policy, ["hotel"], episodes=3)
    assert res["scenes"]["hotel"]["success_rate"]["n"] == 3


def test_resume_continues_counter_and_log(tmp_path):
    base = SMALL_GCN_TD3
    train(compose([*base, "train.total_frames=256"]), tmp_path, progress=False)
    first = read_log(tmp_path, "updates")
    stats = train(compose([*base, "train.total_frames=512"]), tmp_path, resume=True, progress=False)
    assert stats["frames"] == 512
    log = read_log(tmp_path, "updates")
    assert log[: len(first)] == first  # nothing logged before is lost
    steps = [s for s, _ in log]
    assert steps == sorted(set(steps)) and steps[-1] == 512  # the counter continues, no duplicates
    assert log[-1][1] > first[-1][1]  # updates keep counting from the checkpoint


def test_a_fresh_run_never_overwrites_a_saved_one(tmp_path):
    base = SMALL_GCN_TD3
    train(compose([*base, "train.total_frames=256"]), tmp_path, progress=False)
    saved = (tmp_path / "checkpoint.pt").read_bytes()
    log = read_log(tmp_path, "updates")
    with pytest.raises(CheckpointError, match="already holds a training run .*resume=true"):
        train(compose([*base, "train.total_frames=512"]), tmp_path, progress=False)
    assert (tmp_path / "checkpoint.pt").read_bytes() == saved and read_log(tmp_path, "updates") == log


def test_resume_checks_the_config(tmp_path):
    """A resumed run must keep the model and task; the replay buffer may change kind (tests/test_runs.py)."""
    base = SMALL_GCN_TD3
    train(compose([*base, "train.total_frames=256"]), tmp_path, progress=False)
    with pytest.raises(CheckpointError, match=r"config 'encoder' differs .*\(encoder\.dim\)"):
        train(compose([*base, "train.total_frames=512", "encoder.dim=8"]), tmp_path, resume=True, progress=False)
    with pytest.raises(CheckpointError, match=r"config 'algo' differs .*\(algo\.lr_critic\)"):
        train(compose([*base, "train.total_frames=512", "algo.lr_critic=0.01"]), tmp_path, resume=True, progress=False)
    stats = train(compose([*base, "train.total_frames=512", "algo.replay=uniform"]), tmp_path, resume=True,
                  progress=False)
    assert stats["frames"] == 512 and load_checkpoint(tmp_path / "checkpoint.pt")["frames"] == 512


@pytest.mark.slow
def test_resume_after_kill(tmp_path):
    """Kill a real `crowdbench run` after its first checkpoint, resume it, and check the log and counter."""
    args = [sys.executable, "-m", "crowdbench.cli", "run", "algo=td3", "encoder=gcn", *TINY, *SMALL_ENCODER["gcn"],
            "train.total_frames=100000", "eval.episodes=2", "eval.scenes=[hotel]", f"out={tmp_path}"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = tmp_path / "checkpoint.pt"
    deadline = time.time() + 240
    while time.time() < deadline and not (ckpt.exists() and load_checkpoint(ckpt)["frames"] >= 256):
        time.sleep(0.5)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    saved = load_checkpoint(ckpt)["frames"]
    assert saved >= 256
    before = read_log(tmp_path, "updates")
    rc = main(["run", "algo=td3", "encoder=gcn", *TINY, *SMALL_ENCODER["gcn"], f"train.total_frames={saved + 128}",
               "eval.episodes=2", "eval.scenes=[hotel]", f"out={tmp_path}", "resume=true"])
    assert rc == 0
    after = read_log(tmp_path, "updates")
    kept = [r for r in before if r[0] <= saved]
    assert after[: len(kept)] == kept and after[-1][0] == saved + 128
    assert load_checkpoint(ckpt)["frames"] == saved + 128
    assert (tmp_path / "results.json").exists()


def test_corrupted_checkpoint_and_bad_names(tmp_path, capsys):
    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes(b"not a zip file at all")
    with pytest.raises(CheckpointError, match="corrupted or unsafe checkpoint"):
        load_checkpoint(bad)
    assert main(["eval", f"policy={bad}", f"out={tmp_path / 'e'}"]) == 2
    err = capsys.readouterr().err
    assert "corrupted or unsafe checkpoint" in err and err.count("\n") == 1
    # a pickled object (code) is refused by weights_only loading
    torch.save({"format": "crowdbench-checkpoint-v1", "obj": CheckpointError("x")}, bad)
    with pytest.raises(CheckpointError, match="corrupted or unsafe"):
        load_checkpoint(bad)
    assert main(["run", "encoder=transformer9000"]) == 2
    assert "unknown encoder 'transformer9000'; valid choices:" in capsys.readouterr().err
    assert main(["run", "algo=dqn"]) == 2
    err = capsys.readouterr().err
    assert "unknown algo 'dqn'; valid choices: " in err
    listed = err.split("valid choices: ")[1].strip().split(", ")
    assert listed == sorted(algo_registry.names())  # every registered algorithm, none else
    assert main(["run", "resume=true"]) == 2
    assert "resume=true needs out=" in capsys.readouterr().err


def test_n_step_returns_by_hand():
    """Two episodes in one [1, 6] batch (the first ends at step 2), n = 3, gamma = 0.5."""
    from tensordict import TensorDict

    from crowdbench.algos.nstep import STEPS, n_step
    from crowdbench.algos.td3 import TD3

    T = 6
    reward = torch.tensor([1.0, 2.0, 4.0, 8.0, 16.0, 32.0]).view(1, T, 1, 1)
    done = torch.tensor([0, 0, 1, 0, 0, 0], dtype=torch.bool).view(1, T, 1, 1)
    obs_id = torch.arange(1, T + 1, dtype=torch.float).view(1, T, 1, 1)  # next observation of step t is t + 1
    batch = TensorDict({"agents": {"x": obs_id - 1}, "next": {"agents": {
        "x": obs_id, "reward": reward, "done": done, "terminated": done.clone()}}}, batch_size=[1, T])
    out = n_step(batch, 3, 0.5)
    # step 0: 1 + 0.5*2 + 0.25*4, ends its episode at step 2 -> terminal next obs 3, no bootstrap
    assert out["next", "agents", "reward"].flatten().tolist() == [3.0, 4.0, 4.0, 8 + 8 + 8, 16 + 16, 32]
    assert out["next", "agents", "x"].flatten().tolist() == [3, 3, 3, 6, 6, 6]
    assert out["next", "agents", "terminated"].flatten().tolist() == [True, True, True, False, False, False]
    assert out[STEPS].flatten().tolist() == [3, 2, 1, 3, 2, 1]  # the batch ends after step 5: shorter tails
    assert torch.equal(out["agents", "x"], batch["agents", "x"])  # the start state is unchanged
    # TorchRL's TD(0) estimator then bootstraps with gamma^m: r + 0.99^m * V(s_{t+m}) on non-terminal rows
    loss = TD3(compose(["encoder=mlp", "encoder.dim=8", "encoder.hidden=[8]", "algo.gamma=0.99"]), 1).loss
    td = TensorDict({"next": {"agents": {"reward": torch.ones(3, 1, 1), "done": torch.zeros(3, 1, 1, dtype=torch.bool),
                                         "terminated": torch.tensor([False, False, True]).view(3, 1, 1),
                                         "state_action_value": torch.full((3, 1, 1), 2.0)}},
                     "agents": {"steps_to_next_obs": torch.tensor([1, 3, 3]).view(3, 1, 1)}}, batch_size=[3])
    target = loss.value_estimator.value_estimate(td).flatten()
    assert target.tolist() == pytest.approx([1 + 0.99 * 2, 1 + 0.99**3 * 2, 1.0])
    with pytest.raises(ValueError, match="n_steps"):
        n_step(batch, 0, 0.5)


@pytest.mark.parametrize("env", ["replay", "selfplay"])
def test_n_step_and_ou_exploration_train(env, tmp_path):
    extra = ["env=selfplay", "env.n_agents=4"] if env == "selfplay" else []
    cfg = compose(["algo.n_steps=4", "algo.exploration=ou", "algo.exploration_sigma=0.3", "train.total_frames=256",
                   *TINY, *SMALL_ENCODER["mlp"], "encoder=mlp", *extra])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["updates"] > 0 and all(torch.isfinite(torch.tensor(v)) for _, v in read_log(tmp_path, "loss_critic"))
    with pytest.raises(ValueError, match="algo.exploration"):
        train(compose([*TINY, "algo.exploration=pink"]), tmp_path / "bad", progress=False)


@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_lookahead_critic_trains(algo, tmp_path):
    cfg = compose([f"algo={algo}", "algo.critic_lookahead=0.25", "train.total_frames=256", *TINY,
                   *SMALL_ENCODER["gatedgcn"]])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["updates"] > 0 and all(torch.isfinite(torch.tensor(v)) for _, v in read_log(tmp_path, "loss_critic"))
    with pytest.raises(ValueError, match="robot-relative"):
        train(compose(["algo.critic_lookahead=0.25", "env.frame=world", *TINY]), tmp_path / "w", progress=False)


def test_same_seed_same_run(tmp_path):
    """A frame budget and a seed reproduce a run (the leaderboard rows rely on it); another seed does not."""
    recipe = ["algo=td3", "encoder=gatedgcn", "algo.critic_lookahead=0.25", "train.progress_reward=0.1",
              "algo.exploration_sigma=0.3", "train.total_frames=320", *TINY, *SMALL_ENCODER["gatedgcn"]]
    runs = {}
    for name, seed in [("a", 0), ("b", 0), ("c", 1)]:
        train(compose([*recipe, f"seed={seed}"]), tmp_path / name, progress=False)
        runs[name] = load_checkpoint(tmp_path / name / "checkpoint.pt")["actor"]
    assert runs["a"].keys() == runs["b"].keys()
    assert all(torch.equal(runs["a"][k], runs["b"][k]) for k in runs["a"])
    assert read_log(tmp_path / "a", "loss_critic") == read_log(tmp_path / "b", "loss_critic")
    assert read_log(tmp_path / "a", "episode_return") == read_log(tmp_path / "b", "episode_return")
    assert not all(torch.equal(runs["a"][k], runs["c"][k]) for k in runs["a"])
