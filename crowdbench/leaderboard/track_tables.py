"""The generated ``leaderboard/TRACKS.md``: one table per track and the transfer table. Pure functions of
the results; each table sits between ``generated:track-<name>`` (``generated:transfer``) markers so that
``--check`` of a subset of the tracks compares the tables of those tracks only."""

from __future__ import annotations

from crowdbench.envs.protocol import PAPER_SCENES
from crowdbench.leaderboard.render import (
    average_cell,
    fmt,
    group_results,
    label,
    markers,
    metric_table,
    scene_cell,
    seeds_cell,
)
from crowdbench.leaderboard.stats import ranked
from crowdbench.leaderboard.text import md
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS, Track
from crowdbench.metric_table import IN_TRACKS, columns
from crowdbench.protocols import homes


def trained_on(r: dict) -> str | None:
    """The track a learned result's entry was trained on; None for baselines and the oracle."""
    return r["submission"].get("track", "v1") if r["meta"]["kind"] == "learned" else None


def at_home(r: dict, track: Track) -> bool:
    """Whether ``r`` is a row of ``track``'s table: a baseline, the oracle or an entry trained on the track
    (or on its protocol's home: self-play)."""
    origin = trained_on(r)
    return origin is None or track.is_home(origin)


def origin_rank(origin: str) -> int:
    """The place of a training track in the tables' order (tracks, each protocol's home after its tracks)."""
    return homes().index(origin)


def headline(r: dict, track: Track, metric: str, digits: int) -> tuple[float | None, str]:
    """A run's figure on a track: the paper-scene average (replay tracks) or the setting's value (CrowdNav)."""
    if not track.replay:
        return scene_cell(r, track.setting, metric, digits)
    if all(s in r["scenes"] for s in PAPER_SCENES):
        return average_cell(r, metric, digits)
    vals = [(v.get(metric) or {}).get("mean") for v in r["scenes"].values()]  # an unofficial subset: plain mean
    if not vals or None in vals:
        return None, "—"
    return sum(vals) / len(vals), fmt(sum(vals) / len(vals), digits)


def headline_scenes(r: dict, track: Track) -> list[str]:
    """The scenes (settings) a track's figure averages: the paper scenes, the scenes of an unofficial
    subset, or the CrowdNav setting."""
    if not track.replay:
        return [track.setting]
    return list(PAPER_SCENES) if all(s in r["scenes"] for s in PAPER_SCENES) else list(r["scenes"])


def group_cell(g: list[dict], track: Track, metric: str, digits: int) -> tuple[float | None, str]:
    """A run's :func:`headline`; several seeds: their mean [95% two-level bootstrap interval]."""
    if len(g) == 1:
        return headline(g[0], track, metric, digits)
    cols = headline_scenes(g[0], track)
    return seeds_cell([[r["scenes"].get(s, {}).get(metric) for s in cols] for r in g], metric, digits)


def above_the_oracle(by_track: dict[str, list[dict]]) -> list[str]:
    """Rows that beat the oracle where it claims to be the task's upper bound (a privileged track): any such
    row means the oracle's search, not the task, bounded it (docs/protocol.md, "Oracle")."""
    out = []
    for name, results in by_track.items():
        track = TRACKS[name]
        oracle = [r for r in results if r["meta"]["kind"] == "oracle"]
        if not track.privileged_ok or not oracle:
            continue
        bound = headline(oracle[0], track, "success_rate", 3)[0]
        for g in group_results([r for r in results if r["meta"]["kind"] == "learned"]):
            got = group_cell(g, track, "success_rate", 3)[0]
            if bound is not None and got is not None and got > bound:
                out.append(f"{name}: {label(g, escape=False)} {got:.3f} > the oracle's {bound:.3f}")
    return out


def track_table(track: Track, results: list[dict], scenes: list[str]) -> list[str]:
    """Baselines, the oracle (where it applies) and the entries trained on ``track``."""
    home = [r for r in results if at_home(r, track)]
    groups = group_results(home)
    cols = columns(IN_TRACKS, home, track.label)
    where = track.evaluator.where(track)
    L = [f"## `{track.name}`: {track.title}", "",
         f"Ranked (#) by success, the first column. Each cell: {where}; mean [95% interval] of a run, or over "
         "several seeds (two-level bootstrap: seeds, then episodes)."
         + ("" if track.privileged_ok else " " + track.evaluator.oracle_note), "", f"![{track.name}, ranked](plots/{track.name}.png)", ""]
    head = ["#", "method", "trained on", "seeds", *(m.column for m in cols)]
    L += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for rank, g in ranked(groups, lambda g: group_cell(g, track, "success_rate", 3)[0]):
        origin = trained_on(g[0]) or "—"
        cells = [str(rank or "—"), label(g), md(origin), str(len(g))]
        L.append("| " + " | ".join(cells + [group_cell(g, track, m.key, m.digits)[1] for m in cols]) + " |")
    if track.replay and len(scenes) > 1:
        L += ["", "Success rate per scene:", "", *metric_table(groups, scenes, "success_rate", 3)]
    return L


def transfer_table(by_track: dict[str, list[dict]]) -> list[str]:
    """Every learned entry (mean [95% interval] over seeds) on every track; bold: the track it was trained on."""
    entries: dict[tuple[str, str], dict[str, list[dict]]] = {}  # (label, trained on): one label may be trained twice
    for name, results in by_track.items():
        for r in results:
            if trained_on(r) is not None:
                entries.setdefault((r["meta"]["entry"], trained_on(r)), {}).setdefault(name, []).append(r)
    # a track no learned entry was evaluated on (self-play before its first submission) has no column
    tracks = [t for t in TRACK_ORDER if t in by_track and any(trained_on(r) for r in by_track[t])]
    head = ["method", "trained on", "seeds", *(f"`{t}`" for t in tracks)]
    L = ["## Transfer: success of every learned entry on every track", "",
         ("Replay tracks: average over the four paper scenes; CrowdNav tracks: its test cases"
          + ("; self-play tracks: per agent" if any(TRACKS[t].evaluator.home for t in tracks) else "")
          + ". Mean [95% interval] over seeds; **bold**: the track the entry was trained on."), "",
         "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = []
    for (entry, origin), per in entries.items():
        seeds = max(len(v) for v in per.values())
        cells = []
        for t in tracks:
            g = sorted(per.get(t, []), key=lambda r: r["meta"]["submission"])
            c = group_cell(g, TRACKS[t], "success_rate", 3)[1] if g else "—"
            cells.append(f"**{c}**" if TRACKS[t].is_home(origin) and c != "—" else c)
        rows.append((origin_rank(origin), entry.lower(),
                     [label(next(iter(per.values()))), f"`{origin}`", str(seeds), *cells]))  # privileged: marked
    L += ["| " + " | ".join(c) + " |" for *_, c in sorted(rows)]
    return L


def block(name: str, lines: list[str]) -> str:
    start, end = markers(name)
    return "\n".join([start, *lines, end])


def render_tracks(by_track: dict[str, list[dict]], scenes: list[str], episodes: int | None,
                  missing: list[str], rejected: list[str]) -> str:
    """The whole ``leaderboard/TRACKS.md``."""
    L = [("<!-- GENERATED by `crowdbench leaderboard` from leaderboard/results/*/*.json: DO NOT EDIT BY HAND. "
         "`crowdbench leaderboard --check` fails if a table differs from a fresh evaluation. -->"), "",
         "# crowdbench leaderboard: every track", "",
         ("Every entry evaluated by the harness on every track it fits (docs/submitting.md, \"Tracks\"). "
         "Protocol v1's full tables are in [README.md](README.md)."), ""]
    if episodes is not None or set(PAPER_SCENES) - set(scenes):
        L += [f"**Unofficial subset**: scenes {', '.join(scenes)}, episodes {episodes or 'all'}.", ""]
    for name in TRACK_ORDER:
        if name in by_track:
            L += [block(f"track-{name}", track_table(TRACKS[name], by_track[name], scenes)), ""]
    if len(by_track) == len(TRACK_ORDER):
        L += [block("transfer", transfer_table(by_track)), ""]
    if missing:
        L += ["## Not evaluated", "", *(f"- {m}" for m in missing), ""]
    if rejected:
        L += ["## Rejected", "", *(f"- {md(m)}" for m in rejected), ""]
    return "\n".join(L)


__all__ = ["at_home", "fmt", "render_tracks", "track_table", "trained_on", "transfer_table"]
