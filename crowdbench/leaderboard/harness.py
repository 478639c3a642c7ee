"""The harness: build each submission's policy (crowdbench.policies), evaluate it, fan the jobs out.

Layout (``--root``, default ``./leaderboard``)::

    leaderboard/submissions/<name>/submission.yaml   (+ checkpoint.pt for learned entries)
    leaderboard/results/<name>/results.json           track v1, written by the harness, never by hand
    leaderboard/results/<name>/<track>.json           the other tracks (crowdbench.leaderboard.tracks)
    leaderboard/results/oracle/unavoidable.json       episodes the privileged oracle fails
    leaderboard/README.md, TRACKS.md, leaderboard.png generated (crowdbench.leaderboard.board)

The harness computes every number itself (each track's protocol, crowdbench/protocols/, the
same code as ``crowdbench eval``); submitters only provide a yaml and, for learned entries, a
state-dict checkpoint (``torch.load(..., weights_only=True)``) and optionally an encoder module. A
learned entry's code and checkpoint are loaded only in its worker process
(crowdbench/leaderboard/worker.py), which receives observations and returns actions.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import tempfile
import time
from pathlib import Path

import torch

from crowdbench import policies
from crowdbench.envs.protocol import EVAL_SCENES
from crowdbench.leaderboard.budget import budget_of
from crowdbench.leaderboard.cache import HARNESS_VERSION
from crowdbench.leaderboard.sandbox import DEFAULT_LIMITS, Limits
from crowdbench.leaderboard.submission import (
    Submission,
    SubmissionError,
    baseline_args,
    policy_error,
)
from crowdbench.leaderboard.tracks import (
    TRACKS,
    Track,
    evaluate_track,
    track_config,
)
from crowdbench.leaderboard.worker import WorkerError, WorkerPolicy
from crowdbench.numerics import PINNED

OUTCOME_CHAR = {"success": "S", "collision": "C", "timeout": "T"}
LAUNCHERS = ("local", "ray")


class LauncherError(RuntimeError):
    """The launcher itself cannot run (not a submission's fault): the run stops with one line."""


def build_policy(sub: Submission, track: Track = TRACKS["v1"], limits: Limits = DEFAULT_LIMITS):
    """The :class:`~crowdbench.envs.observation.Policy` of a validated submission: a learned one behind its
    worker process (close it: a context manager), a baseline or the oracle built by the registry with
    ``track``'s env config, as ``crowdbench eval`` with it builds them."""
    if sub.kind == "learned":
        try:
            worker = WorkerPolicy(sub.dir, sub.name, limits)
        except WorkerError as e:
            raise SubmissionError(sub.yaml_path, e.field, str(e), e.public) from None
        # the worker is not trusted to say how it acts: the candidates it is handed follow submission.yaml
        declared, said = getattr(worker, "lookahead", (None,))[0], sub.data.get("lookahead")
        if declared != said:
            worker.close()
            raise SubmissionError(sub.yaml_path, "lookahead", f"{said!r} but its policy acts with lookahead "
                                                              f"{declared!r}")
        return worker
    try:
        policy = policies.build(*baseline_args(sub.data, track_config(track)))
    except policies.PolicyError as e:
        raise policy_error(sub.yaml_path, e) from None
    policy.name = sub.name
    return policy


def evaluate_submission(sub: Submission, policy, scenes: list[str], episodes: int | None, fp: str,
                        track: Track = TRACKS["v1"]) -> dict:
    """Run ``track``'s protocol (the evaluation code ``crowdbench eval`` runs); add per-episode outcome strings."""
    meta = {"submission": sub.name, "kind": sub.kind, "entry": sub.entry}
    if track.name != "v1":  # (v1's results keep their pre-track layout)
        meta.update(track=track.name, trained_on=sub.data.get("track", "v1") if sub.kind == "learned" else None)
    with tempfile.TemporaryDirectory() as tmp:
        res = evaluate_track(track, policy, scenes, episodes, Path(tmp), meta)
        track.evaluator.check_results(res)  # (the replay lists are checked before any job starts)
        rows = [json.loads(line) for line in (Path(tmp) / "episodes.jsonl").read_text().splitlines()]
    outcomes: dict[str, list] = {s: [] for s in res["scenes"]}
    for r in rows:
        outcomes[r.get("scene", r.get("setting"))].append((r["episode"], OUTCOME_CHAR[r["outcome"]]))
    res["episode_ids"] = {s: [e for e, _ in v] for s, v in outcomes.items()}
    res["episode_outcomes"] = {s: "".join(c for _, c in v) for s, v in outcomes.items()}
    res["submission"] = sub.data
    res["harness"] = {"version": HARNESS_VERSION, "scenes": scenes if track.replay else [track.setting],
                      "episodes": episodes, "official": episodes is None and (set(scenes) == set(EVAL_SCENES)
                                                                            or not track.replay), "fingerprint": fp}
    if track.name != "v1":
        res["harness"]["track"] = track.name
    if sub.data.get("lookahead"):
        res["lookahead"] = sub.data["lookahead"]
    if sub.data.get("privileged"):  # the oracle; a value entry that reads the simulator's next human states
        res["privileged"] = True
    if sub.kind == "oracle":
        res["unavoidable"] = unavoidable(res)
    return res


def unavoidable(res: dict) -> dict:
    """Episodes the oracle fails: candidate unavoidable collisions (and timeouts), per scene."""
    out = {}
    for s, chars in res["episode_outcomes"].items():
        ids = res["episode_ids"][s]
        out[s] = {"collision": [ids[i] for i, c in enumerate(chars) if c == "C"],
                  "timeout": [ids[i] for i, c in enumerate(chars) if c == "T"], "episodes": len(chars)}
    return out


# ---------------------------------------------------------------------------------- jobs
def _job(sub: Submission, tracks: list[tuple[str, str]], scenes: list[str], episodes: int | None,
         limits: Limits = DEFAULT_LIMITS) -> list:
    """Evaluate one validated submission on each of ``tracks`` (``(track, fingerprint)`` pairs): per
    track ``(results, seconds)`` or the :class:`SubmissionError`.

    A learned entry's tracks share one worker process (starting it, ~2.5 s, costs about as much as
    its whole v1 evaluation); a worker that failed is replaced for the next track. Single-threaded
    (``torch.set_num_threads(1)``; the worker too) whatever the caller's setting, so the
    floating-point reductions, and hence the numbers, do not depend on the machine or ``--jobs``.
    Any failure of an evaluation is that submission's rejection on that track, never the whole run's.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    out, worker = [], None
    try:
        for i, (track, fp) in enumerate(tracks):
            t, t_ = time.time(), TRACKS[track]
            loading = sub.kind == "learned" and worker is None
            try:
                if sub.kind == "learned":
                    worker = worker or build_policy(sub, t_, limits)
                    worker.steps = 0
                    budget = budget_of(limits, track)
                    if budget is not None:
                        worker.start_budget(budget, f"{limits.budget_factor:g} x ORCA's time on track {track}, "
                                                    "--budget-factor")
                policy = worker or build_policy(sub, t_, limits)
                out.append((evaluate_submission(sub, policy, scenes, episodes, fp, t_), time.time() - t))
                continue
            except SubmissionError as e:
                out.append(e)
            except WorkerError as e:
                out.append(SubmissionError(sub.yaml_path, e.field, str(e), e.public))
            except Exception as e:  # noqa: BLE001 - e.g. a model that fails on a real observation mid-episode
                out.append(_failed(sub, e))
            if loading and worker is None:  # it failed to load: it would on the next track too (M7: 300 s each)
                out += [out[-1]] * (len(tracks) - i - 1)
                break
            if worker is not None:
                worker.close()
                worker = None
        return out
    finally:
        if worker is not None:
            worker.close()
        torch.set_num_threads(threads)


def _failed(sub: Submission, e: BaseException) -> SubmissionError:
    e = getattr(e, "cause", None) or e  # a Ray task's error wraps the exception it raised
    return SubmissionError(sub.yaml_path, None, f"evaluation failed: {type(e).__name__}: {e}")


def _absolute(sub: Submission) -> Submission:
    """Workers may run in another directory (Ray): give them absolute paths."""
    return dataclasses.replace(sub, dir=sub.dir.resolve(), yaml_path=sub.yaml_path.resolve(),
                               checkpoint=sub.checkpoint.resolve() if sub.checkpoint else None,
                               extra_files=[p.resolve() for p in sub.extra_files])


def _groups(todo: list) -> list[tuple[Submission, list[tuple[str, str]]]]:
    """``todo``'s consecutive entries of one submission as one job: ``(submission, [(track, fp), ...])``."""
    groups: list = []
    for d, sub, track, fp, _ in todo:
        if groups and groups[-1][0] == d:
            groups[-1][2].append((track, fp))
        else:
            groups.append((d, sub, [(track, fp)]))
    return [(sub, tracks) for _, sub, tracks in groups]


def _local(todo: list, scenes, episodes, jobs: int, limits: Limits):
    groups = _groups(todo)
    if jobs <= 1 or len(groups) <= 1:
        for sub, tracks in groups:
            yield from _job(sub, tracks, scenes, episodes, limits)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"), initializer=_pool_init) as pool:
        try:
            futures = [pool.submit(_job, sub, tracks, scenes, episodes, limits) for sub, tracks in groups]
            for (sub, tracks), fut in zip(groups, futures, strict=True):
                try:
                    yield from fut.result()
                except Exception as e:  # noqa: BLE001 - a crashed job process
                    yield from [_failed(sub, e)] * len(tracks)
        except BaseException:  # Ctrl-C, SIGTERM (crowdbench/leaderboard/board.py), the generator closed early
            _stop(pool)
            raise


def _pool_init() -> None:
    # SIGTERM unwinds a job like Ctrl-C: its finally kills its worker's process group
    signal.signal(signal.SIGTERM, _raise_exit)


def _raise_exit(signum, frame):
    raise SystemExit(128 + signum)


def _stop(pool) -> None:
    """Terminate the pool's processes now (``shutdown`` alone waits for the running jobs to finish)."""
    procs = list(getattr(pool, "_processes", {}).values())  # (no public API lists them)
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=5)


def _ray(todo: list, scenes, episodes, jobs: int, address: str | None, limits: Limits):
    """One Ray task per submission (all its tracks): a local cluster of ``jobs`` CPUs, or the cluster at ``address``
    (``auto``, ``ray://host:10001``; crowdbench installed and the leaderboard directory at the same
    absolute path on its nodes)."""
    try:
        import ray

        started = not ray.is_initialized()
        if started:
            if address:
                ray.init(address=address)
            else:  # a small object store: results are a few hundred kB
                ray.init(num_cpus=jobs, include_dashboard=False, object_store_memory=100 * 1024 ** 2)
    except Exception as e:  # noqa: BLE001 - no ray, an unreachable address, ...: one line, not a traceback
        where = f"join the Ray cluster at {address}" if address else "start a local Ray cluster"
        raise LauncherError(f"--launcher ray: cannot {where}: {type(e).__name__}: {' '.join(str(e).split())}") \
            from None
    try:
        # the workers evaluate with this process's numerical path (crowdbench/numerics.py), on any node
        pinned = {k: os.environ[k] for k in PINNED if k in os.environ}
        task = ray.remote(num_cpus=1, max_retries=0, runtime_env={"env_vars": pinned})(_job)
        groups = _groups(todo)
        refs = [task.remote(_absolute(sub), tracks, scenes, episodes, limits) for sub, tracks in groups]
        for (sub, tracks), ref in zip(groups, refs, strict=True):
            try:
                yield from ray.get(ref)
            except Exception as e:  # noqa: BLE001 - the task raised or its worker died
                yield from [_failed(sub, e)] * len(tracks)
    finally:
        if started:
            ray.shutdown()


def _evaluate_all(todo: list, scenes: list[str], episodes: int | None, jobs: int, launcher: str,
                  address: str | None, limits: Limits = DEFAULT_LIMITS):
    """Yield ``(dir, submission, track, results path, (results, seconds) | SubmissionError)`` in ``todo`` order."""
    if launcher not in LAUNCHERS:
        raise ValueError(f"unknown launcher {launcher!r}; valid: {', '.join(LAUNCHERS)}")
    outs = _ray(todo, scenes, episodes, jobs, address, limits) if launcher == "ray" and todo else \
        _local(todo, scenes, episodes, jobs, limits)
    for (d, sub, track, _, res_path), out in zip(todo, outs, strict=True):
        yield d, sub, track, res_path, out
