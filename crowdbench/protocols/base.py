"""What a protocol is, and the registry the factory, the command line and the leaderboard dispatch through.

A :class:`Protocol` bundles everything one evaluation protocol decides: the world it runs in (a name
of :data:`crowdbench.envs.factory.WORLDS`, whose config class types ``env``), its fixed episode lists
and their published hashes, its evaluation (``crowdbench eval``, the leaderboard's tracks), its table,
its training probe and the leaderboard tracks it defines. Nothing outside this package asks which
protocol it has: it asks the protocol (docs/architecture.md, "How to add a protocol").
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

from crowdbench.envs.factory import env_name, sim_config


class ProtocolError(ValueError):
    """An unknown protocol or track name, or a protocol that does not fit the env: one line."""


@dataclass(frozen=True)
class Track:
    """A leaderboard track: one evaluation of ``protocol`` (a registry name) with fixed settings."""

    name: str
    title: str
    protocol: str
    humans: str | None = None  # reactive replay: the crowd model
    setting: str | None = None  # a protocol evaluated per setting (CrowdNav): the one setting

    @property
    def evaluator(self) -> Protocol:
        return get(self.protocol)

    @property
    def label(self) -> str:
        """The protocol's name in results.json (``v1``, ``v2``, ``crowdnav-v1``; the metric table's key)."""
        return self.evaluator.label

    @property
    def privileged_ok(self) -> bool:
        """The oracle's plan is privileged knowledge only where the humans' future ignores the robot."""
        return self.evaluator.privileged_ok

    @property
    def replay(self) -> bool:
        """Its results are per replay scene (``--scenes`` applies), not per setting."""
        return self.evaluator.per_scene

    @property
    def results_file(self) -> str:
        return "results.json" if self.name == "v1" else f"{self.name}.json"

    @property
    def config_overrides(self) -> tuple[str, ...]:
        """The Hydra overrides that give this track's env (and ``orca.*``) to the baselines."""
        return self.evaluator.track_overrides(self)

    def fits(self, kind: str, privileged: bool = False, trained_on: str | None = None) -> bool:
        """Privileged entries (the oracle, a value entry with the ``query`` lookahead) only where the humans'
        future ignores the robot: there their knowledge is of the task, elsewhere it does not exist; and
        only the entries the protocol admits (``trained_on``: a learned entry's training track)."""
        return (not (kind == "oracle" or privileged) or self.privileged_ok) and \
            self.evaluator.admits(kind, trained_on)

    def is_home(self, trained_on: str | None) -> bool:
        """Whether an entry trained on ``trained_on`` belongs in this track's table (not only the transfer table)."""
        return trained_on is not None and trained_on in (self.name, self.evaluator.home)


class Protocol:
    """One protocol. Subclasses set the class attributes and override the methods their protocol needs;
    the defaults are those of a protocol evaluated per setting with no published lists."""

    name = ""  # registry key (``+env.protocol=NAME``)
    label = ""  # results.json's "protocol"; crowdbench/metric_table.py's protocols key
    world = ""  # the world it runs in (crowdbench/envs/factory.py WORLDS)
    command = "eval"  # crowdbench eval's output directory prefix
    tracks: tuple[Track, ...] = ()
    per_scene = False  # results per replay scene (``eval.scenes``) rather than per setting
    privileged_ok = True  # the humans' future ignores the robot: a privileged policy's plan is valid
    # a training track that names the protocol rather than one of its tracks: an entry trained on it is at
    # home on every track of the protocol (self-play trains on mixed crossings of any agent count)
    home: str | None = None
    danger_metric = "dangers_per_episode"  # the x-axis of the tracks' success-against-dangers plot
    oracle_note = "The oracle does not apply: these humans react to the robot, so their future is not known in advance."

    def selects(self, env_cfg) -> bool:
        """Whether an ``env`` config without ``env.protocol`` means this protocol (default: only when named)."""
        return False

    def sim_config(self, env_cfg, **overrides):
        """The typed simulator config of ``env_cfg`` (the world's config class)."""
        return sim_config(env_cfg, **overrides)

    # ------------------------------------------------------------------ crowdbench eval / run
    def check(self, cfg, policy_name: str) -> None:
        """``crowdbench eval``: refuse ``cfg`` (ValueError) before an output directory is claimed."""

    def check_run(self, cfg) -> None:
        """``crowdbench run``: refuse ``cfg`` (ValueError) before training, not after it."""

    def run(self, policy, cfg, out: Path, overrides: list[str], strict: bool = True, progress=None) -> dict:
        """Evaluate ``policy`` per ``cfg`` into ``out`` (``crowdbench eval``, the end of ``crowdbench run``:
        ``strict=False``); ``progress(units, steps)``, if given, is a context manager yielding a recorder
        factory (a progress bar, viz recordings). ValueError for bad input."""
        raise NotImplementedError

    def format_table(self, results: dict) -> str:
        from crowdbench.protocols.engine import format_table

        return format_table(results)

    def probe(self, cfg):
        """The training probe: ``probe(actor) -> {name: value}`` on held-out episodes."""
        raise NotImplementedError

    # ------------------------------------------------------------------ leaderboard
    def evaluate_track(self, track: Track, policy, scenes: list[str], episodes: int | None, out_dir, meta: dict,
                       env=None, save_episodes: bool = True) -> dict:
        """The results of ``policy`` on ``track`` (``scenes``: per-scene protocols; ``env``: the track's composed
        ``env`` config, as ``crowdbench eval`` with the track's overrides sees it), written to ``out_dir``."""
        raise NotImplementedError

    def track_overrides(self, track: Track) -> tuple[str, ...]:
        return ()

    short = ""  # the protocol's name in a plot's title, before the track's setting

    def where(self, track: Track) -> str:
        """What a cell of ``track``'s table is computed over (the tables' and the site's text)."""
        return "average over the four paper scenes" if self.per_scene else f"the setting {track.setting}"

    def units(self, track: Track, scenes: list[str]) -> list[str]:
        """The result keys of ``track``: the scenes of a per-scene protocol, else its one setting."""
        return list(scenes) if self.per_scene else [track.setting]

    def list_files(self, track: Track, scenes: list[str]) -> list[Path]:
        """The episode list files the results of ``track`` on ``scenes`` depend on (hashed into the cache)."""
        return []

    def check_lists(self, scenes: list[str]) -> None:
        """Refuse (:class:`~crowdbench.protocols.lists.ListError`) saved lists that are not the published ones."""

    def check_results(self, results: dict) -> None:
        """Refuse a result computed on lists that are not the published ones."""

    def trained_track(self, env: dict) -> str | None:
        """The track (or :attr:`home`) a training run's ``env`` (a plain dict) corresponds to, or None."""
        return None

    def admits(self, kind: str, trained_on: str | None) -> bool:
        """Whether the leaderboard evaluates an entry of ``kind`` trained on ``trained_on`` on this protocol's
        tracks (default: every entry; the privileged ones are filtered by :meth:`Track.fits`)."""
        return True


REGISTRY: dict[str, Protocol] = {}


def register(protocol: Protocol) -> Protocol:
    """Add ``protocol`` (its name and its tracks' names must be new); returns it."""
    if not protocol.name or protocol.name in REGISTRY:
        raise ProtocolError(f"protocol name {protocol.name!r} is empty or taken; registered: {', '.join(REGISTRY)}")
    clash = [t.name for t in protocol.tracks if t.name in tracks()]
    if clash:
        raise ProtocolError(f"track(s) {', '.join(clash)} of protocol {protocol.name} are taken")
    REGISTRY[protocol.name] = protocol
    return protocol


def unregister(name: str) -> None:
    REGISTRY.pop(name, None)


@contextlib.contextmanager
def registered(protocol: Protocol):
    """``protocol`` registered for the block (a test's protocol; the registry is per process)."""
    register(protocol)
    try:
        yield protocol
    finally:
        unregister(protocol.name)


def names() -> list[str]:
    return list(REGISTRY)


def get(name: str) -> Protocol:
    try:
        return REGISTRY[str(name)]
    except KeyError:
        raise ProtocolError(f"unknown protocol {name!r}; valid: {', '.join(REGISTRY)}") from None


def of_config(env_cfg) -> Protocol:
    """The protocol of a composed ``env`` config: ``env.protocol`` if given, else the one that claims it."""
    world = env_name(env_cfg)
    explicit = env_cfg.get("protocol")
    if explicit is not None:
        protocol = get(explicit)
        if protocol.world != world:
            raise ProtocolError(f"env.protocol={protocol.name} runs in env.name={protocol.world}, not {world}")
        return protocol
    for protocol in REGISTRY.values():
        if protocol.selects(env_cfg):
            return protocol
    raise ProtocolError(f"no protocol evaluates env.name={world} with these settings; "
                        f"name one with +env.protocol=NAME (valid: {', '.join(REGISTRY)})")


def tracks() -> dict[str, Track]:
    """Every registered protocol's tracks, in registration order."""
    return {t.name: t for p in REGISTRY.values() for t in p.tracks}


def homes() -> list[str]:
    """What a learned entry may name as the track it was trained on: every track, and each protocol's
    :attr:`~Protocol.home`, in registration order (a home right after its protocol's tracks)."""
    out = []
    for p in REGISTRY.values():
        out += [t.name for t in p.tracks] + ([p.home] if p.home else [])
    return out
