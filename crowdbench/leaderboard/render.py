"""Rendering: the generated leaderboard/README.md tables, the plot, the generated blocks of the
top-level README and the docs (:data:`BLOCKS`), and row-level diffs for ``--check``. Pure functions of
the results (no evaluation). Submission text enters the markdown escaped (:func:`~.text.md`).
"""

from __future__ import annotations

from crowdbench.envs.protocol import EVAL_SCENES, PAPER_SCENES, PROTOCOL_VERSION
from crowdbench.leaderboard.entries import model_of
from crowdbench.leaderboard.stats import (  # noqa: F401 - the cells' functions, as render.* for the renderers
    average_cell,
    average_stat,
    fmt,
    group_stat,
    interval,
    ranked,
    scene_cell,
    seeds_cell,
)
from crowdbench.leaderboard.submission import KINDS, link_problem
from crowdbench.leaderboard.text import diff_rows, md  # noqa: F401 - diff_rows: render.diff_rows for --check
from crowdbench.metric_table import IN_DOCS, IN_README, V1, Metric, columns


def markers(name: str) -> tuple[str, str]:
    """The start and end markers of the generated block ``name`` in a markdown file."""
    return f"<!-- generated:{name}:start -->", f"<!-- generated:{name}:end -->"


BLOCK_START, BLOCK_END = markers("results")  # the top-level README's block
DOCS_START, DOCS_END = markers("docs-results")  # docs/results.md


def label(group: list[dict], escape: bool = True) -> str:
    """The entry's row label, markdown-escaped (``escape``; the plot's legend takes it raw): a privileged
    entry says so, and so does an unofficial one among official ones (:func:`group_results`)."""
    r = group[0]
    name = r["meta"]["entry"]
    if r.get("privileged") and "privileged" not in name.lower():
        name += " (PRIVILEGED)"
    if any(x.get(UNOFFICIAL_ROW) for x in group):
        name += " (UNOFFICIAL)"
    return md(name) if escape else name


UNOFFICIAL_ROW = "_unofficial_row"  # set on (a copy of) a result that :func:`label` marks as unofficial


def official(r: dict) -> bool:
    """Whether the harness evaluated ``r`` on the official protocol (every scene, every episode)."""
    return r.get("harness", {}).get("official") is not False


def group_results(results: list[dict]) -> list[list[dict]]:
    """Results grouped by entry (seeds together), ordered baseline < learned < oracle, then by name. In a
    table that mixes official and unofficial results (e.g. a cached subset shown beside a full evaluation),
    the unofficial ones are marked for :func:`label` (the header of an all-unofficial table says so)."""
    if len({official(r) for r in results}) > 1:
        results = [r if official(r) else {**r, UNOFFICIAL_ROW: True} for r in results]
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in sorted(results, key=lambda r: r["meta"]["submission"]):
        groups.setdefault((r["meta"]["kind"], r["meta"]["entry"]), []).append(r)  # a kind never joins another
    order = {k: i for i, k in enumerate(KINDS)}
    return sorted(groups.values(), key=lambda g: (order[g[0]["meta"]["kind"]], g[0]["meta"]["entry"].lower()))


def readme_sections(results: list[dict]) -> list[Metric]:
    """The metrics of leaderboard/README.md's sections: those of the paper's tables (III / IV, V) first."""
    return sorted(columns(IN_README, results, V1), key=lambda m: m.paper_title is None)


AVG = "AVG (paper scenes)"


def table_columns(scenes: list[str]) -> list[str]:
    """A metric table's value columns: the paper scenes' average first (all four present: the headline),
    the paper scenes, the others."""
    paper = [s for s in PAPER_SCENES if s in scenes]
    return [*([AVG] * (len(paper) == len(PAPER_SCENES))), *paper, *(s for s in scenes if s not in paper)]


def table_cell(g: list[dict], col: str, metric: str, digits: int, intervals: bool = True) -> tuple[float | None, str]:
    """Entry ``g``'s cell in column ``col`` (a scene or ``AVG...``): mean [95% interval] (``intervals``) of
    one run, or over its seeds (:func:`seeds_cell`)."""
    if len(g) > 1:
        parts = list(PAPER_SCENES) if col.startswith("AVG") else [col]
        return seeds_cell([[r["scenes"].get(s, {}).get(metric) for s in parts] for r in g], metric, digits, intervals)
    v = average_cell(g[0], metric, digits) if col.startswith("AVG") else scene_cell(g[0], col, metric, digits)
    return v[0], v[1] if intervals else fmt(v[0], digits)


def success_score(g: list[dict], scenes: list[str]) -> float | None:
    """The headline of protocol v1's tables: success averaged over the paper scenes (over the scenes
    evaluated, on a subset without all four), mean over seeds."""
    cols = [AVG] if all(s in scenes for s in PAPER_SCENES) else list(scenes)
    vals = [table_cell(g, c, "success_rate", 3, intervals=False)[0] for c in cols]
    return None if not vals or None in vals else sum(vals) / len(vals)


def metric_table(groups: list[list[dict]], scenes: list[str], metric: str, digits: int,
                 intervals: bool = True) -> list[str]:
    """One row per entry, ranked by success (:func:`success_score`: every metric's table in the same
    order); mean [95% interval] (``intervals``) of a run or of several seeds."""
    head = ["#", "method", "seeds", *table_columns(scenes)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for rank, g in ranked(groups, lambda g: success_score(g, scenes)):
        cells = [str(rank or "—"), label(g), str(len(g)),
                 *(table_cell(g, col, metric, digits, intervals)[1] for col in head[3:])]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


RANKING = ("Every table ranks the entries (#) by success averaged over the four paper scenes (its first column); "
           "each cell is mean [95% interval]: a single run's Wilson interval for rates and normal approximation "
           "for means (the paper-scene average pools the four scenes); an entry with several training seeds "
           "(per-seed rows below): the mean over seeds and a two-level bootstrap interval (seeds, then each "
           "seed's episodes). Intervals are clipped to the metric's range.")


def render_readme(results: list[dict], rejected: list[str], scenes: list[str], episodes: int | None,
                  missing: list[str]) -> str:
    groups = group_results(results)
    official = episodes is None and set(scenes) == set(EVAL_SCENES)
    L = [("<!-- GENERATED by `crowdbench leaderboard` from leaderboard/results/*/results.json: DO NOT EDIT BY HAND."
         " `crowdbench leaderboard --check` fails if this file differs from a fresh evaluation. -->"), "",
         "# crowdbench leaderboard (protocol " + PROTOCOL_VERSION + ")", ""]
    if official:
        L.append("Every number is computed by the harness (`crowdbench leaderboard`) on the fixed protocol: 250 episodes "
                 "per scene, 4 paper scenes (students003, zara2, hotel, eth) and 3 extra scenes (zara1, zara3, "
                 "uni_examples).")
    else:
        L.append(f"**UNOFFICIAL subset**: {episodes or 250} episodes per scene, scenes {', '.join(scenes)}. "
                 "Not comparable with the official table.")
    L += ["", RANKING, "", ("The **oracle** is PRIVILEGED: it knows every replayed human's future and plans with the "
          "simulator's own collision test. It is an upper bound on what is achievable, not a navigation policy. "
          "How to submit: [docs/submitting.md](../docs/submitting.md)."), "", "![leaderboard](leaderboard.png)", ""]
    for m in readme_sections(results):
        L += [f"## {m.paper_title or m.title}", "", *metric_table(groups, scenes, m.key, m.digits), ""]
    oracle = [r for g in groups for r in g if r["meta"]["kind"] == "oracle"]
    if oracle:
        u = oracle[0]["unavoidable"]
        L += ["## Unavoidable episodes (oracle failures)", "",
              ("Episodes in which the privileged oracle fails are candidate unavoidable collisions (its search is "
              "not exhaustive, so each is a candidate, not a proof); the list is in "
              f"`results/{oracle[0]['meta']['submission']}/unavoidable.json`."), "",
              "| scene | episodes | oracle collisions | oracle timeouts |", "|---|---|---|---|"]
        for s in scenes:
            if s in u:
                L.append(f"| {s} | {u[s]['episodes']} | {len(u[s]['collision'])} | {len(u[s]['timeout'])} |")
        L.append("")
    multi = [g for g in groups if len(g) > 1]
    if multi:
        L += ["## Per-seed results (success rate)", "", "| entry | submission | seed | " + " | ".join(scenes) + " |",
              "|" + "---|" * (3 + len(scenes))]
        for g in multi:
            for r in g:
                cells = [scene_cell(r, s, "success_rate", 3)[1] for s in scenes]
                L.append(f"| {label(g)} | {md(r['meta']['submission'])} | {md(r['submission'].get('seed', '—'))} | "
                         + " | ".join(cells) + " |")
        L.append("")
    L += ["## Submissions", "", "| submission | entry | kind | encoder | algo | seed | authors | link |",
          "|---|---|---|---|---|---|---|---|"]
    for g in groups:
        for r in g:
            d = r["submission"]
            authors = d["authors"] if isinstance(d["authors"], str) else ", ".join(map(str, d["authors"]))
            kind, link = d["kind"] + (" (privileged)" if d.get("privileged") else ""), d.get("link", "—")
            cells = [d["name"], kind, model_of(d), d.get("algo", "—"), d.get("seed", "—"),
                     authors]
            name, kind, enc, algo, seed, authors = map(md, cells)  # a valid link needs no escaping (LINK_RE)
            L.append(f"| {name} | {label(g)} | {kind} | {enc} | {algo} | {seed} | {authors} | "
                     f"{link if link == '—' or not link_problem(link) else md(link)} |")
    L.append("")
    if missing:
        L += ["## Not evaluated", "", *[f"- {m}" for m in missing], ""]  # harness text of validated names
    if rejected:
        L += ["## Rejected submissions", "", *[f"- {md(e)}" for e in rejected], ""]
    return "\n".join(L)


# ---------------------------------------------------------------------------------- README block
def _group_average(g: list[dict], metric: str, digits: int) -> tuple[float | None, str]:
    return table_cell(g, AVG, metric, digits)


def summary_sentence(groups: list[list[dict]]) -> str:
    """ORCA's, the oracle's and the best learned entry's paper-scene average success and dangers."""
    def kind(g):
        return g[0]["meta"]["kind"]

    def stats(g):
        s, d = _group_average(g, "success_rate", 3)[1], _group_average(g, "dangers_per_episode", 3)[1]
        seeds = f", {len(g)} seeds" if len(g) > 1 else ""
        return f"{s} ({d} dangers per episode{seeds})"

    parts = []
    orca = [g for g in groups if kind(g) == "baseline" and g[0]["submission"].get("policy") == "orca"]
    if orca:
        parts.append(f"{label(orca[0])} {stats(orca[0])}")
    learned = [g for g in groups if kind(g) == "learned" and _group_average(g, "success_rate", 3)[0] is not None]
    if learned:
        best = max(learned, key=lambda g: _group_average(g, "success_rate", 3)[0])
        parts.append(f"the best learned entry, {label(best)}, {stats(best)}")
    oracle = [g for g in groups if kind(g) == "oracle"]
    if oracle:
        parts.append(f"the privileged oracle {stats(oracle[0])}")
    if not parts:
        return ""
    return ("Average success over the four paper scenes, mean [95% interval] (over seeds for entries with "
            "several): " + "; ".join(parts) + ".")


def render_block(results: list[dict], scenes: list[str], episodes: int | None) -> str:
    """The top-level README's results block (between BLOCK_START and BLOCK_END): the success table,
    ranked, means only (of a run or over seeds), and the summary sentence."""
    groups = group_results(results)
    L = [*_subset_note(scenes, episodes), *metric_table(groups, scenes, "success_rate", 3, intervals=False)]
    sentence = summary_sentence(groups) if all(s in scenes for s in PAPER_SCENES) else ""
    if sentence:
        L += ["", sentence]
    return "\n\n" + "\n".join(L) + "\n\n"


def _bounds(text: str, name: str = "results") -> tuple[int, int]:
    start_marker, end_marker = markers(name)
    start, end = text.find(start_marker), text.find(end_marker)
    if start < 0 or end < start:
        raise ValueError(f"no {start_marker} ... {end_marker} block")
    return start + len(start_marker), end


def read_block(text: str, name: str = "results") -> str:
    """The text between the markers of block ``name`` (ValueError if they are missing)."""
    a, b = _bounds(text, name)
    return text[a:b]


def splice(text: str, block: str, name: str = "results") -> str:
    """``text`` with the block ``name`` between its markers replaced by ``block``."""
    a, b = _bounds(text, name)
    return text[:a] + block + text[b:]


# ---------------------------------------------------------------------------------- docs blocks
def _subset_note(scenes: list[str], episodes: int | None) -> list[str]:
    if episodes is None and set(scenes) == set(EVAL_SCENES):
        return []
    # (an episode list holds 250 episodes: a larger --episodes evaluates them all, L5)
    return [f"**UNOFFICIAL subset**: {min(episodes or 250, 250)} episodes per scene, scenes {', '.join(scenes)}.", ""]


def summary_table(groups: list[list[dict]]) -> list[str]:
    """Every entry, ranked by average success over the paper scenes: seeds, that success and dangers per
    episode, mean [95% interval] (of a run or over seeds)."""
    lines = ["| # | entry | seeds | average success | dangers / episode |", "|---|---|---|---|---|"]
    for rank, g in ranked(groups, lambda g: _group_average(g, "success_rate", 3)[0]):
        lines.append(f"| {rank or '—'} | {label(g)} | {len(g)} | {_group_average(g, 'success_rate', 3)[1]} | "
                     f"{_group_average(g, 'dangers_per_episode', 3)[1]} |")
    return lines


def baseline_table(results: list[dict], scenes: list[str], metric: str, digits: int) -> list[str]:
    """One row per baseline (named by its policy): every scene's mean [95% interval] from its
    results.json, then the plain mean over the paper scenes."""
    with_avg = all(s in scenes for s in PAPER_SCENES)
    head = ["policy", *scenes, *(["avg (paper scenes)"] if with_avg else [])]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        cells = [md(r["submission"].get("policy", r["meta"]["submission"]))]
        cells += [scene_cell(r, s, metric, digits)[1] for s in scenes]
        if with_avg:
            cells.append(fmt(average_cell(r, metric, digits)[0], digits))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def render_docs_block(results: list[dict], scenes: list[str], episodes: int | None) -> str:
    """docs/results.md's block (between DOCS_START and DOCS_END): the summary table of every entry and
    the per-metric tables of the baseline submissions."""
    groups = group_results(results)
    baselines = [r for g in groups for r in g if r["meta"]["kind"] == "baseline"]
    L = [*_subset_note(scenes, episodes), *summary_table(groups), "", "## Baselines", "",
         ("From `leaderboard/results/<name>/results.json` of the baseline submissions "
          f"({', '.join(md(r['meta']['submission']) for r in baselines)}): {episodes or 250} episodes per scene, "
          "mean [95% interval] (Wilson for rates, normal approximation for means); the last column is the "
          "mean over the paper scenes.")]
    for m in columns(IN_DOCS, baselines, V1):
        L += ["", f"### {m.title}", "", *baseline_table(baselines, scenes, m.key, m.digits)]
    return "\n\n" + "\n".join(L) + "\n\n"


def paper_scene_block(metric: str, digits: int):
    """A block of docs/reproduction.md: every entry on the paper scenes and their average, ranked by
    success, means only (of a run or over seeds: the rows set against the paper's numbers)."""
    def render(results: list[dict], scenes: list[str], episodes: int | None) -> str:
        paper = [s for s in scenes if s in PAPER_SCENES]
        L = [*_subset_note(scenes, episodes), *metric_table(group_results(results), paper, metric, digits,
                                                             intervals=False)]
        return "\n\n" + "\n".join(L) + "\n\n"

    return render


def experiment_block(experiment: str):
    """A block of docs/training.md: the entries one experiment trained (``submission.experiment``) beside the
    ORCA baseline, ranked by success: the paper scenes' average success with its 95% interval, each paper
    scene's, then dangers per episode and SPL over the paper scenes (mean of a run or over seeds)."""
    def render(results: list[dict], scenes: list[str], episodes: int | None) -> str:
        if not all(s in scenes for s in PAPER_SCENES):
            return "\n\n" + "\n".join(_subset_note(scenes, episodes)) + "\n\n"
        keep = [r for r in results if r["submission"].get("experiment") == experiment
                or r["meta"]["kind"] == "baseline" and r["meta"]["submission"] == "orca"]
        head = ["#", "method", "seeds", "success (paper scenes)", *PAPER_SCENES, "dangers / episode", "SPL"]
        lines = [*_subset_note(scenes, episodes), "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for rank, g in ranked(group_results(keep), lambda g: success_score(g, scenes)):
            cells = [str(rank or "—"), label(g), str(len(g)), table_cell(g, AVG, "success_rate", 3)[1],
                     *(table_cell(g, s, "success_rate", 3, intervals=False)[1] for s in PAPER_SCENES),
                     table_cell(g, AVG, "dangers_per_episode", 3)[1], table_cell(g, AVG, "spl", 3)[1]]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n\n" + "\n".join(lines) + "\n\n"

    return render


# name -> renderer(results, scenes, episodes); a file's block ``name`` lies between ``markers(name)``
BLOCKS = {
    "results": render_block,
    "docs-results": render_docs_block,
    "reproduction-success": paper_scene_block("success_rate", 3),
    "reproduction-nav-time": paper_scene_block("nav_time_s", 2),
    "reproduction-dangers": paper_scene_block("dangers_per_episode", 3),
    "experiment-leaderboard": experiment_block("leaderboard"),
}


def blocks_in(text: str) -> list[str]:
    """The names of the generated blocks ``text`` holds (both markers, in order)."""
    out = []
    for name in BLOCKS:
        start, end = markers(name)
        a, b = text.find(start), text.find(end)
        if 0 <= a < b:
            out.append(name)
    return out


def regenerate(text: str, results: list[dict], scenes: list[str], episodes: int | None) -> str:
    """``text`` with every generated block it holds rendered afresh from ``results``."""
    for name in blocks_in(text):
        text = splice(text, BLOCKS[name](results, scenes, episodes), name)
    return text
