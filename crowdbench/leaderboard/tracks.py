"""Leaderboard tracks: the protocols every entry is evaluated on, and the tables of each.

=====================  =========================================================================
track                  protocol
=====================  =========================================================================
``v1``                 replayed ETH/UCY pedestrians who never yield (the paper's protocol, frozen)
``v2-orca``            reactive replay: the same episodes, the humans yield through ORCA
``v2-sfm``             reactive replay, social-force humans
``crowdnav-circle5``   CrowdNav circle crossing, 5 ORCA humans, invisible robot (its Table I)
``crowdnav-circle20``  the same with 20 humans
``crowdnav-square5``   CrowdNav square crossing, 5 humans
=====================  =========================================================================

Every submission is evaluated on every track it fits: every robot policy fits all of them; the
privileged entries (the oracle, value-lookahead entries that read the simulator's next human states)
only the tracks where the humans' future does not depend on the robot (v1, whose humans are a
recording, and CrowdNav with its invisible robot), not reactive replay. A learned
submission names the track it was trained on (``track``, default ``v1``; the harness checks it
against the checkpoint's config): each track's table lists the baselines, the oracle where it
applies and the entries trained on that track; the transfer table lists every learned entry on every
track. Baselines are built with each track's own settings (CrowdNav's ORCA on CrowdNav tracks).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

TRACK_ORDER = ("v1", "v2-orca", "v2-sfm", "crowdnav-circle5", "crowdnav-circle20", "crowdnav-square5")


@dataclass(frozen=True)
class Track:
    name: str
    title: str
    protocol: str  # v1 | v2 | crowdnav-v1
    humans: str | None = None  # v2: the reactive model
    setting: str | None = None  # CrowdNav: e.g. circle_n5

    @property
    def privileged_ok(self) -> bool:
        """The oracle's plan is privileged knowledge only where the humans' future ignores the robot."""
        return self.protocol != "v2"

    @property
    def replay(self) -> bool:
        return self.protocol in ("v1", "v2")

    @property
    def results_file(self) -> str:
        return "results.json" if self.name == "v1" else f"{self.name}.json"

    @property
    def config_overrides(self) -> tuple[str, ...]:
        """The Hydra overrides that give this track's env (and ``orca.*``) to the baselines."""
        if self.replay:
            return ("env.humans=reactive_replay", f"env.reactive.model={self.humans}") if self.humans else ()
        scenario, n = self.setting.split("_n")
        return ("env=crowdnav", f"env.scenario={scenario}", f"env.n_humans={n}")

    def fits(self, kind: str, privileged: bool = False) -> bool:
        """Privileged entries (the oracle, a value entry with the ``query`` lookahead) only where the humans'
        future ignores the robot: there their knowledge is of the task, elsewhere it does not exist."""
        return not (kind == "oracle" or privileged) or self.privileged_ok


TRACKS = {t.name: t for t in (
    Track("v1", "Replay (protocol v1): the recorded ETH/UCY pedestrians, who never yield", "v1"),
    Track("v2-orca", "Reactive replay (protocol v2): the recorded pedestrians yield through ORCA", "v2", "orca"),
    Track("v2-sfm", "Reactive replay (protocol v2): the recorded pedestrians yield through social force", "v2", "sfm"),
    Track("crowdnav-circle5", "CrowdNav circle crossing, 5 ORCA humans, invisible robot", "crowdnav-v1",
          setting="circle_n5"),
    Track("crowdnav-circle20", "CrowdNav circle crossing, 20 ORCA humans, invisible robot", "crowdnav-v1",
          setting="circle_n20"),
    Track("crowdnav-square5", "CrowdNav square crossing, 5 ORCA humans, invisible robot", "crowdnav-v1",
          setting="square_n5"),
)}


def check_tracks(names) -> list[str]:
    names = list(names or TRACK_ORDER)
    unknown = [n for n in names if n not in TRACKS]
    if unknown:
        raise ValueError(f"unknown track(s) {', '.join(unknown)}; valid: {', '.join(TRACK_ORDER)}")
    return [n for n in TRACK_ORDER if n in names]


def trained_track(cfg: dict) -> str | None:
    """The track a checkpoint's training config (``env``) corresponds to, or None (self-play, other settings)."""
    env = cfg.get("env") or {}
    name = env.get("name", "replay")
    if name == "replay":
        if env.get("humans", "replay") == "replay":
            return "v1"
        return f"v2-{(env.get('reactive') or {}).get('model', 'orca')}"
    if name == "crowdnav" and env.get("humans", "orca") == "orca" and not env.get("robot_visible", False):
        track = f"crowdnav-{env.get('scenario', 'circle')}{env.get('n_humans', 5)}"
        return track if track in TRACKS else None
    return None


@functools.cache
def _track_config(overrides: tuple[str, ...]) -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from crowdbench.policies import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return OmegaConf.to_container(compose(config_name="config", overrides=list(overrides)), resolve=True)


def track_config(track: Track) -> dict:
    """The composed config of ``track`` (what ``crowdbench eval`` with its overrides sees), a fresh copy."""
    import copy

    return copy.deepcopy(_track_config(track.config_overrides))


def evaluate_track(track: Track, policy, scenes: list[str], episodes: int | None, out_dir, meta: dict) -> dict:
    """Evaluate ``policy`` on ``track`` (``scenes``: replay tracks only) into ``out_dir`` with episodes."""
    if track.replay:
        from crowdbench.eval import evaluate

        return evaluate(policy, scenes, episodes, out_dir=out_dir, save_episodes=True,
                        sim_overrides={"frame": policy.frame}, meta=meta, humans=track.humans)
    from crowdbench.envs.factory import sim_config
    from crowdbench.eval_crowdnav import evaluate_crowdnav

    cfg = replace(sim_config(track_config(track)["env"]), frame=policy.frame)
    return evaluate_crowdnav(policy, cfg, [track.setting], episodes, out_dir=out_dir, save_episodes=True, meta=meta)


def units(track: Track, scenes: list[str]) -> list[str]:
    """The result keys of ``track``: the scenes of a replay track, the one setting of a CrowdNav track."""
    return list(scenes) if track.replay else [track.setting]
