"""The leaderboard run: validate every submission, evaluate it on every track it fits (cached by
fingerprint), write the results and regenerate the tables; ``--check`` re-evaluates and compares.

Results: ``leaderboard/results/<name>/results.json`` (track v1, the layout from before tracks) and
``leaderboard/results/<name>/<track>.json``. Tables: ``leaderboard/README.md`` (protocol v1: the
baselines, the oracle and the entries trained on v1; plus the generated blocks of the README and the
docs) and ``leaderboard/TRACKS.md`` (every track, and the transfer table).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import yaml
from tqdm import tqdm

from crowdbench.envs.protocol import EVAL_SCENES, PROTOCOL_VERSION
from crowdbench.leaderboard import render
from crowdbench.leaderboard.budget import with_budgets
from crowdbench.leaderboard.cache import fingerprint
from crowdbench.leaderboard.entries import entry_problems
from crowdbench.leaderboard.harness import LauncherError, _evaluate_all
from crowdbench.leaderboard.sandbox import DEFAULT_LIMITS, Limits, SandboxError, confinement, sandbox_name
from crowdbench.leaderboard.store import RootBusy, locked, read_cached, write_atomic, write_results
from crowdbench.leaderboard.submission import DEFAULT_ROOT, SubmissionError, read_submission
from crowdbench.leaderboard.track_tables import render_tracks, trained_on
from crowdbench.leaderboard.tracks import TRACK_ORDER, TRACKS, check_tracks
from crowdbench.protocols import get as protocol
from crowdbench.protocols import names as protocol_names
from crowdbench.protocols.lists import ListError

TRACKS_FILE = "TRACKS.md"


def _tag(sub: str, track: str) -> str:
    return sub if track == "v1" else f"{sub} ({track})"


def _targets(readme, docs, log) -> list[tuple[Path, str]] | None:
    """``(file, text)`` whose generated v1 blocks are rendered; None (after logging) if one lacks its block."""
    targets = []
    for path, names in ([(readme, ["results"])] if readme is not None else []) + \
            [(d, [n for n in render.BLOCKS if n != "results"]) for d in docs or []]:
        path = Path(path)
        text = path.read_text() if path.is_file() else ""
        if not set(render.blocks_in(text)) & set(names):
            start, end = render.markers(names[0])
            log(f"crowdbench leaderboard: error: {path} has no {start} ... {end} block")
            return None
        targets.append((path, text))
    return targets


def _scene_problem(scenes: list[str]) -> str | None:
    """``file: problem`` of the first evaluation scene whose recording or v1 / v2 episode list is missing,
    corrupted or not the published one, or None; checked once up front so that a broken install stops
    the run, not every submission."""
    from crowdbench.data import scenes as data

    for s in scenes:
        path = data.DATA_DIR / f"{s}.txt"
        try:
            data.read_rows(s)
        except (OSError, ValueError) as e:  # missing, sha256 mismatch, unknown scene
            return f"{path}: {' '.join(str(e).replace(str(path), 'the file').split())}"
    try:
        for name in protocol_names():
            protocol(name).check_lists(scenes)  # missing, not JSON, or not the published list (protocols/lists.py)
    except ListError as e:
        return str(e)
    return None


def _committed(path: Path) -> dict | None:
    """The results file as it is on disk (whatever its fingerprint), or None if there is none readable."""
    try:
        res = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return res if isinstance(res, dict) else None


def _print(msg: str) -> None:
    tqdm.write(msg, file=sys.stdout)  # above the progress bar, if any
    sys.stdout.flush()


def _terminate(signum, frame):
    raise SystemExit(128 + signum)  # unwinds: every job's finally kills its worker, the pool is terminated


def missing_line(name: str, track: str) -> str:
    """How TRACKS.md lists a submission's track without results (and the command that evaluates it)."""
    return f"{name} ({track}): results missing or out of date (`crowdbench leaderboard --only {name} --tracks {track}`)"


def unevaluated(root: Path, by_track: dict[str, list[dict]], tracks=TRACK_ORDER) -> list[str]:
    """:func:`missing_line` of every learned submission under ``root`` and every one of ``tracks`` it fits
    that ``by_track`` holds no result of, in the order a run lists them (submission, then track)."""
    subs = {d.name: yaml.safe_load((d / "submission.yaml").read_text()) or {}
            for d in sorted((Path(root) / "submissions").iterdir()) if (d / "submission.yaml").is_file()}
    have = {t: {r["meta"]["submission"] for r in by_track.get(t, [])} for t in TRACK_ORDER}
    return [missing_line(n, t) for n, d in subs.items() if d.get("kind") == "learned" for t in tracks
            if TRACKS[t].fits("learned", bool(d.get("privileged")), d.get("track", "v1")) and n not in have[t]]


def run(root: Path = DEFAULT_ROOT, only: list[str] | None = None, check: bool = False, force: bool = False,
        episodes: int | None = None, scenes: list[str] | None = None, log=None, **kw) -> int:
    """:func:`_run` holding the root's lock (not with ``check``, which writes nothing), with SIGTERM
    unwinding like Ctrl-C, and a file that cannot be written as one line (the previous one is kept)."""
    root = Path(root)
    log = log or _print
    stack = contextlib.ExitStack()
    try:
        with stack:
            if threading.current_thread() is threading.main_thread():
                old = signal.signal(signal.SIGTERM, _terminate)
                stack.callback(signal.signal, signal.SIGTERM, old)
            if root.is_dir() and not check:
                if not os.access(root, os.W_OK):
                    log(f"crowdbench leaderboard: error: {root} is not writable (--check needs no write access)")
                    return 1
                stack.enter_context(locked(root))
            return _run(root, only=only, check=check, force=force, episodes=episodes, scenes=scenes, log=log, **kw)
    except RootBusy as e:
        log(f"crowdbench leaderboard: error: {e}")
        return 1
    except OSError as e:
        if e.filename is None:
            raise
        log(f"crowdbench leaderboard: error: cannot write {e.filename}: {e.strerror}; the previous file is kept")
        return 1


def _run(root: Path, only: list[str] | None = None, check: bool = False, force: bool = False,
         episodes: int | None = None, scenes: list[str] | None = None, log=None, jobs: int = 1,
         launcher: str = "local", address: str | None = None, readme: Path | None = None,
         docs: list[Path] | None = None, tracks: list[str] | None = None, limits: Limits = DEFAULT_LIMITS,
         site: Path | None = None, site_figures: int = 2, progress: bool = False) -> int:
    """Validate, evaluate and render; returns the exit code (0 ok, 1 a submission failed or --check differs).

    ``tracks``: the tracks evaluated (default all; the others keep their cached results, and ``--check``
    compares only their tables). ``readme``: a file whose block between the ``generated:results``
    markers is regenerated too; ``docs``: files whose generated blocks (``render.BLOCKS``) are
    regenerated too (None: no other file is touched). Both are protocol v1's. ``limits``: the bounds
    and the sandbox of the learned submissions' worker processes (crowdbench/leaderboard/sandbox.py).
    ``site``: also write the web site into this directory from the same results (not with ``check``;
    crowdbench/leaderboard/site.py), with ``site_figures`` episodes per entry for its figures.
    ``progress``: a progress bar on stderr over the (submission, track) evaluations."""
    scenes = list(scenes or EVAL_SCENES)
    try:
        tracks = check_tracks(tracks)
        sandbox = sandbox_name(limits)
    except (ValueError, SandboxError) as e:
        log(f"crowdbench leaderboard: error: {e}")
        return 1
    log(confinement(sandbox, limits))
    sub_root = root / "submissions"
    dirs = sorted(p for p in sub_root.iterdir() if p.is_dir()) if sub_root.is_dir() else []
    if not dirs:
        log(f"crowdbench leaderboard: error: no submissions under {sub_root}")
        return 1
    names = [d.name for d in dirs]
    unknown = [n for n in (only or []) if n not in names]
    if unknown:
        log(f"crowdbench leaderboard: error: unknown submission(s) {', '.join(unknown)}; known: {', '.join(names)}")
        return 1
    targets = _targets(readme, docs, log) if "v1" in tracks else []
    if targets is None:
        return 1
    problem = _scene_problem(scenes)
    if problem:
        log(f"crowdbench leaderboard: error: {problem}")
        return 1
    results: dict[str, list[dict]] = {t: [] for t in TRACK_ORDER}
    rejected: list[tuple[str | None, str]] = []  # (track or None for every track, message)
    missing: list[tuple[str, str]] = []
    todo = []
    unverified = 0
    t_all = time.time()

    def reject(e: SubmissionError, track: str | None) -> None:
        log(f"crowdbench leaderboard: error: {e}" + (f" (track {track})" if track else ""))
        rejected.append((track, e.public.replace(str(root.resolve()) + "/", "").replace(str(root) + "/", "")))

    subs = []
    for d in dirs:
        try:  # (a learned entry's code is imported only by its worker: crowdbench/leaderboard/worker.py)
            subs.append((d, read_submission(d)))
        except SubmissionError as e:
            reject(e, None)
    conflicts = entry_problems([sub for _, sub in subs])
    for d, sub in subs:
        if sub.name in conflicts:
            reject(conflicts[sub.name], None)
            continue
        for name in TRACK_ORDER:
            track = TRACKS[name]
            origin = sub.data.get("track", "v1") if sub.kind == "learned" else None
            if not track.fits(sub.kind, sub.data.get("privileged", False), origin) or (check and name not in tracks):
                continue
            res_path = root / "results" / d.name / track.results_file
            selected = (only is None or d.name in only) and name in tracks
            try:
                fp = fingerprint(sub, scenes, episodes, track)
            except SubmissionError as e:
                reject(e, None)
                break
            if check and not selected:  # --check --only: the other rows as committed, the named ones re-evaluated
                committed = _committed(res_path)
                if committed is not None:
                    results[name].append(committed)
                else:  # listed as the run that wrote the tables lists it (a full --check evaluates it)
                    missing.append((name, missing_line(d.name, name)))
                continue
            cached, why = (None, None) if check else read_cached(res_path, d.name, sub.kind, sub.data, fp)
            trusted = cached is not None and why is None
            if not check and (trusted and not force or not selected):
                if cached is None and why == "out of date" and not selected:
                    # --only: the other rows keep their results as on disk even when the code changed since
                    # (only the named rows are re-evaluated; dropping the rest emptied the tables)
                    cached = _committed(res_path)
                if cached is not None:  # (unselected and not in the ledger: shown as committed, counted below)
                    results[name].append(cached)
                    if selected:
                        log(f"{_tag(d.name, name)}: unchanged, cached results; --force re-evaluates")
                    unverified += not trusted
                else:
                    missing.append((name, missing_line(d.name, name)))
                continue
            if why and selected and not force:
                log(f"{_tag(d.name, name)}: cached results {why}: re-evaluated")
            todo.append((d, sub, name, fp, res_path))
    learned_tracks = list(dict.fromkeys(name for _, sub, name, _, _ in todo if sub.kind == "learned"))
    if learned_tracks:
        limits = with_budgets(limits, learned_tracks, scenes, episodes, log)
    outcomes = _evaluate_all(todo, scenes, episodes, jobs, launcher, address, limits)
    bar = tqdm(total=len(todo), disable=not progress or not todo, unit="evaluation", desc="leaderboard",
               dynamic_ncols=True, file=sys.stderr)
    while True:
        if bar.n < len(todo):  # the evaluation waited for next (in order; with --jobs / Ray others run too)
            bar.set_postfix_str(f"{todo[bar.n][0].name} on {todo[bar.n][2]}")
        try:
            d, sub, name, res_path, outcome = next(outcomes)
        except StopIteration:
            break
        except LauncherError as e:
            bar.close()
            log(f"crowdbench leaderboard: error: {e}")
            return 1
        bar.update(1)
        if isinstance(outcome, SubmissionError):
            reject(outcome, name)
            continue
        res, seconds = outcome
        head = "average success (paper scenes)" if TRACKS[name].replay else "success"
        value = res.get("average_paper_scenes", {}).get("success_rate") if TRACKS[name].replay else \
            res["scenes"][TRACKS[name].setting]["success_rate"]["mean"]
        log(f"{_tag(d.name, name)}: evaluated in {seconds:.1f} s; {head} {render.fmt(value, 3)}")
        results[name].append(res)
        if not check:
            write_results(res_path, res)
            if sub.kind == "oracle" and name == "v1":
                write_atomic(res_path.parent / "unavoidable.json", json.dumps(
                    {"privileged": True, "note": "episodes the privileged oracle fails: candidate unavoidable",
                     "protocol": PROTOCOL_VERSION, "scenes": res["unavoidable"]}, indent=1) + "\n")
    bar.close()
    failed = bool(rejected)
    v1 = [r for r in results["v1"] if trained_on(r) in (None, "v1")]
    v1_rejected = sorted(m for t, m in rejected if t in (None, "v1"))
    v1_missing = [m for t, m in missing if t == "v1"]
    table = render.render_readme(v1, v1_rejected, scenes, episodes, v1_missing)
    shown = {t: results[t] for t in TRACK_ORDER if t in tracks or results[t]}
    all_rejected = sorted(f"{m} (track {t})" if t else m for t, m in rejected)
    board = render_tracks(shown, scenes, episodes, [m for _, m in missing], all_rejected)
    if unverified:
        log(f"note: {unverified} cached result(s) not selected, out of date or not written by this harness, are "
            "shown as they are on disk; a run without --only re-evaluates them (docs/submitting.md, Cache)")
    log(f"leaderboard: {sum(map(len, results.values()))} results evaluated/cached on {len(tracks)} track(s), "
        f"{len(rejected)} rejected, {time.time() - t_all:.1f} s")
    if check:
        return _check(root, tracks, table, board, targets, v1, scenes, episodes, log) or (1 if failed else 0)
    from crowdbench.leaderboard.plots import colour_map, track_plot, v1_plot

    wrote = []
    colours = colour_map([r for rs in shown.values() for r in rs])  # one colour per method in every plot
    if "v1" in tracks:
        write_atomic(root / "README.md", table)
        if v1:
            v1_plot(v1, scenes, root / "leaderboard.png", colours)
        wrote += [str(root / "README.md"), str(root / "leaderboard.png")]
        for path, _ in targets:
            # read again: the file may have been edited during the run (minutes to hours), and only its
            # generated blocks are the run's to replace
            text = path.read_text() if path.is_file() else ""
            new = render.regenerate(text, v1, scenes, episodes)
            if new != text:
                write_atomic(path, new)
            wrote.append(f"the results block of {path}" if render.blocks_in(text) == ["results"] else
                         f"the generated blocks of {path}")
    write_atomic(root / TRACKS_FILE, board)
    wrote.append(str(root / TRACKS_FILE))
    for t, rs in shown.items():
        if rs:
            track_plot(TRACKS[t], rs, root / "plots" / f"{t}.png", colours)
    wrote.append(f"{root / 'plots'}/<track>.png")
    if site is not None:  # from the results just written: the tables' numbers
        from crowdbench.leaderboard.site import write_site

        t_site = time.time()
        index = write_site(site, root, results, scenes, episodes, site_figures, [m for _, m in missing],
                           all_rejected, log, limits)
        wrote.append(f"{index} ({time.time() - t_site:.1f} s)")
    log(f"wrote {', '.join(wrote)}")
    return 1 if failed else 0


def _check(root: Path, tracks: list[str], table: str, board: str, targets, v1, scenes, episodes, log) -> int:
    """Compare the generated text of the checked tracks with the committed files; 1 if anything differs."""
    diffs = []
    if "v1" in tracks:
        committed = (root / "README.md").read_text() if (root / "README.md").is_file() else ""
        if committed != table:
            diffs += render.diff_rows(committed, table) or ["(whitespace or layout)"]
        for path, text in targets:
            for name in render.blocks_in(text):
                old, new = render.read_block(text, name), render.BLOCKS[name](v1, scenes, episodes)
                if old != new:
                    where = f"{path}" if name == "results" else f"{path} ({name})"
                    diffs += [f"{where}: {m}" for m in render.diff_rows(old, new) or ["(whitespace or layout)"]]
    path = root / TRACKS_FILE
    committed = path.read_text() if path.is_file() else ""
    blocks = [f"track-{t}" for t in tracks] + (["transfer"] if len(tracks) == len(TRACK_ORDER) else [])
    for name in blocks:
        old = render.read_block(committed, name) if render.markers(name)[0] in committed else ""
        new = render.read_block(board, name)
        if old != new:
            diffs += [f"{TRACKS_FILE} ({name}): {m}" for m in render.diff_rows(old, new) or ["(whitespace or layout)"]]
    if diffs:
        log("crowdbench leaderboard --check: FAILED: the generated text differs from a fresh evaluation in "
            f"{len(diffs)} row(s):\n  " + "\n  ".join(diffs))
        return 1
    log(f"crowdbench leaderboard --check: every table of track(s) {', '.join(tracks)} matches a fresh evaluation"
        + (f" (and the generated blocks of {', '.join(str(p) for p, _ in targets)})" if targets else ""))
    return 0
