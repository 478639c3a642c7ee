"""Rendering: the generated leaderboard/README.md tables, the plot, the generated blocks of the
top-level README and the docs (:data:`BLOCKS`), and row-level diffs for ``--check``. Pure functions of
the results (no evaluation). Submission text enters the markdown escaped (:func:`~.text.md`).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from crowdbench.envs.protocol import EVAL_SCENES, PAPER_SCENES, PROTOCOL_VERSION
from crowdbench.eval import rate_ci
from crowdbench.leaderboard.entries import model_of
from crowdbench.leaderboard.metrics import sections
from crowdbench.leaderboard.schema import KINDS, link_problem
from crowdbench.leaderboard.text import diff_rows, md  # noqa: F401 - diff_rows: render.diff_rows for --check


def markers(name: str) -> tuple[str, str]:
    """The start and end markers of the generated block ``name`` in a markdown file."""
    return f"<!-- generated:{name}:start -->", f"<!-- generated:{name}:end -->"


BLOCK_START, BLOCK_END = markers("results")  # the top-level README's block
DOCS_START, DOCS_END = markers("docs-results")  # docs/results.md


def fmt(v, digits: int) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def scene_cell(r: dict, scene: str, metric: str, digits: int) -> tuple[float | None, str]:
    v = r["scenes"].get(scene, {}).get(metric)
    if not v or v["mean"] is None:
        return None, "—"
    return v["mean"], f"{v['mean']:.{digits}f} [{v['ci95'][0]:.{digits}f}, {v['ci95'][1]:.{digits}f}]"


def average_cell(r: dict, metric: str, digits: int) -> tuple[float | None, str]:
    """Paper-scene average: pooled Wilson interval for rates, combined normal interval for means."""
    vals = [r["scenes"].get(s, {}).get(metric) for s in PAPER_SCENES]
    if any(v is None or v["mean"] is None for v in vals):
        return None, "—"
    mean = sum(v["mean"] for v in vals) / len(vals)
    if metric.endswith("_rate"):
        n = sum(v["n"] for v in vals)
        k = round(sum(v["mean"] * v["n"] for v in vals))
        ci = rate_ci(k, n)["ci95"] if len({v["n"] for v in vals}) == 1 else [None, None]
    else:
        half = math.sqrt(sum(((v["ci95"][1] - v["ci95"][0]) / 2) ** 2 for v in vals)) / len(vals)
        ci = [mean - half, mean + half]
    return mean, fmt(mean, digits) if ci[0] is None else f"{mean:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def seed_cell(values: list[float | None], digits: int) -> tuple[float | None, str]:
    """Mean ± standard deviation over seeds (and the number of seeds)."""
    if not values or any(v is None for v in values):
        return None, "—"
    m = sum(values) / len(values)
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return m, f"{m:.{digits}f} ± {sd:.{digits}f}"


def label(group: list[dict], escape: bool = True) -> str:
    """The entry's row label, markdown-escaped (``escape``; the plot's legend takes it raw)."""
    r = group[0]
    name = r["meta"]["entry"]
    if r.get("privileged") and "privileged" not in name.lower():
        name += " (PRIVILEGED)"
    return md(name) if escape else name


def group_results(results: list[dict]) -> list[list[dict]]:
    """Results grouped by entry (seeds together), ordered baseline < learned < oracle, then by name."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in sorted(results, key=lambda r: r["meta"]["submission"]):
        groups.setdefault((r["meta"]["kind"], r["meta"]["entry"]), []).append(r)  # a kind never joins another
    order = {k: i for i, k in enumerate(KINDS)}
    return sorted(groups.values(), key=lambda g: (order[g[0]["meta"]["kind"]], g[0]["meta"]["entry"].lower()))


METRICS = [
    ("success_rate", "Success rate (Tables III / IV)", 3),
    ("nav_time_s", "Navigation time, s, successful episodes (Tables III / IV)", 2),
    ("dangers_per_episode", "Dangers per episode, steps with 0 <= d < 0.2 m (Table V)", 3),
    ("collision_rate", "Collision rate", 3),
    ("timeout_rate", "Timeout rate", 3),
]


def table_columns(scenes: list[str]) -> list[str]:
    """A metric table's value columns: the paper scenes, their average (all four present), the others."""
    paper = [s for s in PAPER_SCENES if s in scenes]
    return [*paper, *(["AVG (paper scenes)"] * (len(paper) == len(PAPER_SCENES))), *(s for s in scenes if s not in paper)]


def table_cell(g: list[dict], col: str, metric: str, digits: int, intervals: bool = True) -> tuple[float | None, str]:
    """Entry ``g``'s cell in column ``col`` (a scene or ``AVG...``): one run [95% interval], seeds mean ± sd."""
    vals = [average_cell(r, metric, digits) if col.startswith("AVG") else scene_cell(r, col, metric, digits) for r in g]
    if len(g) > 1:
        return seed_cell([v[0] for v in vals], digits)
    return vals[0][0], vals[0][1] if intervals else fmt(vals[0][0], digits)


def metric_table(groups: list[list[dict]], scenes: list[str], metric: str, digits: int,
                 intervals: bool = True) -> list[str]:
    """One row per entry; a single run shows its 95% interval (``intervals``), seeds mean ± sd."""
    head = ["method", "seeds", *table_columns(scenes)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        cells = [label(g), str(len(g)), *(table_cell(g, col, metric, digits, intervals)[1] for col in head[2:])]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


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
                 "uni_examples). Single runs: mean [95% interval] (Wilson for rates, normal approximation for means; "
                 "the paper-scene average pools the four scenes). Entries with several training seeds: mean ± "
                 "standard deviation across seeds (per-seed rows below).")
    else:
        L.append(f"**UNOFFICIAL subset**: {episodes or 250} episodes per scene, scenes {', '.join(scenes)}. "
                 "Not comparable with the official table.")
    L += ["", ("The **oracle** is PRIVILEGED: it knows every replayed human's future and plans with the simulator's "
          "own collision test. It is an upper bound on what is achievable, not a navigation policy. "
          "How to submit: [docs/submitting.md](../docs/submitting.md)."), "", "![leaderboard](leaderboard.png)", ""]
    for metric, title, digits in METRICS + sections(results):  # the social metrics only if some result has them
        L += [f"## {title}", "", *metric_table(groups, scenes, metric, digits), ""]
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


def plot(results: list[dict], scenes: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_results(results)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    width = 0.8 / max(len(groups), 1)
    xs = range(len(scenes))
    for i, g in enumerate(groups):
        for ax, metric in zip(axes, ("success_rate", "dangers_per_episode"), strict=True):
            means, lo, hi = [], [], []
            for s in scenes:
                vals = [r["scenes"][s][metric] for r in g if s in r["scenes"]]
                m = sum(v["mean"] for v in vals) / len(vals) if vals else float("nan")
                if len(g) == 1 and vals:
                    a, b = vals[0]["ci95"]
                else:
                    sd = torch.tensor([v["mean"] for v in vals], dtype=torch.float64).std().item() if vals else 0
                    a, b = m - sd, m + sd
                means.append(m)
                lo.append(max(m - a, 0))
                hi.append(max(b - m, 0))
            ax.bar([x + (i - (len(groups) - 1) / 2) * width for x in xs], means, width, yerr=[lo, hi], capsize=2,
                   label=label(g, escape=False).replace("$", r"\$"), color=plt.get_cmap("tab20")(i % 20))
    for ax, title in zip(axes, ("success rate (95% CI; seeds: ± sd)", "dangers per episode"), strict=True):
        ax.set_xticks(list(xs), scenes, rotation=30, ha="right")
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylim(0, 1.05)
    handles, labels = axes[0].get_legend_handles_labels()
    ncol = min(len(groups), 4)
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    fig.suptitle(f"crowdbench leaderboard, protocol {PROTOCOL_VERSION} (oracle = privileged upper bound)")
    fig.tight_layout(rect=(0, 0.04 + 0.035 * math.ceil(len(groups) / ncol), 1, 1))
    fig.savefig(out, dpi=110, metadata={"Software": None})
    plt.close(fig)


# ---------------------------------------------------------------------------------- README block
def _group_average(g: list[dict], metric: str, digits: int) -> tuple[float | None, str]:
    vals = [average_cell(r, metric, digits)[0] for r in g]
    return seed_cell(vals, digits) if len(g) > 1 else (vals[0], fmt(vals[0], digits))


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
    return ("Average success over the four paper scenes (mean ± sd over seeds for entries with several): "
            + "; ".join(parts) + ".")


def render_block(results: list[dict], scenes: list[str], episodes: int | None) -> str:
    """The top-level README's results block (between BLOCK_START and BLOCK_END): the success table,
    means only (single runs) or mean ± sd over seeds, and the summary sentence."""
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


BASELINE_METRICS = [
    ("success_rate", "Success rate", 3),
    ("collision_rate", "Collision rate", 3),
    ("timeout_rate", "Timeout rate", 3),
    ("nav_time_s", "Navigation time (s, successful episodes)", 2),
    ("dangers_per_episode", "Dangers per episode (steps with 0 <= d < 0.2 m)", 3),
    ("min_clearance", "Minimum clearance (m)", 3),
    ("path_length_ratio", "Path length ratio (successful)", 3),
    ("jerk", "Jerk (m/s^3)", 2),
]


def summary_table(groups: list[list[dict]]) -> list[str]:
    """Every entry: seeds, average success over the paper scenes and dangers per episode (single runs:
    the mean; several seeds: mean ± sd over seeds)."""
    lines = ["| entry | seeds | average success | dangers / episode |", "|---|---|---|---|"]
    for g in groups:
        lines.append(f"| {label(g)} | {len(g)} | {_group_average(g, 'success_rate', 3)[1]} | "
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
    for metric, title, digits in BASELINE_METRICS + sections(baselines):
        L += ["", f"### {title}", "", *baseline_table(baselines, scenes, metric, digits)]
    return "\n\n" + "\n".join(L) + "\n\n"


def paper_scene_block(metric: str, digits: int):
    """A block of docs/reproduction.md: every entry on the paper scenes and their average, means only
    (single runs) or mean ± sd over seeds (the rows set against the paper's numbers)."""
    def render(results: list[dict], scenes: list[str], episodes: int | None) -> str:
        paper = [s for s in scenes if s in PAPER_SCENES]
        L = [*_subset_note(scenes, episodes), *metric_table(group_results(results), paper, metric, digits,
                                                             intervals=False)]
        return "\n\n" + "\n".join(L) + "\n\n"

    return render


# name -> renderer(results, scenes, episodes); a file's block ``name`` lies between ``markers(name)``
BLOCKS = {
    "results": render_block,
    "docs-results": render_docs_block,
    "reproduction-success": paper_scene_block("success_rate", 3),
    "reproduction-nav-time": paper_scene_block("nav_time_s", 2),
    "reproduction-dangers": paper_scene_block("dangers_per_episode", 3),
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
