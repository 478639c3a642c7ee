"""The algorithm registry: a toy algorithm registered from a test is trained by the CLI without touching
the CLI, refused names are one-line errors, and every algorithm resumes."""

import json
from dataclasses import dataclass

import pytest
import torch

from crowdbench.algos.checkpoint import load_checkpoint, policy_from_checkpoint
from crowdbench.algos.registry import entry, names, register_algorithm, unregister_algorithm
from crowdbench.algos.td3 import TD3, TD3Config
from crowdbench.algos.train import train
from crowdbench.cli import compose, main
from crowdbench.config_fields import bounded

TINY = ["train.pretrain=null", "env.batch=8", "train.frames_per_batch=64", "train.checkpoint_every=64", "eval.episodes=2",
        "eval.scenes=[hotel]", "train.probe_every=100000"]
SMALL_MLP = ["encoder=mlp", "encoder.dim=16", "encoder.hidden=[32]"]
OFF_POLICY = ["algo.warmup=64", "algo.batch_size=16", "train.utd=0.125"]
PPO = ["algo.minibatch_size=64", "algo.epochs=1"]


@dataclass
class ToyConfig(TD3Config):
    """TD3 whose actor is updated with every critic update and a fixed learning rate decay key."""

    name: str = bounded("toy", choices=("toy",))
    policy_delay: int = bounded(1, ge=1)
    decay: float = bounded(0.5, gt=0, le=1)


class Toy(TD3):
    name = "toy"
    config = ToyConfig
    calls = 0

    def learn(self, batch):
        Toy.calls += 1
        logs = super().learn(batch)
        for group in self.opt_actor.param_groups:
            group["lr"] *= self.a.decay
        return logs


def test_a_registered_algorithm_is_picked_up_by_the_cli(tmp_path, capsys):
    register_algorithm(Toy)
    try:
        assert "toy" in names()
        out = tmp_path / "run"
        assert main(["run", "algo=toy", "algo.decay=0.9", *SMALL_MLP, *TINY, *OFF_POLICY, "train.total_frames=192",
                     f"out={out}"]) == 0
        assert Toy.calls == 3
        state = load_checkpoint(out / "checkpoint.pt")
        assert state["config"]["algo"]["name"] == "toy" and state["config"]["algo"]["decay"] == 0.9
        assert state["opt_actor"]["param_groups"][0]["lr"] == pytest.approx(1e-3 * 0.9**3)
        assert policy_from_checkpoint(out / "checkpoint.pt").name == "toy-mlp"
        assert json.loads((out / "results.json").read_text())["scenes"]["hotel"]["success_rate"]["n"] == 2
        # its schema checks types and bounds like a shipped one
        assert main(["run", "algo=toy", "algo.decay=2", f"out={tmp_path / 'bad'}"]) == 2
        assert capsys.readouterr().err.endswith("crowdbench: error: algo.decay: must be in (0, 1] (got 2.0)\n")
    finally:
        unregister_algorithm("toy")
    assert "toy" not in names()
    from hydra.core.config_store import ConfigStore

    assert "toy.yaml" not in ConfigStore.instance().repo["algo"]


def test_unknown_algorithms_and_keys_are_one_line_errors(tmp_path, capsys):
    with pytest.raises(ValueError, match="^unknown algo 'dqn'; valid: td3, ddpg, sac, ppo, matd3, ippo, mappo, value$"):
        entry("dqn")
    assert main(["run", "algo=dqn", f"out={tmp_path / 'a'}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "algo" in err and "ppo" in err
    # another algorithm's key, as an experiment written for TD3 would set it
    assert main(["run", "algo=sac", "+algo.policy_noise=0.1", f"out={tmp_path / 'b'}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "algo.policy_noise: algo='sac' has no such key" in err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


@pytest.mark.parametrize("algo", ["td3", "ddpg", "sac", "ppo", "mappo", "matd3"])
def test_every_algorithm_resumes_where_it_stopped(algo, tmp_path):
    """Two halves with a resume in between give the uninterrupted run's frames, updates and log rows."""
    extra = PPO if algo in ("ppo", "mappo") else OFF_POLICY
    base = [f"algo={algo}", *SMALL_MLP, *TINY, *extra]
    whole = train(compose([*base, "train.total_frames=256"]), tmp_path / "whole", progress=False)
    train(compose([*base, "train.total_frames=128"]), tmp_path / "split", progress=False)
    split = train(compose([*base, "train.total_frames=256"]), tmp_path / "split", resume=True, progress=False)
    assert (split["frames"], split["updates"]) == (whole["frames"], whole["updates"]) == (256, split["updates"])
    assert split["updates"] > 0
    rows = [(tmp_path / d / "logs" / "scalars" / "updates.csv").read_text() for d in ("whole", "split")]
    assert rows[0] == rows[1]
    a, b = (load_checkpoint(tmp_path / d / "checkpoint.pt") for d in ("whole", "split"))
    assert a["actor"].keys() == b["actor"].keys() and all(torch.isfinite(v).all() for v in b["actor"].values())
