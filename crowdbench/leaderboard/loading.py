"""Loading a learned submission: its checkpoint read and checked against submission.yaml, its policy
built and tried on an observation. Runs in the submission's worker process (crowdbench/leaderboard/worker.py),
never in the harness: it imports the submission's encoder module."""

from __future__ import annotations

import torch

from crowdbench import policies
from crowdbench.envs.rules import FRAMES
from crowdbench.leaderboard.encoders import register_encoder
from crowdbench.leaderboard.submission import Submission, SubmissionError
from crowdbench.leaderboard.tracks import trained_track


def dummy_obs(batch: int = 2, humans: int = 3):
    from crowdbench.envs.observation import obs_tensordict

    g = torch.Generator().manual_seed(0)
    robot = torch.zeros(batch, 1, 6)
    robot[..., 4] = 4.0
    h = torch.randn(batch, 1, humans, 4, generator=g)
    mask = torch.ones(batch, 1, humans, dtype=torch.bool)
    return obs_tensordict({"robot": robot, "humans": h, "humans_mask": mask}, batch)


def learned_policy(sub: Submission):
    """A learned submission's policy, validated; runs in its worker process (:func:`worker._serve`),
    never in the harness: it imports the submission's encoder module."""
    from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint

    d, path = sub.data, sub.yaml_path
    register_encoder(sub)
    try:
        state = load_checkpoint(sub.checkpoint)  # weights_only=True: never runs pickled code
    except CheckpointError as e:
        raise SubmissionError(path, "checkpoint", str(e)) from None
    cfg = state["config"]
    try:
        c_enc, c_algo = cfg["encoder"]["name"], cfg["algo"]["name"]
        _, frame = cfg["env"]["v_max"], cfg["env"]["frame"]
    except (KeyError, TypeError) as e:
        raise SubmissionError(path, "checkpoint", f"{sub.checkpoint}: config lacks {e}") from None
    if frame not in FRAMES:
        raise SubmissionError(path, "checkpoint", f"{sub.checkpoint}: env.frame {str(frame)[:40]!r} is not one of "
                                                  f"{', '.join(FRAMES)}")
    if c_enc != d["encoder"]:
        raise SubmissionError(path, "encoder", f"{d['encoder']!r} but the checkpoint was trained with {c_enc!r}")
    if c_algo != d["algo"]:
        raise SubmissionError(path, "algo", f"{d['algo']!r} but the checkpoint was trained with {c_algo!r}")
    look = cfg["algo"].get("lookahead") if c_algo == "value" else None  # (cfg["algo"]["name"] read: a mapping)
    if look != d.get("lookahead"):
        raise SubmissionError(path, "lookahead", f"{d.get('lookahead')!r} but the checkpoint acts with lookahead {look!r}")
    net = cfg["algo"].get("net") if c_algo == "value" else None
    if net != d.get("net"):
        raise SubmissionError(path, "net", f"{d.get('net')!r} but the checkpoint's value network is {net!r}")
    home, got = d.get("track", "v1"), trained_track(cfg)
    if got != home:
        raise SubmissionError(path, "track", f"{home!r} but the checkpoint was trained on "
                                             f"{repr(got) if got else 'an env that is no leaderboard track'}")
    try:
        policy = policies.from_checkpoint(sub.checkpoint)
    except policies.PolicyError as e:
        raise SubmissionError(path, "checkpoint", str(e)) from None
    obs = dummy_obs()
    look = getattr(policy, "lookahead", None)
    if look is not None:  # a value-lookahead policy reads candidates with its observation
        from crowdbench.envs.lookahead import placeholder_candidates
        from crowdbench.envs.observation import OBS

        for key, value in placeholder_candidates(obs[OBS], look[1], float(cfg["env"].get("dt", 0.25))).items():
            obs.set(OBS + (key,), value)
    try:
        out = policy.act(obs)
    except Exception as e:  # noqa: BLE001 - a model that cannot act on an observation is rejected
        raise SubmissionError(path, "checkpoint", f"the model fails on an observation: {type(e).__name__}: {e}") \
            from None
    if tuple(out.shape) != (2, 1, 2) or not torch.isfinite(out).all():
        raise SubmissionError(path, "checkpoint", f"the model returns actions of shape {tuple(out.shape)} "
                                                  "(expected [B, 1, 2], finite)")
    return policy
