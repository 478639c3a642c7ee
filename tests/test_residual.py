"""``algo.actor_base=orca``: the actor is ORCA plus a learned residual (crowdbench/algos/actors.py OrcaResidual)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from crowdbench.algos.actors import OrcaResidual
from crowdbench.algos.checkpoint import load_checkpoint, policy_from_checkpoint
from crowdbench.algos.td3 import TD3
from crowdbench.algos.train import train
from crowdbench.cli import compose
from crowdbench.envs.factory import make_env
from crowdbench.models.heads import OBS_KEYS, Actor
from crowdbench.policies import build

TINY = ["train.pretrain=null", "env.batch=4", "train.frames_per_batch=32", "algo.warmup=64", "algo.batch_size=8",
        "train.utd=0.25", "train.checkpoint_every=64", "encoder.dim=16", "algo.actor_base=orca"]


def _rollout_obs(cfg, steps: int = 12):
    """Observations of a few steps of the training env driven by ORCA."""
    env = make_env(cfg)
    orca = build("orca", cfg)
    td, seen = env.reset(), []
    for _ in range(steps):
        seen.append(td.select(*OBS_KEYS).clone())
        td["agents", "action"] = orca.act(td)
        td = env.step(td).get("next")
    return torch.cat(seen)


def test_the_untrained_actor_is_the_orca_baseline():
    cfg = compose(TINY)
    obs = _rollout_obs(cfg)
    actor = TD3(cfg, 1).actor
    assert isinstance(actor.module, OrcaResidual)
    mine = actor(obs.clone())["agents", "action"]
    theirs = build("orca", cfg).act(obs)  # the policy registry's ORCA, as `crowdbench eval policy=orca` builds it
    assert obs["agents", "observation", "humans_mask"].any()
    assert torch.equal(mine, theirs)


@pytest.mark.parametrize("scale", [1.0, 0.3])
def test_the_residual_is_added_then_scaled_into_the_speed_disc(scale):
    cfg = compose([*TINY, f"algo.actor_residual={scale}"])
    obs = _rollout_obs(cfg, steps=4)
    actor = TD3(cfg, 1).actor.module
    z = (0.6, -1.1)
    with torch.no_grad():
        actor.head[-1].bias.copy_(torch.tensor(z))
    base = build("orca", cfg).act(obs).reshape(-1, 2).tolist()
    got = actor(obs)
    nz = math.hypot(*z)
    res = [scale * math.tanh(nz) * z[0] / nz, scale * math.tanh(nz) * z[1] / nz]  # the radial squash of z
    expected = []
    for bx, by in base:
        sx, sy = bx + res[0], by + res[1]
        n = math.hypot(sx, sy)
        scale = 1.0 / n if n > 1.0 else 1.0
        expected.append([sx * scale, sy * scale])
    assert torch.allclose(got.reshape(-1, 2), torch.tensor(expected), atol=1e-6)
    assert (got.norm(dim=-1) <= 1.0 + 1e-6).all()
    assert any(math.hypot(bx + res[0], by + res[1]) > 1.0 for bx, by in base)  # the scaling was exercised


def test_the_gradient_reaches_the_residual_and_the_base_has_none():
    cfg = compose(TINY)
    obs = _rollout_obs(cfg, steps=4)
    actor = TD3(cfg, 1).actor.module
    actor(obs)[..., 0].sum().backward()
    assert actor.head[-1].weight.grad.abs().sum() > 0
    assert set(actor.state_dict()) == set(Actor(actor.encoder, None, 1.0).state_dict())  # ORCA adds no weights


def test_a_run_checkpoints_and_its_policy_acts_as_in_training(tmp_path):
    cfg = compose([*TINY, "train.total_frames=128"])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["updates"] > 0
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["config"]["algo"]["actor_base"] == "orca"
    policy = policy_from_checkpoint(tmp_path / "checkpoint.pt")
    assert isinstance(policy.actor.module, OrcaResidual)
    obs = _rollout_obs(cfg, steps=3)
    algo = TD3(cfg, 1)
    algo.actor.load_state_dict(state["actor"])
    assert torch.equal(policy.act(obs.clone()), algo.actor(obs.clone())["agents", "action"])
    assert not torch.equal(policy.act(obs.clone()), build("orca", cfg).act(obs))  # it learned a residual


@pytest.mark.parametrize("algo", ["td3", "ddpg"])
def test_it_trains_with_the_papers_critic_too(algo, tmp_path):
    """The paper's critic reads graphs prepared once per batch for a plain actor; beside an ORCA residual it
    reads the raw observation (the actor needs it, and TorchRL's target step hands the critic the actor's keys)."""
    cfg = compose([*TINY, f"algo={algo}", "algo.critic_lookahead=0", "train.total_frames=96"])
    stats = train(cfg, tmp_path, progress=False)
    assert stats["updates"] > 0
    assert isinstance(policy_from_checkpoint(tmp_path / "checkpoint.pt").actor.module, OrcaResidual)


def test_a_checkpoint_before_the_option_loads_with_a_plain_actor(tmp_path):
    cfg = compose([*TINY, "train.total_frames=128"])
    train(cfg, tmp_path, progress=False)
    raw = torch.load(tmp_path / "checkpoint.pt", map_location="cpu", weights_only=True)
    del raw["config"]["algo"]["actor_base"]
    raw["format"] = 8
    torch.save(raw, tmp_path / "old.pt")  # (save_checkpoint would stamp today's format)
    assert load_checkpoint(tmp_path / "old.pt")["config"]["algo"]["actor_base"] == "none"
    assert not isinstance(policy_from_checkpoint(tmp_path / "old.pt").actor.module, OrcaResidual)


@pytest.mark.parametrize("bad", ["algo.actor_base=rvo", "algo=sac algo.actor_base=orca"])
def test_a_bad_base_is_refused_in_one_line(bad, capsys):
    from crowdbench.cli import main

    rc = main(["run", *bad.split(), "train.total_frames=64", "out=/nonexistent/never"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "actor_base" in err and len(err.splitlines()) == 1


WORKER_RUNS = {  # a residual actor of each kind: TD3's deterministic one, MAPPO's sampled residual (self-play)
    "td3": [*TINY, "train.total_frames=64"],
    "mappo": ["train.pretrain=null", "algo=mappo", "env=selfplay", "env.n_agents=4", "env.batch=4", "encoder.dim=16",
              "algo.actor_base=orca", "train.frames_per_batch=64", "train.total_frames=64", "algo.minibatch_size=64"],
}


@pytest.mark.slow
@pytest.mark.parametrize("algo", sorted(WORKER_RUNS))
def test_a_residual_submission_acts_in_its_worker_as_in_process(algo, tmp_path):
    """ORCA's solver (pyrvo) inside the confined worker: the same bits as in-process."""
    from crowdbench.leaderboard.loading import dummy_obs
    from crowdbench.leaderboard.sandbox import Limits
    from crowdbench.leaderboard.worker import WorkerPolicy

    cfg = compose(WORKER_RUNS[algo])
    sub = tmp_path / "lb" / "submissions" / "res"
    train(cfg, sub, progress=False)
    track = "track: selfplay\n" if algo == "mappo" else ""
    (sub / "submission.yaml").write_text(f"name: res\nkind: learned\nentry: res\nencoder: gatedgcn\nalgo: {algo}\n"
                                         f"{track}authors: [crowdbench]\n")
    obs = dummy_obs(batch=4, humans=3)
    with WorkerPolicy(sub, "res", Limits(step_s=20.0, load_s=120.0, memory_gb=6.0)) as p:
        remote = p.act(obs)
    assert torch.equal(remote, policy_from_checkpoint(Path(sub) / "checkpoint.pt").act(obs))


def _collected(cfg, algo, steps: int = 6):
    """A collected ``[B, T]`` batch of the training env, acted by the residual actor."""
    env = make_env(cfg)
    with torch.no_grad():
        return env.rollout(steps, algo.actor, break_when_any_done=False)


def test_updates_read_the_base_stored_with_each_transition(monkeypatch):
    """ORCA runs once per collected observation (next ones too); the updates never run its solver, and what
    they read equals what the solver gives for the same observations."""
    from crowdbench.baselines.orca import ORCA
    from crowdbench.models.heads import BASE_ACTION

    cfg = compose([*TINY, "algo.warmup=0"])
    algo = TD3(cfg, 1)
    batch = _collected(cfg, algo)
    orca = build("orca", cfg)
    algo.store_base(batch)
    for pre in ((), ("next",)):
        obs = [batch.get((*pre, *k)) for k in OBS_KEYS]
        assert torch.equal(batch.get((*pre, *BASE_ACTION)), orca.velocities(*obs))
    algo.rb.extend(batch.reshape(-1).select(*algo.keep))
    sample = algo.rb.sample()
    before = algo.actor(sample.select(*OBS_KEYS).clone())["agents", "action"]

    def refuse(*a, **k):
        raise AssertionError("ORCA's solver ran in an update")

    monkeypatch.setattr(ORCA, "velocities", refuse)
    assert torch.equal(algo.actor(sample.clone())["agents", "action"], before)  # the stored base, same bits
    for n in range(4):  # critic-only and full steps (the target actor, the actor term)
        algo.update(sample.clone(), n)


def test_a_buffer_without_stored_bases_gets_them_on_resume():
    """A replay buffer saved before the bases were stored (a resume) is completed, not refused."""
    from crowdbench.models.heads import BASE_ACTION

    cfg = compose(TINY)
    algo = TD3(cfg, 1)
    batch = _collected(cfg, algo).reshape(-1)
    algo.rb.extend(batch.select(*[k for k in algo.keep if BASE_ACTION[-1] not in k]))
    algo.fill_base()
    stored = algo.rb.storage.get(torch.arange(len(algo.rb)))
    assert torch.equal(stored.get(BASE_ACTION), algo.store_base(batch.clone()).get(BASE_ACTION))
