"""The social-navigation metrics (crowdbench/social_metrics.py) in the generated tables: a section of
leaderboard/README.md and docs/results.md per metric, a column of every TRACKS.md table.

Results computed before these metrics existed lack them: a section or column is rendered only when some
result of the table holds its metric (:func:`present`), so those results render exactly as before, and a
result without it shows "—" next to one with it."""

from __future__ import annotations

# key in results.json, section title (README.md, docs/results.md), column name (TRACKS.md), digits
SOCIAL = [
    ("spl", "SPL, success weighted by path length (Anderson et al. 2018)", "SPL", 3),
    ("stl", "STL, success weighted by time length (free-space time l / v_max)", "STL", 3),
    ("personal_space_compliance_50cm", "Personal-space compliance, fraction of steps ending with d >= 0.5 m",
     "pers. space 0.5 m", 3),
    ("min_ttc_s", "Minimum time-to-collision, s, capped at 10 s", "min TTC s", 2),
    ("path_irregularity", "Path irregularity, rad/m (Guzzi et al. 2013)", "irregularity rad/m", 3),
    ("social_nav_score", "Social-navigation score (composite in [0, 1], docs/protocol.md)", "score", 3),
]


def present(results: list[dict]) -> list[tuple[str, str, str, int]]:
    """The entries of :data:`SOCIAL` that some result holds on some scene or setting."""
    return [m for m in SOCIAL if any(m[0] in s for r in results for s in r["scenes"].values())]


def sections(results: list[dict]) -> list[tuple[str, str, int]]:
    """``(metric, title, digits)`` of the present social metrics: the format of ``render.METRICS``."""
    return [(key, title, digits) for key, title, _, digits in present(results)]


def columns(results: list[dict]) -> list[tuple[str, str, int]]:
    """``(metric, column, digits)`` of the present social metrics: the format of ``track_tables.SUMMARY``."""
    return [(key, column, digits) for key, _, column, digits in present(results)]
