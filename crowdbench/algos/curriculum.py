"""A curriculum over the number of agents in self-play (``train.curriculum_agents``, ``train.curriculum_frames``).

Stage ``i`` trains with ``curriculum_agents[i]`` agents per environment until ``curriculum_frames[i]`` env
frames; from the last of them on, with ``env.n_agents``. Stages are set by frames, not by wall time, so a seed
gives the same run on any machine and a resumed run rebuilds the stage its frames are in. Only for algorithms
whose learning does not keep the observation's shape across batches (on-policy ones: each batch is learnt
and dropped): a replay buffer holds observations of ``A - 1`` other agents, fixed by its first batch.
Why: Long et al. (2018) trained their shared policy on few robots first, then on many.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf


class CurriculumError(ValueError):
    """A curriculum that cannot be run: one line naming the key."""


def stages(cfg: DictConfig) -> list[tuple[int, int]]:
    """``[(n_agents, end_frames), ...]``: the run's stages in order, the last ending at ``train.total_frames``."""
    t = cfg.train
    agents = [int(n) for n in (t.get("curriculum_agents") or [])]
    ends = [int(f) for f in (t.get("curriculum_frames") or [])]
    if not agents and not ends:
        return [(int(cfg.env.get("n_agents", 1)), int(t.total_frames))]
    if len(agents) != len(ends):
        raise CurriculumError(f"train.curriculum_agents has {len(agents)} entries and train.curriculum_frames "
                              f"{len(ends)}: one end (in frames) per stage")
    if "n_agents" not in cfg.env:  # an env whose agents all learn (env.n_agents)
        raise CurriculumError(f"train.curriculum_agents needs env=selfplay (agents that learn), got env={cfg.env.name}")
    fpb = int(t.frames_per_batch)
    for i, end in enumerate(ends):
        if end % fpb or end <= (ends[i - 1] if i else 0):
            raise CurriculumError(f"train.curriculum_frames must increase and be multiples of train.frames_per_batch "
                                  f"({fpb}), got {ends}")
    plan = list(zip(agents, ends, strict=True)) + [(int(cfg.env.n_agents), int(t.total_frames))]
    out, begin = [], 0
    for n, end in plan:  # the stages that start before total_frames, the last cut there
        if begin >= t.total_frames:
            break
        out.append((n, min(end, int(t.total_frames))))
        begin = end
    return out


def with_agents(cfg: DictConfig, n: int) -> DictConfig:
    """``cfg`` with ``env.n_agents = n`` (the stage's env; everything else as configured)."""
    if int(cfg.env.n_agents) == n:
        return cfg
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    out.env.n_agents = n
    return out


def stage_of(plan: list[tuple[int, int]], frames: int) -> int:
    """The index of the stage ``frames`` collected frames are in (the last one once they are all done)."""
    return next((i for i, (_, end) in enumerate(plan) if frames < end), len(plan) - 1)
