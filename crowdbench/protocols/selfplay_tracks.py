"""The self-play leaderboard tracks and their published episode lists.

A track is one setting: a scenario, an agent count and, for one track, reactive humans placed among the
agents. Its episodes are the ones ``crowdbench eval env=selfplay`` draws for that setting
(:func:`crowdbench.envs.selfplay.episode_set`, seed ``EVAL_SEED``, ``EPISODES`` episodes), saved once as
``crowdbench/data/selfplay_v1/<setting>.json`` with the geometry they were drawn with, and checked against
their published sha256 (``crowdbench/protocols/lists.py``) before every evaluation. Why saved rather than
only regenerated: a change of torch's generator or of the placement code would otherwise move every
number silently; with the files it is a failed hash check (``tests/test_selfplay_tracks.py`` regenerates
them). The coordinates are float32 written with the fewest digits that read back to the same float32,
so evaluating the file gives the same episodes, bit for bit, as drawing them.

Square crossing of 32 agents does not fit the 8 m square (``n * min_spacing <= 2 * width``): every track
sets ``env.scale_geometry=true``, which widens the square to ``n * min_spacing / 2`` (12.8 m) and lengthens
the time limit in proportion (160 steps); the tracks of up to 20 bodies are unchanged by it.
"""

from __future__ import annotations

import re
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from crowdbench.envs.selfplay import SelfPlayConfig, episode_set

LIST_DIR = Path(__file__).resolve().parents[1] / "data" / "selfplay_v1"
EVAL_SEED = 20261122  # env.eval_seed's default: the tracks' episodes are crowdbench eval's
EPISODES = 100
SETTING = re.compile(r"^(circle|square)_n([1-9][0-9]*)(?:_(orca|sfm)([1-9][0-9]*))?$")
# the geometry a list was drawn with: the list records it, the evaluation refuses a config that differs
GEOMETRY = ("scenario", "n_agents", "n_humans", "humans", "circle_radius", "square_width", "jitter", "min_spacing",
            "time_limit", "robot_radius", "human_radius", "robot_visible")
KEYS = ("start", "goal", "human_start", "human_goal")
# (setting, title): the order of the leaderboard's self-play tracks
SETTINGS = (
    *((f"circle_n{n}", f"self-play circle crossing, {n} agents") for n in (4, 8, 16, 32)),
    *((f"square_n{n}", f"self-play square crossing, {n} agents") for n in (4, 8, 16, 32)),
    ("circle_n8_orca4", "self-play circle crossing, 8 agents and 4 reactive ORCA humans among them"),
)


def parse_setting(name: str) -> tuple[str, int, str, int]:
    """``circle_n8_orca4`` -> ``("circle", 8, "orca", 4)``; ``square_n16`` -> ``("square", 16, "orca", 0)``."""
    m = SETTING.match(str(name))
    if not m:
        raise ValueError(f"unknown self-play setting {name!r}; valid: circle_n<agents> or square_n<agents>, "
                         "optionally _orca<humans> / _sfm<humans>, e.g. circle_n8_orca4")
    return m.group(1), int(m.group(2)), m.group(3) or "orca", int(m.group(4) or 0)


def track_name(setting: str) -> str:
    return "selfplay-" + setting.replace("_n", "").replace("_", "-")


def setting_overrides(setting: str) -> tuple[str, ...]:
    """The Hydra overrides of ``crowdbench eval env=selfplay`` that evaluate ``setting``'s episodes."""
    scenario, n, humans, h = parse_setting(setting)
    return ("env=selfplay", f"env.scenario={scenario}", f"env.n_agents={n}", f"env.n_humans={h}",
            f"env.humans={humans}", "env.scale_geometry=true", f"env.eval_scenarios=[{scenario}]",
            f"env.eval_n_agents=[{n}]", f"env.eval_episodes={EPISODES}", f"env.eval_seed={EVAL_SEED}")


def setting_config(setting: str, base: SelfPlayConfig | None = None) -> SelfPlayConfig:
    """``base`` (default: the defaults of ``env=selfplay``) set to ``setting``, geometry scaled."""
    scenario, n, humans, h = parse_setting(setting)
    return replace(base or SelfPlayConfig(), scenario=scenario, n_agents=n, n_humans=h, humans=humans,
                   scale_geometry=True)


def geometry(cfg: SelfPlayConfig) -> dict:
    return {k: v for k, v in asdict(cfg).items() if k in GEOMETRY}


def _f32(x: torch.Tensor) -> list:
    """Nested lists of the float32 values, each with the fewest digits that read back to it."""
    return np.vectorize(lambda v: float(str(v)), otypes=[float])(x.numpy().astype(np.float32)).tolist()


def generate(setting: str) -> dict:
    """``setting``'s published list, drawn again: ``EPISODES`` episodes of seed ``EVAL_SEED``."""
    cfg = setting_config(setting)
    eps = episode_set(cfg, EPISODES, EVAL_SEED)
    keys = [k for k in KEYS if k in eps]
    return {"protocol": "selfplay-v1", "setting": setting, "seed": EVAL_SEED, "geometry": geometry(cfg),
            "episodes": [{"episode": i, **{k: _f32(eps[k][i]) for k in keys}} for i in range(EPISODES)]}


def list_path(setting: str) -> Path:
    parse_setting(setting)
    return LIST_DIR / f"{setting}.json"


def episodes_of(saved: dict, cfg: SelfPlayConfig, episodes: int | None = None) -> dict[str, torch.Tensor]:
    """The episodes of a saved list as the env takes them (``episodes``: the first ``n``, a quick check),
    refused if ``cfg``'s geometry is not the list's (one line naming the fields)."""
    diff = sorted(k for k, v in saved["geometry"].items() if geometry(cfg).get(k) != v)
    if diff:
        raise ValueError(f"self-play list {saved['setting']}: env.{', env.'.join(diff)} differ from the geometry "
                         "the list was drawn with")
    rows = saved["episodes"][: episodes or None]
    out = {k: torch.tensor([r[k] for r in rows], dtype=torch.float32) for k in KEYS if k in rows[0]}
    out["t0"] = torch.zeros(len(rows), dtype=torch.long)
    return out
