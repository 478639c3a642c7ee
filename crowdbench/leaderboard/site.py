"""The leaderboard as a static web site (``crowdbench leaderboard --site DIR``): ``DIR/index.html``, one
page per entry under ``DIR/entries/``, the stylesheet and script in ``DIR/assets/`` (copied from
``crowdbench/leaderboard/site_assets/``) and, with ``--site-figures N``, trajectory figures and rerun
recordings in ``DIR/media/`` (crowdbench/leaderboard/site_media.py). No server and nothing fetched
from the network: open ``DIR/index.html`` from disk.

Pure rendering of the results the run holds (the cached or fresh results it also writes the tables
from): every cell is :func:`~.render.table_cell` / :func:`~.track_tables.group_cell`, the functions of
``leaderboard/README.md`` and ``TRACKS.md``, so the page shows their numbers, seeds of one entry grouped
as there (:func:`~.render.group_results`: mean [95% bootstrap interval], n), ranked as there. Submission text is HTML-escaped
(:func:`html.escape`) and a ``link`` becomes a link only if it is an http(s) URL (:func:`~.submission.link_problem`).
"""

from __future__ import annotations

import html
import json
import shlex
import shutil
from pathlib import Path
from urllib.parse import quote

import yaml

from crowdbench.envs.protocol import EVAL_SCENES, PROTOCOL_VERSION
from crowdbench.leaderboard.entries import model_of
from crowdbench.leaderboard.render import (
    group_results,
    label,
    table_cell,
    table_columns,
)
from crowdbench.leaderboard.sandbox import DEFAULT_LIMITS, Limits
from crowdbench.leaderboard.site_media import SCENE, entry_media
from crowdbench.leaderboard.stats import ranked
from crowdbench.leaderboard.submission import SCHEMA, link_problem
from crowdbench.leaderboard.track_tables import at_home, group_cell, origin_rank, trained_on
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS, units
from crowdbench.metric_table import IN_TRACKS, columns, metric, ordered

ASSETS = Path(__file__).with_name("site_assets")
OPEN = ("success_rate",)  # unfolded per-scene tables (every track's summary table comes first)


def e(x) -> str:
    """Text as HTML (element content or a quoted attribute value)."""
    return html.escape(str(x), quote=True)


def metric_info(key: str) -> tuple[str, int]:
    """A metric's title and digits (crowdbench/metric_table.py; a key not in the table: itself, 3 digits)."""
    m = metric(key)
    return (key.replace("_", " "), 3) if m is None else (m.title, m.digits)


def metrics_of(results: list[dict]) -> list[str]:
    """Every per-scene metric the results hold, in the metric table's order."""
    return ordered({m for r in results for v in r["scenes"].values() for m in v})


def page(title: str, body: list[str], depth: int = 0) -> str:
    up = "../" * depth
    return "\n".join([
        "<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">', f"<title>{e(title)}</title>",
        f'<link rel="stylesheet" href="{up}assets/site.css">', "</head>", "<body>", *body,
        f'<script src="{up}assets/site.js"></script>', "</body>", "</html>", ""])


def external(link) -> str:
    """A submission's ``link``: an anchor only for a valid http(s) URL, else plain (escaped) text."""
    if not link:
        return "—"
    if link_problem(link):
        return e(link)
    return f'<a class="external" rel="noopener noreferrer nofollow" href="{e(link)}">{e(link)}</a>'


def th(text: str, numeric: bool) -> str:
    return f'<th scope="col" data-type="{"num" if numeric else "text"}" title="click to sort">{e(text)}</th>'


def td(value: float | None, text: str) -> str:
    return f'<td data-sort="{"" if value is None else repr(float(value))}">{e(text)}</td>'


def table(head: list[tuple[str, bool]], rows: list[list[str]], cls: str = "sortable", tid: str = "") -> list[str]:
    out = [f'<table class="{cls}"' + (f' id="{e(tid)}"' if tid else "") + ">",
           "<thead><tr>" + "".join(th(h, n) for h, n in head) + "</tr></thead>", "<tbody>"]
    out += ["<tr>" + "".join(r) + "</tr>" for r in rows]
    return [*out, "</tbody>", "</table>"]


class Site:
    """The results of one run, indexed for the pages: ``by_track`` as the tables are rendered from."""

    def __init__(self, root: Path, by_track: dict[str, list[dict]], scenes: list[str], episodes: int | None):
        self.root, self.scenes, self.episodes = Path(root), list(scenes), episodes
        self.by_track = {t: by_track[t] for t in TRACK_ORDER if by_track.get(t)}
        # an entry: (label, the track it was trained on; None for baselines and the oracle), as the transfer
        # table keys them (one label may be trained on two tracks) -> its results on every track
        self.entries: dict[tuple[str, str | None], list[dict]] = {}
        for results in self.by_track.values():
            for r in results:
                self.entries.setdefault(key(r), []).append(r)
        self.slugs = {lab: min(r["meta"]["submission"] for r in rs) for lab, rs in self.entries.items()}

    def href(self, entry: tuple, depth: int = 0, anchor: str = "") -> str:
        return f"{'../' * depth if depth else 'entries/'}{quote(self.slugs[entry])}.html" + \
            (f"#{quote(anchor)}" if anchor else "")

    def names(self, entry: tuple) -> list[str]:
        return sorted({r["meta"]["submission"] for r in self.entries[entry]})

    # ------------------------------------------------------------------ index
    def entry_cells(self, rank: int | None, g: list[dict]) -> list[str]:
        lab = label(g, escape=False)
        return [td(rank, str(rank or "—")), f'<td data-sort="{e(lab)}"><a href="{self.href(key(g[0]))}">{e(lab)}</a></td>',
                td(None, trained_on(g[0]) or "—"), td(len(g), str(len(g)))]

    def plot(self, name: str) -> list[str]:
        """The track's ranked plot (``leaderboard/plots/<track>.png``, copied by :func:`write_site`), if any."""
        if not (self.root / "plots" / f"{name}.png").is_file():
            return []
        return [f'<p><img class="plot" src="plots/{quote(name)}.png" alt="{e(name)}: success, ranked"></p>']

    def summary_table(self, name: str, order: list) -> list[str]:
        """The track's ranking: its headline figures, success first (the rows of TRACKS.md's table)."""
        track, home = TRACKS[name], [r for g in (g for _, g in order) for r in g]
        cols = columns(IN_TRACKS, home, track.label)
        rows = [self.entry_cells(rank, g) + [td(*group_cell(g, track, m.key, m.digits)) for m in cols]
                for rank, g in order]
        head = [("#", True), ("method", False), ("trained on", False), ("seeds", True), *((m.column, True) for m in cols)]
        return ['<div class="scroll">', *table(head, rows, cls="sortable ranked summary", tid=f"{name}.summary"), "</div>"]

    def track_section(self, name: str) -> list[str]:
        track, results = TRACKS[name], self.by_track[name]
        order = ranked(group_results([r for r in results if at_home(r, track)]),
                       lambda g: group_cell(g, track, "success_rate", 3)[0])
        cols = table_columns(units(track, self.scenes))
        where = "the average over the four paper scenes" if track.replay else track.evaluator.where(track)
        L = [f'<section class="track" id="track-{e(name)}">', f"<h2><code>{e(name)}</code>: {e(track.title)}</h2>",
             (f"<p>Ranked (#) by success on {e(where)}: baselines, the oracle where it applies and the entries "
              "trained on this track. Each cell: mean [95% interval] of a run, or over several seeds of one entry "
              "(two-level bootstrap; n in the <em>seeds</em> column). Click a column header to sort.</p>"),
             *self.summary_table(name, order), *self.plot(name), "<p>Per scene, every metric (same ranking):</p>"]
        for shown in metrics_of(results):
            title, digits = metric_info(shown)
            rows = [self.entry_cells(rank, g) + [td(*table_cell(g, c, shown, digits)) for c in cols]
                    for rank, g in order]
            head = [("#", True), ("method", False), ("trained on", False), ("seeds", True), *((c, True) for c in cols)]
            L += [f'<details{" open" if shown in OPEN else ""}>', f"<summary>{e(title)}</summary>",
                  *table(head, rows, cls="sortable ranked", tid=f"{name}.{shown}"), "</details>"]
        return [*L, "</section>"]

    def transfer_section(self) -> list[str]:
        per: dict[tuple[str, str], dict[str, list[dict]]] = {}
        for name, results in self.by_track.items():
            for r in results:
                if trained_on(r) is not None:
                    per.setdefault((r["meta"]["entry"], trained_on(r)), {}).setdefault(name, []).append(r)
        if not per:
            return []
        tracks = [t for t, rs in self.by_track.items() if any(trained_on(r) for r in rs)]
        rows = []
        for (entry, origin), got in sorted(per.items(), key=lambda kv: (origin_rank(kv[0][1]), kv[0][0].lower())):
            shown = label(next(iter(got.values())), escape=False)  # a privileged entry says so, as in its track's table
            cells = [f'<td data-sort="{e(entry)}"><a href="{self.href((entry, origin))}">{e(shown)}</a></td>',
                     td(None, origin),
                     td(max(map(len, got.values())), str(max(map(len, got.values()))))]
            for t in tracks:
                g = sorted(got.get(t, []), key=lambda r: r["meta"]["submission"])
                v, c = group_cell(g, TRACKS[t], "success_rate", 3) if g else (None, "—")
                cells.append(td(v, c).replace("<td", '<td class="home"', 1) if TRACKS[t].is_home(origin) else td(v, c))
            rows.append(cells)
        head = [("method", False), ("trained on", False), ("seeds", True), *((t, True) for t in tracks)]
        return ['<section id="transfer">', "<h2>Transfer: success of every learned entry on every track</h2>",
                ("<p>Replay tracks: average over the four paper scenes; CrowdNav tracks: its test cases. Mean [95% "
                "interval] over seeds; highlighted: the track the entry was trained on.</p>"),
                *table(head, rows, tid="transfer"), "</section>"]

    def submissions_section(self) -> list[str]:
        rows = []
        for entry in sorted(self.entries, key=order):
            for name in self.names(entry):
                d = next(r["submission"] for r in self.entries[entry] if r["meta"]["submission"] == name)
                authors = d["authors"] if isinstance(d["authors"], str) else ", ".join(map(str, d["authors"]))
                rows.append([f'<td data-sort="{e(name)}"><a href="{self.href(entry, anchor=name)}">{e(name)}</a></td>',
                             *(td(None, x) for x in (entry[0], d["kind"], model_of(d),
                                                     d.get("algo", "—"), d.get("seed", "—"), authors)),
                             f'<td data-sort="{e(d.get("link", ""))}">{external(d.get("link"))}</td>'])
        head = [(h, h == "seed") for h in ("submission", "entry", "kind", "encoder / policy", "algo", "seed",
                                           "authors", "link")]
        return ['<section id="submissions">', "<h2>Submissions</h2>", *table(head, rows, tid="submissions"),
                "</section>"]

    def index(self, missing: list[str], rejected: list[str], plot: bool) -> str:
        official = self.episodes is None and set(self.scenes) == set(EVAL_SCENES)
        nav = " · ".join(f'<a href="#track-{e(t)}">{e(t)}</a>' for t in self.by_track)
        body = ["<header>", f"<h1>crowdbench leaderboard (protocol {e(PROTOCOL_VERSION)})</h1>",
                ("<p>Every number is computed by the harness (<code>crowdbench leaderboard</code>) from the "
                "submissions in <code>leaderboard/submissions/</code>; these tables show the same results as "
                "<code>leaderboard/README.md</code> and <code>TRACKS.md</code>. The <strong>oracle</strong> is "
                "PRIVILEGED (it knows every replayed human's future): an upper bound, not a navigation policy.</p>"),
                *([] if official else [(f'<p class="warn"><strong>UNOFFICIAL subset</strong>: '
                                       f'{e(self.episodes or 250)} episodes per scene, scenes '
                                       f'{e(", ".join(self.scenes))}.</p>')]),
                (f'<nav>Tracks: {nav} · <a href="#transfer">transfer</a> · <a href="#submissions">submissions'
                "</a></nav>"), "</header>", "<main>"]
        if plot:
            body.append('<p><img class="plot" src="leaderboard.png" alt="success and dangers per episode, ranked"></p>')
        for name in self.by_track:
            body += self.track_section(name)
        body += self.transfer_section() + self.submissions_section()
        for title, items in (("Not evaluated", missing), ("Rejected submissions", rejected)):
            if items:
                body += [f"<section><h2>{title}</h2><ul>", *(f"<li>{e(m)}</li>" for m in items), "</ul></section>"]
        return page("crowdbench leaderboard", [*body, "</main>"])

    # ------------------------------------------------------------------ entry pages
    def results_of(self, name: str) -> list[tuple[str, dict]]:
        return [(t, r) for t, rs in self.by_track.items() for r in rs if r["meta"]["submission"] == name]

    def submission_block(self, name: str, data: dict) -> list[str]:
        rows = []
        for key in [k for k in SCHEMA if k in data]:
            v = data[key]
            if key == "link":
                cell = external(v)
            elif key == "notes":
                cell = f'<pre class="notes">{e(v)}</pre>'
            elif isinstance(v, list):
                cell = "<br>".join(f"<code>{e(x)}</code>" for x in v) if key == "overrides" else e(", ".join(map(str, v)))
            elif isinstance(v, dict):
                cell = "<br>".join(f"<code>{e(k)}: {e(x)}</code>" for k, x in v.items()) or "{}"
            else:
                cell = e(v)
            rows.append(f"<tr><th scope=\"row\">{e(key)}</th><td>{cell}</td></tr>")
        L = [f'<section class="submission" id="{e(name)}">', f"<h2>{e(name)}</h2>",
             "<h3><code>submission.yaml</code></h3>", '<table class="fields"><tbody>', *rows, "</tbody></table>"]
        command = training_command(data)
        if command:
            L += ["<h3>Training command</h3>", f"<pre><code>{e(command)}</code></pre>"]
        if data.get("kind") == "learned":
            L += ["<details><summary>The checkpoint's config</summary>", (f"<pre>{e(checkpoint_config(self.root, name))}"
                  "</pre></details>")]
        for track, r in self.results_of(name):
            metrics, cols = metrics_of([r]), table_columns(units(TRACKS[track], list(r["scenes"])))
            rows = [[td(None, metric_info(m)[0])] + [td(*table_cell([r], c, m, metric_info(m)[1])) for c in cols]
                    for m in metrics]
            L += [f"<h3>Track <code>{e(track)}</code>: {e(TRACKS[track].title)}</h3>",
                  *table([("metric", False), *((c, True) for c in cols)], rows, tid=f"{name}.{track}")]
        return [*L, "</section>"]

    def media_block(self, name: str, manifest: dict | None) -> list[str]:
        if not manifest:
            return []
        base = f"../media/{quote(name)}/"
        links = [f'<li><a href="{base}{quote(x["recording"])}" download>{e(x["recording"])}</a> '
                 f'(episode {e(x["episode"])}: {e(x["outcome"])})</li>' for x in manifest["episodes"]]
        replays = [f'<figure class="replay"><img src="{base}{quote(x["replay"])}" alt="replay of episode '
                   f'{e(x["episode"])}"><figcaption>episode {e(x["episode"])}: {e(x["outcome"])}, {e(x["steps"])} '
                   "steps</figcaption></figure>" for x in manifest["episodes"] if x.get("replay")]
        return ['<section class="media">', f"<h2>Trajectories: {e(name)}, {e(manifest['stamp']['scene'])}</h2>",
                f'<img src="{base}{quote(manifest["figure"])}" alt="trajectories of {e(name)}">',
                *(["<h3>Replays (one frame per step, real time)</h3>", '<div class="replays">', *replays, "</div>"]
                  if replays else []),
                "<p>Rerun recordings (open with <code>rerun FILE.rrd</code>):</p>", "<ul>", *links, "</ul>",
                "</section>"]

    def entry_page(self, entry: tuple, media: dict[str, dict | None]) -> str:
        names = self.names(entry)
        rs = self.entries[entry]
        kinds = sorted({r["meta"]["kind"] + (" (privileged)" if r.get("privileged") else "") for r in rs})
        origins = sorted({trained_on(r) for r in rs if trained_on(r)})
        seeds = ", ".join(f'<a href="#{e(quote(n))}">{e(n)}</a>' for n in names)
        body = ["<header>", '<p><a href="../index.html">← leaderboard</a></p>', f"<h1>{e(entry[0])}</h1>",
                f"<p>{e(', '.join(kinds))}" + (f"; trained on {e(', '.join(origins))}" if origins else "") +
                f"; {len(names)} submission(s): {seeds}</p>", "</header>", "<main>"]
        body += self.media_block(names[0], media.get(names[0]))
        for name in names:
            data = next(r["submission"] for r in rs if r["meta"]["submission"] == name)
            body += self.submission_block(name, data)
        return page(f"{entry[0]}: crowdbench leaderboard", [*body, "</main>"], depth=1)


def key(r: dict) -> tuple[str, str | None]:
    """The entry of a result: its label and the track it was trained on (None: a baseline, the oracle)."""
    return r["meta"]["entry"], trained_on(r)


def order(entry: tuple[str, str | None]) -> tuple:
    return entry[0].lower(), origin_rank(entry[1]) if entry[1] else -1


def training_command(data: dict) -> str | None:
    """A learned submission's ``crowdbench run`` command from its ``overrides`` (as ``crowdbench submit``
    records them) and ``experiment``; None for baselines, the oracle and a learned entry without either."""
    if data.get("kind") != "learned":
        return None
    over = data.get("overrides") or []
    tokens = [str(o) for o in over] if isinstance(over, list) else [f"{k}={v}" for k, v in over.items()]
    if data.get("experiment") and not any(t.startswith("experiment=") for t in tokens):
        tokens.insert(0, f"experiment={data['experiment']}")
    return "crowdbench run " + " ".join(map(shlex.quote, tokens)) if tokens else None


def checkpoint_config(root: Path, name: str) -> str:
    """The config saved in a learned submission's checkpoint, as YAML (loaded with ``weights_only``)."""
    from crowdbench.algos.checkpoint import load_checkpoint
    from crowdbench.leaderboard.submission import read_submission

    try:
        cfg = load_checkpoint(read_submission(root / "submissions" / name).checkpoint)["config"]
        return yaml.safe_dump(cfg, sort_keys=False, width=100)
    except Exception as ex:  # noqa: BLE001 - shown on the page instead of the config
        return f"(unavailable: {type(ex).__name__}: {' '.join(str(ex).split())[:300]})"


def write_site(out: Path, root: Path, by_track: dict[str, list[dict]], scenes: list[str], episodes: int | None,
               figures: int = 2, missing: list[str] = (), rejected: list[str] = (), log=print,
               limits: Limits = DEFAULT_LIMITS, scene: str = SCENE) -> Path:
    """Write the site into ``out`` (``index.html``, ``entries/``, ``assets/``, ``media/``); returns the index.
    ``figures``: episodes of ``scene`` per entry for its figure and recordings (0: none), cached by
    the fingerprint of its v1 result."""
    out, root = Path(out), Path(root)
    site = Site(root, by_track, scenes, episodes)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copytree(ASSETS, out / "assets", dirs_exist_ok=True)
    plot = (root / "leaderboard.png").is_file()
    if plot:
        shutil.copyfile(root / "leaderboard.png", out / "leaderboard.png")
    shutil.rmtree(out / "plots", ignore_errors=True)
    if (root / "plots").is_dir():  # the tracks' ranked plots
        shutil.copytree(root / "plots", out / "plots")
    v1 = {r["meta"]["submission"]: r["harness"].get("fingerprint") for r in site.by_track.get("v1", [])}
    media = {}
    for entry in sorted(site.entries, key=order):
        first = site.names(entry)[0]
        media[first] = entry_media(out, root, first, v1.get(first), figures, log, limits, scene)
    if (out / "media").is_dir():  # the media of submissions no longer shown
        for d in (out / "media").iterdir():
            if d.name not in media:
                shutil.rmtree(d, ignore_errors=True)
    shutil.rmtree(out / "entries", ignore_errors=True)
    (out / "entries").mkdir()
    for entry in site.entries:
        (out / "entries" / f"{site.slugs[entry]}.html").write_text(site.entry_page(entry, media))
    index = out / "index.html"
    index.write_text(site.index(list(missing), list(rejected), plot and not (out / "plots").is_dir()))
    (out / "site.json").write_text(json.dumps({"protocol": PROTOCOL_VERSION, "scenes": scenes, "episodes": episodes,
                                               "tracks": list(site.by_track), "entries": len(site.entries)}) + "\n")
    return index
