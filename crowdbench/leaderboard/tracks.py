"""Leaderboard tracks: the protocols every entry is evaluated on, and the tables of each. Each protocol of
the registry (crowdbench/protocols/) defines its tracks; this module reads them from there.

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
from collections.abc import Mapping, Sequence

from crowdbench.protocols import ProtocolError, get, of_config, tracks
from crowdbench.protocols.base import Track

__all__ = ["TRACKS", "TRACK_ORDER", "Track", "check_tracks", "evaluate_track", "track_config", "trained_track",
           "units"]


class _Tracks(Mapping):
    """Every registered protocol's tracks by name, read when asked (a protocol registered later has its own)."""

    def __getitem__(self, name: str) -> Track:
        return tracks()[name]

    def __iter__(self):
        return iter(tracks())

    def __len__(self) -> int:
        return len(tracks())


class _Order(Sequence):
    """The tracks' names in registration order (tables, the default ``--tracks``)."""

    def __getitem__(self, i):
        return tuple(tracks())[i]

    def __len__(self) -> int:
        return len(tracks())

    def __repr__(self) -> str:
        return repr(tuple(tracks()))


TRACKS: Mapping[str, Track] = _Tracks()
TRACK_ORDER: Sequence[str] = _Order()


def check_tracks(names) -> list[str]:
    names = list(names or TRACK_ORDER)
    unknown = [n for n in names if n not in TRACKS]
    if unknown:
        raise ValueError(f"unknown track(s) {', '.join(unknown)}; valid: {', '.join(TRACK_ORDER)}")
    return [n for n in TRACK_ORDER if n in names]


def trained_track(cfg: dict) -> str | None:
    """The track a checkpoint's training config (``env``) corresponds to, or None (self-play, other settings)."""
    env = cfg.get("env") or {}
    try:
        return of_config(env).trained_track(env)
    except (ProtocolError, ValueError, TypeError):  # an env no protocol evaluates
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


def evaluate_track(track: Track, policy, scenes: list[str], episodes: int | None, out_dir, meta: dict,
                   save_episodes: bool = True) -> dict:
    """Evaluate ``policy`` on ``track`` (``scenes``: per-scene tracks only) into ``out_dir`` with episodes."""
    return get(track.protocol).evaluate_track(track, policy, scenes, episodes, out_dir, meta,
                                              env=track_config(track)["env"], save_episodes=save_episodes)


def units(track: Track, scenes: list[str]) -> list[str]:
    """The result keys of ``track``: the scenes of a replay track, the one setting of a CrowdNav track."""
    return track.evaluator.units(track, scenes)
