"""The metric table: every metric of ``results.json`` declared once, with what the evaluation aggregates it
from, its labels and digits, its range, its interval and the protocols and tables that have it.

Read by the evaluations' aggregation (``crowdbench/protocols/``: ``engine.py``, ``replay.py``, ``selfplay.py``),
``crowdbench eval``'s tables, the leaderboard's tables (``leaderboard/README.md``, ``TRACKS.md``, the
generated blocks of the README and the docs), its statistics and the site. Adding a metric is one entry
here plus its per-episode value (docs/architecture.md, "How to add a metric"). Definitions:
docs/protocol.md, docs/selfplay.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

Z95 = 1.959963984540054  # the normal quantile of a two-sided 95% interval

# the protocols, as results.json's "protocol" names them (tests/test_metric_table.py checks the modules' names)
V1, V2, CROWDNAV, SELFPLAY = "v1", "v2", "crowdnav-v1", "selfplay-v1"
ROBOT = (V1, V2, CROWDNAV)  # one robot among humans: the per-episode values of eval.episode_metrics

# the tables a metric is shown in
IN_AVERAGE = "average"  # results.json's average over the paper scenes (and `crowdbench eval`'s avg row)
IN_README = "readme"  # a section of leaderboard/README.md (protocol v1)
IN_DOCS = "docs"  # a table of docs/results.md's baselines
IN_TRACKS = "tracks"  # a column of TRACKS.md's and the site's track tables and of `crowdbench eval`'s table
IN_SELFPLAY = "selfplay"  # a column of `crowdbench eval`'s self-play table
EVERY_TABLE = (IN_AVERAGE, IN_README, IN_DOCS, IN_TRACKS)  # of the single-robot protocols

UNIT = (0.0, 1.0)
COUNT = (0.0, math.inf)  # counts, times, lengths: never negative
ANY = (-math.inf, math.inf)


@dataclass(frozen=True)
class Metric:
    key: str  # in results.json
    title: str  # a section or page heading (README.md, docs/results.md, the site)
    column: str  # a column header (TRACKS.md, the site's track tables, `crowdbench eval`)
    digits: int = 3
    range: tuple[float, float] = ANY  # every interval is clipped to it
    interval: str = "normal"  # "wilson": a rate (Wilson score); "normal": mean ± Z95·sd/√n
    source: str | None = None  # the per-episode value aggregated (eval.episode_metrics), when not named ``key``
    successful_only: bool = False  # aggregated over the successful episodes only
    protocols: tuple[str, ...] = ROBOT
    shown_in: tuple[str, ...] = ()
    paper_title: str | None = None  # README.md's heading of a metric of the paper's tables, shown first there
    optional: bool = False  # results written before it existed lack it: a table shows it once some result has it


# the social-navigation metrics (crowdbench/social_metrics.py), added after protocol v1's own
SOCIAL = {"protocols": ROBOT, "shown_in": (IN_README, IN_DOCS, IN_TRACKS), "optional": True}

# in the order every table shows them (README.md puts those with a paper_title first); results.json lists
# the rates, then the means over successful episodes, then the others, each in this order (eval.aggregate)
METRICS: tuple[Metric, ...] = (
    Metric("success_rate", "Success rate", "success", range=UNIT, interval="wilson", source="success",
           protocols=(*ROBOT, SELFPLAY), shown_in=(*EVERY_TABLE, IN_SELFPLAY), paper_title="Success rate (Tables III / IV)"),
    Metric("collision_rate", "Collision rate", "collision", range=UNIT, interval="wilson", source="collision",
           protocols=(*ROBOT, SELFPLAY), shown_in=(*EVERY_TABLE, IN_SELFPLAY)),
    Metric("timeout_rate", "Timeout rate", "timeout", range=UNIT, interval="wilson", source="timeout",
           protocols=(*ROBOT, SELFPLAY), shown_in=(*EVERY_TABLE, IN_SELFPLAY)),
    Metric("nav_time_s", "Navigation time (s, successful episodes)", "nav time s", 2, COUNT, source="nav_time",
           successful_only=True, protocols=(*ROBOT, SELFPLAY), shown_in=(*EVERY_TABLE, IN_SELFPLAY),
           paper_title="Navigation time, s, successful episodes (Tables III / IV)"),
    Metric("dangers_per_episode", "Dangers per episode (steps with 0 <= d < 0.2 m)", "dangers/ep", range=COUNT,
           source="danger_steps", shown_in=EVERY_TABLE,
           paper_title="Dangers per episode, steps with 0 <= d < 0.2 m (Table V)"),
    Metric("danger_events", "Danger events per episode (entries into 0 <= d < 0.2 m)", "danger events",
           range=COUNT),
    Metric("min_clearance", "Minimum clearance (m)", "min clearance m", shown_in=(IN_DOCS, IN_TRACKS)),
    Metric("path_length_ratio", "Path length ratio (successful)", "path ratio", range=COUNT, source="path_ratio",
           successful_only=True, protocols=(*ROBOT, SELFPLAY), shown_in=(IN_DOCS,)),
    Metric("path_length", "Path length (m)", "path m", range=COUNT),
    Metric("mean_speed", "Mean speed (m/s)", "speed m/s", range=COUNT),
    Metric("jerk", "Jerk (m/s^3)", "jerk m/s^3", 2, COUNT, shown_in=(IN_DOCS,)),
    Metric("personal_space_compliance", "Personal-space compliance, fraction of steps ending with d >= 0.45 m",
           "pers. space 0.45 m", range=UNIT, source="personal_space"),
    Metric("discounted_return", "Discounted return (gamma 0.99)", "return", source="return"),
    Metric("crowd_offset_max_m", "Crowd offset, m, the farthest a human was pushed off its track", "crowd offset m",
           range=COUNT, source="crowd_offset_max", protocols=(V2,), shown_in=(IN_TRACKS,)),
    Metric("crowd_deviation_m", "Crowd deviation, m, summed deviation from the recorded motion", "crowd deviation m",
           range=COUNT, source="crowd_deviation", protocols=(V2,), shown_in=(IN_TRACKS,)),
    Metric("spl", "SPL, success weighted by path length (Anderson et al. 2018)", "SPL", range=UNIT, **SOCIAL),
    Metric("stl", "STL, success weighted by time length (free-space time l / v_max)", "STL", range=UNIT, **SOCIAL),
    Metric("personal_space_compliance_50cm", "Personal-space compliance, fraction of steps ending with d >= 0.5 m",
           "pers. space 0.5 m", range=UNIT, source="personal_space_50cm", **SOCIAL),
    # 10 s: social_metrics.TTC_HORIZON, the cap of the per-episode value
    Metric("min_ttc_s", "Minimum time-to-collision, s, capped at 10 s", "min TTC s", 2, (0.0, 10.0), source="min_ttc",
           **SOCIAL),
    Metric("path_irregularity", "Path irregularity, rad/m (Guzzi et al. 2013)", "irregularity rad/m", range=COUNT,
           **SOCIAL),
    Metric("social_nav_score", "Social-navigation score (composite in [0, 1], docs/protocol.md)", "score",
           range=UNIT, **SOCIAL),
    # self-play (docs/selfplay.md): per agent, then per episode (results.json's "episode")
    Metric("agent_dangers_per_agent", "Dangers between agents per agent", "agent dangers", range=COUNT,
           protocols=(SELFPLAY,), shown_in=(IN_SELFPLAY, IN_TRACKS)),
    Metric("dangers_per_agent", "Dangers with any body per agent", "dangers", range=COUNT, protocols=(SELFPLAY,),
           shown_in=(IN_TRACKS,)),
    Metric("min_agent_clearance", "Minimum agent-agent clearance (m)", "min agent clearance m", protocols=(SELFPLAY,),
           shown_in=(IN_TRACKS,)),
    Metric("all_arrived_rate", "Episodes in which every agent arrived", "all arrived", range=UNIT, interval="wilson",
           protocols=(SELFPLAY,), shown_in=(IN_SELFPLAY, IN_TRACKS)),
    Metric("any_collision_rate", "Episodes with a collision", "any collision", range=UNIT, interval="wilson",
           protocols=(SELFPLAY,), shown_in=(IN_TRACKS,)),
    Metric("collisions_per_episode", "Collided agents per episode", "collisions/ep", range=COUNT,
           protocols=(SELFPLAY,)),
    Metric("colliding_pairs_per_episode", "Colliding agent pairs per episode", "pairs/ep", range=COUNT,
           protocols=(SELFPLAY,)),
    Metric("agent_dangers_per_episode", "Dangers between agents per episode", "agent dangers/ep", range=COUNT,
           protocols=(SELFPLAY,)),
    Metric("episode_time_s", "Episode time (s, episodes in which every agent arrived)", "episode s", range=COUNT,
           protocols=(SELFPLAY,), shown_in=(IN_SELFPLAY, IN_TRACKS)),
)


def metric(key: str) -> Metric | None:
    return next((m for m in METRICS if m.key == key), None)


def metric_range(key: str) -> tuple[float, float]:
    """The values ``key`` can take (a metric not in the table: unbounded)."""
    m = metric(key)
    return ANY if m is None else m.range


def within(bounds: tuple[float, float], lo: float, hi: float) -> tuple[float, float]:
    a, b = bounds
    return min(max(lo, a), b), min(max(hi, a), b)


def clip(key: str, lo: float, hi: float) -> tuple[float, float]:
    """An interval within ``key``'s range (a normal approximation can leave it: a count below 0)."""
    return within(metric_range(key), lo, hi)


def is_rate(key: str) -> bool:
    """A rate of ``n`` trials (a Wilson interval; the leaderboard draws it binomially)."""
    m = metric(key)
    return m is not None and m.interval == "wilson"


def half_width(sd: float | None, n: int) -> float:
    """The normal interval's half-width ``Z95·sd/√n`` (0 for a single value): the one formula of the
    aggregation and of the leaderboard's statistics, so that both see the same bits."""
    return Z95 * sd / math.sqrt(n) if n > 1 and sd is not None else 0.0


def spread(v: dict) -> tuple[float | None, float | None]:
    """The unclipped normal interval of a mean (from its ``sd``; a result written before ``sd`` existed
    holds it as its ``ci95``): its width is the standard error the seeds' bootstrap and the paper-scene
    average read, which a clipped interval no longer shows."""
    if "sd" not in v or v.get("mean") is None:
        lo, hi = v.get("ci95") or (None, None)
        return lo, hi
    h = half_width(v["sd"], v["n"])
    return v["mean"] - h, v["mean"] + h


def ordered(keys) -> list[str]:
    """``keys`` in the table's order, then those not in the table by name."""
    keys = set(keys)
    return [m.key for m in METRICS if m.key in keys] + sorted(keys - {m.key for m in METRICS})


def of_protocol(protocol: str) -> list[Metric]:
    return [m for m in METRICS if protocol in m.protocols]


def in_table(table: str) -> list[Metric]:
    return [m for m in METRICS if table in m.shown_in]


def columns(table: str, results: list[dict], protocol: str | None = None) -> list[Metric]:
    """The metrics ``table`` shows for ``results`` (each holding ``scenes``), in the table's order: those of
    ``protocol``, an optional one only once some result holds it; ``protocol`` None: those the results hold."""
    held = {k for r in results for s in r["scenes"].values() for k in s}
    return [m for m in in_table(table) if (m.key in held if protocol is None else
                                           protocol in m.protocols and (m.key in held or not m.optional))]
