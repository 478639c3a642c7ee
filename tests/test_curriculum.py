"""The curriculum over agent counts (train.curriculum_agents / curriculum_frames, crowdbench/algos/curriculum.py):
its stages, its one-line errors, and a MAPPO run that trains each stage with its agents and resumes as if it
had never stopped, at a stage's end and inside a stage."""

import csv

import pytest
import torch

from crowdbench.algos.curriculum import CurriculumError, stage_of, stages
from crowdbench.algos.ppo import PPO
from crowdbench.algos.train import train
from crowdbench.cli import compose, main
from crowdbench.envs.observation import OBS

SELFPLAY = ["experiment=selfplay", "method=gatedgcn_mappo", "env.batch=2", "train.frames_per_batch=32",
            "train.max_minutes=null", "env.n_agents=3", "env.eval_n_agents=[3]", "env.eval_episodes=2"]
CURRICULUM = ["train.curriculum_agents=[2]", "train.curriculum_frames=[64]"]


def test_stages_follow_the_config():
    assert stages(compose([*SELFPLAY, "train.total_frames=128"])) == [(3, 128)]  # no curriculum: one stage
    plan = stages(compose([*SELFPLAY, *CURRICULUM, "train.total_frames=128"]))
    assert plan == [(2, 64), (3, 128)]
    assert [stage_of(plan, f) for f in (0, 32, 63, 64, 127, 128, 500)] == [0, 0, 0, 1, 1, 1, 1]
    two = ["train.curriculum_agents=[2,4]", "train.curriculum_frames=[64,96]"]
    assert stages(compose([*SELFPLAY, *two, "train.total_frames=128"])) == [(2, 64), (4, 96), (3, 128)]
    # a budget that ends inside a stage ends the plan there
    assert stages(compose([*SELFPLAY, *two, "train.total_frames=80"])) == [(2, 64), (4, 80)]
    assert stages(compose([*SELFPLAY, *two, "train.total_frames=64"])) == [(2, 64)]


@pytest.mark.parametrize("args, message", [
    ([*SELFPLAY, "train.curriculum_agents=[2]"], "train.curriculum_agents has 1 entries and train.curriculum_frames 0"),
    ([*SELFPLAY, "train.curriculum_agents=[2,4]", "train.curriculum_frames=[96,64]"], "must increase"),
    ([*SELFPLAY, "train.curriculum_agents=[2]", "train.curriculum_frames=[50]"],
     "multiples of train.frames_per_batch (32)"),
    ([*CURRICULUM, "algo=ppo", "train.frames_per_batch=32"], "needs env=selfplay"),
    ([*SELFPLAY, *CURRICULUM, "method=gatedgcn_td3"], "needs an on-policy algorithm (ppo, ippo, mappo): algo=td3"),
    ([*CURRICULUM, "env=crowdnav", "algo=value"], "needs env=selfplay"),
])
def test_a_curriculum_that_cannot_run_is_one_line_before_any_directory(args, message, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", *args, "train.total_frames=128", f"out={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()
    with pytest.raises(CurriculumError, match="must increase"):
        stages(compose([*SELFPLAY, "train.curriculum_agents=[2,4]", "train.curriculum_frames=[64,64]"]))


def agents_seen(monkeypatch) -> list[tuple[int, int]]:
    """(agents in the batch's observation, algo.n_agents) of every batch PPO learns from."""
    seen = []
    learn = PPO.learn

    def spy(self, batch):
        seen.append((batch[OBS + ("robot",)].shape[-2], self.n_agents))
        return learn(self, batch)

    monkeypatch.setattr(PPO, "learn", spy)
    return seen


def logged(run, name: str) -> list[tuple[int, float]]:
    with open(run / "logs" / "scalars" / f"{name}.csv") as f:
        return [(int(r[0]), float(r[1])) for r in csv.reader(f)]


@pytest.mark.parametrize("stop", [64, 96])  # at the first stage's end; inside the second stage
def test_each_stage_trains_with_its_agents_and_a_resume_continues_in_its_stage(stop, tmp_path, monkeypatch):
    seen = agents_seen(monkeypatch)
    whole = tmp_path / "whole"
    train(compose([*SELFPLAY, *CURRICULUM, "train.total_frames=128", f"out={whole}"]), whole, progress=False)
    assert seen == [(2, 2), (2, 2), (3, 3), (3, 3)]  # 2 agents until 64 frames, then env.n_agents
    assert logged(whole, "agents") == [(32, 2.0), (64, 2.0), (96, 3.0), (128, 3.0)]

    seen.clear()
    part = tmp_path / "part"
    train(compose([*SELFPLAY, *CURRICULUM, f"train.total_frames={stop}", f"out={part}"]), part, progress=False)
    train(compose([*SELFPLAY, *CURRICULUM, "train.total_frames=128", f"out={part}"]), part, resume=True,
          progress=False)
    assert seen == [(2, 2)] * 2 + [(3, 3)] * 2  # the resumed run builds the env of the stage it is in
    assert logged(part, "agents") == logged(whole, "agents")
    a, b = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (whole, part))
    assert a["frames"] == b["frames"] == 128 and a["updates"] == b["updates"] and a["stage"] == b["stage"] == 1
    if stop == 64:
        # stopped at a stage's end: the next stage starts a fresh env in both runs, so the resumed run is the
        # uninterrupted one bit for bit (inside a stage, as for any on-policy run, the envs restart their episodes)
        for k, v in a["actor"].items():
            assert torch.equal(v, b["actor"][k]), k
