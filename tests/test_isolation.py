"""Submissions run in isolated workers: malicious or broken encoder code cannot change another row.

Each hostile submission below ships its code as ``evil.py`` (the same module name for all of them:
each worker is a fresh interpreter). The straight-to-goal row must come out byte-identical to a run
without them, every hostile one must be rejected in one line, and the table must be written.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from crowdbench.algos.actors import build_actor
from crowdbench.algos.checkpoint import save_checkpoint
from crowdbench.leaderboard import run
from crowdbench.leaderboard.sandbox import Limits, bubblewrap
from crowdbench.leaderboard.worker import WorkerError, WorkerPolicy
from crowdbench.models import ENCODERS

FAST = {"episodes": 3, "scenes": ["hotel"], "tracks": ["v1"]}
LIMITS = Limits(step_s=20.0, load_s=120.0, memory_gb=6.0)

ENCODER = '''
import torch
from torch import nn


class Enc(nn.Module):
    def __init__(self, dim=8):
        super().__init__()
        self.out_dim = dim
        self.lin = nn.Linear(6, dim)

    def forward(self, robot, humans=None, humans_mask=None):
        if isinstance(robot, dict) or hasattr(robot, "keys"):
            robot = robot["robot"]
        h = torch.relu(self.lin(robot))
        return h.unsqueeze(-2), h
'''

# name -> (code appended to the encoder module, what the one-line rejection says)
HOSTILE = {
    # the finding: a module that rewrites the metrics turned straight's 0.8 into 1.0 on hotel
    "patcher": ('''
import crowdbench.protocols.replay as ev
_orig = ev.episode_metrics
def _all_success(*a, **k):
    m = _orig(*a, **k)
    m["success"] = torch.ones_like(m["success"])
    m["outcome"] = torch.ones_like(m["outcome"])
    return m
ev.episode_metrics = _all_success
import crowdbench.leaderboard.harness as h
h.evaluate_submission = lambda *a, **k: {}
''', None),
    "exit0": ("raise SystemExit(0)\n", "the worker exited with code 0 while loading"),
    "exit3": ('''
import os
_f = Enc.forward
def _exit(self, robot, *a, **k):
    if robot.shape[0] > 2:
        os._exit(3)
    return _f(self, robot, *a, **k)
Enc.forward = _exit
''', "the worker exited with code 3 while acting at step 0"),
    "hang": ('''
_f = Enc.forward
def _hang(self, robot, *a, **k):
    while robot.shape[0] > 2:
        pass
    return _f(self, robot, *a, **k)
Enc.forward = _hang
''', "the worker did not answer within 3 s (acting at step 0)"),
    "nan": ('''
_f = Enc.forward
def _nan(self, robot, *a, **k):
    h, r = _f(self, robot, *a, **k)
    return (h, r * float("nan")) if robot.shape[0] > 2 else (h, r)
Enc.forward = _nan
''', "returned a non-finite action at step 0 (environment 0, agent 0)"),
    "hog": ("_hoard = [bytearray(1 << 28) for _ in range(1 << 12)]\n", "MemoryError"),
    "writer": ('''
from pathlib import Path
import crowdbench
root = Path(crowdbench.__file__).parent
# (crowdbench's own files are bound read-only; the leaderboard under /tmp is not even visible)
for target in (root / "eval.py", Path(__file__).parents[2] / "results" / "straight" / "results.json"):
    target.write_text("{}")
''', "Read-only file system"),
    "printer": ('''
import sys
print("x" * 100000)
sys.stdout.write("\\0\\0\\0\\1garbage")
sys.stdout.flush()
''', None),
}


def make_learned(root: Path, name: str, code: str) -> None:
    d = root / "submissions" / name
    d.mkdir(parents=True)
    (d / "submission.yaml").write_text(
        f"name: {name}\nkind: learned\nentry: {name}\nencoder: evil\nencoder_import: evil:Enc\nalgo: td3\n"
        "authors: [mallory]\n")
    (d / "evil.py").write_text(code)
    ns: dict = {}
    exec(compile(ENCODER, "enc", "exec"), ns)  # noqa: S102 - the benign class, to write a checkpoint it loads into
    ENCODERS["evil"] = ns["Enc"]
    try:
        torch.manual_seed(0)
        actor = build_actor("td3", {"name": "evil", "dim": 8}, 1.0, squash="radial")
    finally:
        del ENCODERS["evil"]
    save_checkpoint(d / "checkpoint.pt", {"config": {"algo": {"name": "td3", "actor_squash": "radial"},
                                                     "encoder": {"name": "evil", "dim": 8},
                                                     "env": {"v_max": 1.0, "frame": "rotate"}},
                                          "actor": actor.state_dict(), "frames": 0})


def add_straight(root: Path) -> None:
    d = root / "submissions" / "straight"
    d.mkdir(parents=True)
    (d / "submission.yaml").write_text("name: straight\nkind: baseline\nentry: Straight to goal\npolicy: straight\n"
                                       "authors: [crowdbench]\n")


@pytest.mark.slow
def test_hostile_submissions_cannot_change_another_row(tmp_path):
    """Confined where bubblewrap works; without it every hostile case but the file writer (whose
    protection is the read-only file system) still applies."""
    hostile = HOSTILE if bubblewrap() is not None else {k: v for k, v in HOSTILE.items() if k != "writer"}
    clean = tmp_path / "clean"
    add_straight(clean)
    make_learned(clean, "honest", ENCODER)
    assert run(clean, log=lambda m: None, **FAST) == 0
    reference = (clean / "results" / "straight" / "results.json").read_text()

    root = tmp_path / "hostile"
    add_straight(root)
    make_learned(root, "honest", ENCODER)
    for name, (code, _) in hostile.items():
        make_learned(root, name, ENCODER + code)
    import crowdbench.protocols.replay

    eval_src = Path(crowdbench.protocols.replay.__file__).read_text()
    log: list[str] = []
    limits = Limits(step_s=3.0, load_s=120.0, memory_gb=6.0)
    assert run(root, log=log.append, limits=limits, **FAST) == 1
    errors = [m for m in log if "error" in m]
    for name, (_, says) in hostile.items():
        mine = [m for m in errors if f"submissions/{name}/" in m]
        if says is None:  # harmless once isolated: evaluated like any other entry
            assert not mine and (root / "results" / name / "results.json").is_file(), (name, mine)
            continue
        assert len(mine) == 1 and says in mine[0] and "\n" not in mine[0] and len(mine[0]) < 400, (name, mine)
    assert (root / "results" / "straight" / "results.json").read_text() == reference
    assert Path(crowdbench.protocols.replay.__file__).read_text() == eval_src
    honest = json.loads((root / "results" / "honest" / "results.json").read_text())
    assert honest["episode_outcomes"] == json.loads((clean / "results" / "honest" / "results.json").read_text())[
        "episode_outcomes"]
    readme = (root / "README.md").read_text()
    assert "Straight to goal" in readme and "exit0" in readme.split("## Rejected")[1]


@pytest.mark.slow
def test_two_submissions_with_one_module_name_each_get_their_own(tmp_path):
    """Finding 3: the second `evil.py` was evaluated with the first one's class (sys.modules)."""
    root = tmp_path / "lb"
    make_learned(root, "a", ENCODER)
    make_learned(root, "b", ENCODER + "\nclass Enc(Enc):\n    def forward(self, robot, *a, **k):\n"
                                      "        h, r = super().forward(robot, *a, **k)\n        return h, r + 100.0\n")
    acts = {}
    obs = _obs()
    for name in ("a", "b"):
        with WorkerPolicy(root / "submissions" / name, name, LIMITS) as p:
            acts[name] = p.act(obs)
    assert not torch.equal(acts["a"], acts["b"])


def _obs():
    from crowdbench.leaderboard.loading import dummy_obs

    return dummy_obs(batch=4, humans=3)


def test_worker_actions_equal_in_process_actions(tmp_path):
    """The round trip changes no bit: the same actor in-process and behind the pipe."""
    from crowdbench.policies import from_checkpoint

    root = tmp_path / "lb"
    shutil.copytree(Path(__file__).resolve().parents[1] / "leaderboard" / "submissions" / "gatedgcn_td3_s0",
                    root / "submissions" / "gatedgcn_td3_s0")
    obs = _obs()
    with WorkerPolicy(root / "submissions" / "gatedgcn_td3_s0", "g", LIMITS) as p:
        remote = p.act(obs)
        assert p.frame == "rotate"
    local = from_checkpoint(root / "submissions" / "gatedgcn_td3_s0" / "checkpoint.pt").act(obs)
    assert torch.equal(remote, local)


@pytest.mark.slow
def test_a_missing_checkpoint_is_the_field_not_a_crash(tmp_path):
    root = tmp_path / "lb"
    make_learned(root, "a", ENCODER)
    (root / "submissions" / "a" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(WorkerError) as e:
        WorkerPolicy(root / "submissions" / "a", "a", LIMITS)
    assert e.value.field == "checkpoint"


@pytest.mark.slow
def test_a_checkpoint_with_an_unknown_frame_is_rejected_by_its_worker(tmp_path):
    """Finding 4: `env.frame: polar` in a checkpoint aborted the whole leaderboard."""
    from crowdbench.algos.checkpoint import load_checkpoint

    root = tmp_path / "lb"
    make_learned(root, "polar", ENCODER)
    ckpt = root / "submissions" / "polar" / "checkpoint.pt"
    state = load_checkpoint(ckpt)
    state["config"]["env"]["frame"] = "polar"
    save_checkpoint(ckpt, state)
    add_straight(root)
    log: list[str] = []
    assert run(root, log=log.append, limits=LIMITS, **FAST) == 1
    (line,) = [m for m in log if "error" in m]
    assert "submissions/polar/submission.yaml: field 'checkpoint'" in line and "env.frame 'polar'" in line
    assert (root / "results" / "straight" / "results.json").is_file() and (root / "README.md").is_file()
