"""Checkpoint format versions: format-1 checkpoints (crowdbench 0.1.0) load through one upgrade."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import pytest
import torch

from crowdbench.algos.actors import build_actor
from crowdbench.algos.checkpoint import (
    FORMAT,
    LEGACY_TAG,
    CheckpointError,
    load_checkpoint,
    policy_from_checkpoint,
    save_checkpoint,
)
from crowdbench.envs.factory import replay_env

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "leaderboard" / "submissions" / "mlp_td3_s0" / "checkpoint.pt"  # format 1, no algo.per_weights


def test_a_shipped_format_1_checkpoint_loads_with_the_upgraded_config():
    raw = torch.load(SHIPPED, map_location="cpu", weights_only=True)
    assert raw["format"] == LEGACY_TAG and "per_weights" not in raw["config"]["algo"]  # really format 1
    state = load_checkpoint(SHIPPED)
    assert state["format"] == FORMAT == 9
    assert state["config"]["algo"]["actor_base"] == "none"  # format 9: a plain actor
    assert state["config"]["train"]["pretrain_dagger_rounds"] == 0  # format 8: no DAgger
    assert state["config"]["env"]["humans"] == "replay"  # format 3: trained among the humans as recorded
    algo = state["config"]["algo"]
    assert algo["per_weights"] is False
    # format 4: only TD3's own keys (its schema's fields)
    from crowdbench.algos.td3 import TD3Config

    assert set(algo) == {f.name for f in fields(TD3Config)} and {"lr_alpha", "alpha_init"} <= set(raw["config"]["algo"])
    assert algo["actor_squash"] == raw["config"]["algo"]["actor_squash"]  # stored values are kept
    assert algo["critic_lookahead"] == raw["config"]["algo"]["critic_lookahead"]
    for k, v in raw["actor"].items():
        assert torch.equal(state["actor"][k], v)

    # the policy acts exactly as the actor rebuilt from the raw (format-1) config and weights
    cfg = raw["config"]
    ref = build_actor(cfg["algo"]["name"], dict(cfg["encoder"]), cfg["env"]["v_max"],
                      squash=cfg["algo"]["actor_squash"])
    ref.load_state_dict(raw["actor"])
    ref.eval()
    policy = policy_from_checkpoint(SHIPPED)
    td = replay_env("students003", batch=8, seed=0).reset()
    with torch.no_grad():
        assert torch.equal(policy.act(td), ref(td.clone(False))["agents", "action"])


def test_format_2_reactive_run_keeps_its_humans(tmp_path):
    """Format 2 -> 3 fills env.humans only where it is missing: a reactive-replay run stays one."""
    env = {"name": "replay", "humans": "reactive_replay", "reactive": {"model": "sfm"}}
    torch.save({"format": 2, "config": {"env": dict(env), "algo": {}, "train": {}}, "actor": {}, "frames": 0},
               tmp_path / "r.pt")
    assert load_checkpoint(tmp_path / "r.pt")["config"]["env"] == env
    torch.save({"format": 2, "config": {"env": {"name": "crowdnav"}, "algo": {}, "train": {}}, "actor": {},
                "frames": 0}, tmp_path / "c.pt")
    assert load_checkpoint(tmp_path / "c.pt")["config"]["env"] == {"name": "crowdnav"}  # not a replay run


def test_every_shipped_checkpoint_loads():
    ckpts = sorted((ROOT / "leaderboard" / "submissions").glob("*/checkpoint.pt"))
    learned = [d for d in (ROOT / "leaderboard" / "submissions").iterdir()
               if "kind: learned" in (d / "submission.yaml").read_text()]
    assert len(ckpts) == len(learned) > 0  # every learned submission ships one; an empty glob fails
    for ckpt in ckpts:
        state = load_checkpoint(ckpt)
        assert state["format"] == FORMAT, ckpt


def test_format_1_defaults(tmp_path):
    """A minimal format-1 training checkpoint gets the values the format-1 code used."""
    old = {"format": LEGACY_TAG, "config": {"seed": 3, "algo": {"name": "td3", "critic_lookahead": True},
                                            "env": {"dt": 0.25}, "train": {}},
           "actor": {}, "frames": 0, "updates": 0, "torch_rng": torch.get_rng_state()}
    torch.save(old, tmp_path / "old.pt")
    state = load_checkpoint(tmp_path / "old.pt")
    algo, train = state["config"]["algo"], state["config"]["train"]
    assert algo["actor_squash"] == "box" and algo["per_weights"] is False
    assert algo["critic_lookahead"] == 0.25  # a flag for one env step
    assert (algo["exploration"], algo["n_steps"], train["progress_reward"], train["human_dropout"]) == \
        ("gaussian", 1, 0.0, 0.0)
    assert state["wall_time_s"] == 0.0
    assert torch.equal(state["replay_rng"], torch.Generator().manual_seed(3).get_state())
    assert state["config"]["env"]["humans"] == "replay" and state["config"]["env"]["reactive"]["model"] == "orca"
    save_checkpoint(tmp_path / "new.pt", state)  # re-saved: the current format, no upgrade needed
    again = torch.load(tmp_path / "new.pt", map_location="cpu", weights_only=True)
    assert again["format"] == FORMAT and again["config"] == state["config"]


def test_a_newer_format_is_a_one_line_error(tmp_path):
    path = tmp_path / "future.pt"
    torch.save({"format": FORMAT + 1, "config": {}, "actor": {}, "frames": 0}, path)
    with pytest.raises(CheckpointError, match=rf"has format {FORMAT + 1}, newer than this crowdbench reads") as e:
        load_checkpoint(path)
    assert "\n" not in str(e.value)


def test_a_foreign_format_tag_is_refused(tmp_path):
    path = tmp_path / "foreign.pt"
    torch.save({"format": "someone-else-v3", "config": {}, "actor": {}, "frames": 0}, path)
    with pytest.raises(CheckpointError, match="not a crowdbench checkpoint"):
        load_checkpoint(path)


def test_format_4_fills_the_warm_start_keys_with_the_schema_defaults():
    """An older run trained without the imitation warm start: its config gets the keys with the values
    the schema gives a run that does not pretrain (so a resumed or compared config matches today's)."""
    from crowdbench.algos.checkpoint import PRETRAIN_DEFAULTS
    from crowdbench.config_schema import TrainConfig

    schema = {f.name: f.default for f in fields(TrainConfig) if f.name.startswith("pretrain")}
    assert PRETRAIN_DEFAULTS == schema
    state = load_checkpoint(SHIPPED)
    assert {k: state["config"]["train"][k] for k in schema} == schema


def test_format_6_runs_had_no_checkpoint_expert():
    shipped = ROOT / "leaderboard" / "submissions" / "sarl_value_query_s0" / "checkpoint.pt"
    raw = torch.load(shipped, map_location="cpu", weights_only=True)
    assert raw["format"] == 6 and "pretrain_checkpoint" not in raw["config"]["train"]
    assert load_checkpoint(shipped)["config"]["train"]["pretrain_checkpoint"] is None


def test_formats_5_and_6_keep_older_runs_on_the_similarity_slots_and_scores_they_trained_with(tmp_path):
    """RGL's cosine similarity and the compacted slots became defaults in format 5: a format-4 RGL run
    (the shipped rgl_bilinear_td3_s0) had the embedded-Gaussian similarity and full slots; values stored
    in a checkpoint are never replaced."""
    shipped = ROOT / "leaderboard" / "submissions" / "rgl_bilinear_td3_s0" / "checkpoint.pt"
    raw = torch.load(shipped, map_location="cpu", weights_only=True)
    assert raw["format"] == 4 and "similarity" not in raw["config"]["encoder"]
    enc = load_checkpoint(shipped)["config"]["encoder"]
    assert (enc["similarity"], enc["scale"], enc["compact"]) == ("embedded_gaussian", 5.0, False)
    for name, extra in (("sarl", {}), ("dsrnn", {}), ("rgl", {"similarity": "cosine", "scale": 2.0, "compact": True})):
        torch.save({"format": 4, "config": {"encoder": {"name": name, **extra}}, "actor": {}, "frames": 0},
                   tmp_path / f"{name}.pt")
        got = load_checkpoint(tmp_path / f"{name}.pt")["config"]["encoder"]
        assert got == {"name": name, "compact": False, **({"similarity": "embedded_gaussian", "scale": 5.0}
                                                          if name == "rgl" else {"score_cap": None}), **extra}
    for fmt in (4, 5):  # format 6: unbounded attention scores, GAT without a compaction key
        torch.save({"format": fmt, "config": {"encoder": {"name": "gat"}}, "actor": {}, "frames": 0}, tmp_path / "g.pt")
        assert load_checkpoint(tmp_path / "g.pt")["config"]["encoder"] == {"name": "gat", "score_cap": None}
    torch.save({"format": 5, "config": {"encoder": {"name": "gat", "score_cap": 5.0}}, "actor": {}, "frames": 0},
               tmp_path / "c.pt")
    assert load_checkpoint(tmp_path / "c.pt")["config"]["encoder"]["score_cap"] == 5.0
