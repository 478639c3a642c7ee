"""The harness: build each submission's policy (crowdbench.policies), evaluate it, fan the jobs out.

Layout (``--root``, default ``./leaderboard``)::

    leaderboard/submissions/<name>/submission.yaml   (+ checkpoint.pt for learned entries)
    leaderboard/results/<name>/results.json           written by the harness, never by hand
    leaderboard/results/oracle/unavoidable.json       episodes the privileged oracle fails
    leaderboard/README.md, leaderboard/leaderboard.png generated

The harness computes every number itself (``crowdbench.eval.evaluate``, the same code as
``crowdbench eval``); submitters only provide a yaml and, for learned entries, a state-dict
checkpoint (``torch.load(..., weights_only=True)``). ``--check`` re-evaluates everything,
writes nothing, and fails if the committed README (or a generated block of the top-level README or
the docs, ``crowdbench.leaderboard.render.BLOCKS``) differs.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import torch

from crowdbench import policies
from crowdbench.envs.protocol import EVAL_SCENES, PROTOCOL_VERSION
from crowdbench.eval import evaluate
from crowdbench.leaderboard import render
from crowdbench.leaderboard.cache import HARNESS_VERSION, fingerprint
from crowdbench.leaderboard.schema import (
    DEFAULT_ROOT,
    Submission,
    SubmissionError,
    baseline_args,
    policy_error,
    read_submission,
    register_encoder,
)
from crowdbench.numerics import PINNED

OUTCOME_CHAR = {"success": "S", "collision": "C", "timeout": "T"}
LAUNCHERS = ("local", "ray")


class LauncherError(RuntimeError):
    """The launcher itself cannot run (not a submission's fault): the run stops with one line."""


def dummy_obs(batch: int = 2, humans: int = 3):
    from crowdbench.envs.policy import obs_tensordict

    g = torch.Generator().manual_seed(0)
    robot = torch.zeros(batch, 1, 6)
    robot[..., 4] = 4.0
    h = torch.randn(batch, 1, humans, 4, generator=g)
    mask = torch.ones(batch, 1, humans, dtype=torch.bool)
    return obs_tensordict({"robot": robot, "humans": h, "humans_mask": mask}, batch)


def _learned_policy(sub: Submission):
    from crowdbench.algos.checkpoint import CheckpointError, load_checkpoint

    d, path = sub.data, sub.yaml_path
    register_encoder(sub)
    try:
        state = load_checkpoint(sub.checkpoint)  # weights_only=True: never runs pickled code
    except CheckpointError as e:
        raise SubmissionError(path, "checkpoint", str(e)) from None
    cfg = state["config"]
    try:
        c_enc, c_algo = cfg["encoder"]["name"], cfg["algo"]["name"]
        _ = cfg["env"]["v_max"], cfg["env"]["frame"]
    except (KeyError, TypeError) as e:
        raise SubmissionError(path, "checkpoint", f"{sub.checkpoint}: config lacks {e}") from None
    if c_enc != d["encoder"]:
        raise SubmissionError(path, "encoder", f"{d['encoder']!r} but the checkpoint was trained with {c_enc!r}")
    if c_algo != d["algo"]:
        raise SubmissionError(path, "algo", f"{d['algo']!r} but the checkpoint was trained with {c_algo!r}")
    try:
        policy = policies.from_checkpoint(sub.checkpoint)
    except policies.PolicyError as e:
        raise SubmissionError(path, "checkpoint", str(e)) from None
    try:
        out = policy.act(dummy_obs())
    except Exception as e:  # noqa: BLE001 - a model that cannot act on an observation is rejected
        raise SubmissionError(path, "checkpoint", f"the model fails on an observation: {type(e).__name__}: {e}") \
            from None
    if tuple(out.shape) != (2, 1, 2) or not torch.isfinite(out).all():
        raise SubmissionError(path, "checkpoint", f"the model returns actions of shape {tuple(out.shape)} "
                                                  "(expected [B, 1, 2], finite)")
    return policy


def build_policy(sub: Submission):
    """The :class:`~crowdbench.envs.policy.Policy` of a validated submission, built by the registry
    (baselines and the oracle with the env config's dynamics, as ``crowdbench eval`` builds them)."""
    if sub.kind == "learned":
        policy = _learned_policy(sub)
    else:
        try:
            policy = policies.build(*baseline_args(sub.data))
        except policies.PolicyError as e:
            raise policy_error(sub.yaml_path, e) from None
    policy.name = sub.name
    return policy


def evaluate_submission(sub: Submission, policy, scenes: list[str], episodes: int | None, fp: str) -> dict:
    """Run the protocol with ``crowdbench.eval.evaluate``; add per-episode outcome strings."""
    with tempfile.TemporaryDirectory() as tmp:
        res = evaluate(policy, scenes, episodes, out_dir=Path(tmp), save_episodes=True,
                       sim_overrides={"frame": policy.frame},
                       meta={"submission": sub.name, "kind": sub.kind, "entry": sub.entry})
        rows = [json.loads(line) for line in (Path(tmp) / "episodes.jsonl").read_text().splitlines()]
    outcomes: dict[str, list] = {s: [] for s in scenes}
    for r in rows:
        outcomes[r["scene"]].append((r["episode"], OUTCOME_CHAR[r["outcome"]]))
    res["episode_ids"] = {s: [e for e, _ in v] for s, v in outcomes.items()}
    res["episode_outcomes"] = {s: "".join(c for _, c in v) for s, v in outcomes.items()}
    res["submission"] = sub.data
    res["harness"] = {"version": HARNESS_VERSION, "scenes": scenes, "episodes": episodes,
                      "official": episodes is None and set(scenes) == set(EVAL_SCENES), "fingerprint": fp}
    if sub.kind == "oracle":
        res["privileged"] = True
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
def _job(sub: Submission, scenes: list[str], episodes: int | None, fp: str):
    """Evaluate one validated submission: ``(results, seconds)`` or the :class:`SubmissionError`.

    Single-threaded (``torch.set_num_threads(1)``) whatever the caller's setting, so the
    floating-point reductions, and hence the numbers, do not depend on the machine or ``--jobs``.
    Any failure of the evaluation is that submission's rejection, never the whole run's.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t = time.time()
        res = evaluate_submission(sub, build_policy(sub), scenes, episodes, fp)
        return res, time.time() - t
    except SubmissionError as e:
        return e
    except Exception as e:  # noqa: BLE001 - e.g. a model that fails on a real observation mid-episode
        return _failed(sub, e)
    finally:
        torch.set_num_threads(threads)


def _failed(sub: Submission, e: BaseException) -> SubmissionError:
    e = getattr(e, "cause", None) or e  # a Ray task's error wraps the exception it raised
    return SubmissionError(sub.yaml_path, None, f"evaluation failed: {type(e).__name__}: {e}")


def _absolute(sub: Submission) -> Submission:
    """Workers may run in another directory (Ray): give them absolute paths."""
    return dataclasses.replace(sub, dir=sub.dir.resolve(), yaml_path=sub.yaml_path.resolve(),
                               checkpoint=sub.checkpoint.resolve() if sub.checkpoint else None,
                               extra_files=[p.resolve() for p in sub.extra_files])


def _local(todo: list, scenes, episodes, jobs: int):
    if jobs <= 1 or len(todo) <= 1:
        for _, sub, fp, _ in todo:
            yield _job(sub, scenes, episodes, fp)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(_job, sub, scenes, episodes, fp) for _, sub, fp, _ in todo]
        for (_, sub, _, _), fut in zip(todo, futures, strict=True):
            try:
                yield fut.result()
            except Exception as e:  # noqa: BLE001 - a crashed worker process
                yield _failed(sub, e)


def _ray(todo: list, scenes, episodes, jobs: int, address: str | None):
    """One Ray task per submission: a local cluster of ``jobs`` CPUs, or the cluster at ``address``
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
        refs = [task.remote(_absolute(sub), scenes, episodes, fp) for _, sub, fp, _ in todo]
        for (_, sub, _, _), ref in zip(todo, refs, strict=True):
            try:
                yield ray.get(ref)
            except Exception as e:  # noqa: BLE001 - the task raised or its worker died
                yield _failed(sub, e)
    finally:
        if started:
            ray.shutdown()


def _evaluate_all(todo: list, scenes: list[str], episodes: int | None, jobs: int, launcher: str,
                  address: str | None):
    """Yield ``(dir, submission, results path, (results, seconds) | SubmissionError)`` in ``todo`` order."""
    if launcher not in LAUNCHERS:
        raise ValueError(f"unknown launcher {launcher!r}; valid: {', '.join(LAUNCHERS)}")
    outs = _ray(todo, scenes, episodes, jobs, address) if launcher == "ray" and todo else \
        _local(todo, scenes, episodes, jobs)
    for (d, sub, _, res_path), out in zip(todo, outs, strict=True):
        yield d, sub, res_path, out


# ---------------------------------------------------------------------------------- run
def run(root: Path = DEFAULT_ROOT, only: list[str] | None = None, check: bool = False, force: bool = False,
        episodes: int | None = None, scenes: list[str] | None = None, log=None, jobs: int = 1,
        launcher: str = "local", address: str | None = None, readme: Path | None = None,
        docs: list[Path] | None = None) -> int:
    """Validate, evaluate and render; returns the exit code (0 ok, 1 a submission failed or --check differs).

    ``readme``: a file whose block between the ``generated:results`` markers is regenerated too;
    ``docs``: files whose generated blocks (``render.BLOCKS``, e.g. ``generated:docs-results`` of
    docs/results.md) are regenerated too (None: no other file is touched)."""
    root = Path(root)
    log = log or (lambda msg: print(msg, flush=True))
    scenes = list(scenes or EVAL_SCENES)
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
    targets: list[tuple[Path, str]] = []  # (file, its text) whose generated blocks are rendered
    for path, names in ([(readme, ["results"])] if readme is not None else []) + \
            [(d, [n for n in render.BLOCKS if n != "results"]) for d in docs or []]:
        path = Path(path)
        text = path.read_text() if path.is_file() else ""
        if not set(render.blocks_in(text)) & set(names):
            start, end = render.markers(names[0])
            log(f"crowdbench leaderboard: error: {path} has no {start} ... {end} block")
            return 1
        targets.append((path, text))
    results, rejected, missing, todo = [], [], [], []
    t_all = time.time()

    def reject(e: SubmissionError) -> None:
        log(f"crowdbench leaderboard: error: {e}")
        rejected.append(str(e).replace(str(root.resolve()) + "/", "").replace(str(root) + "/", ""))

    for d in dirs:
        res_path = root / "results" / d.name / "results.json"
        selected = only is None or d.name in only
        try:
            sub = read_submission(d)
            if sub.kind == "learned":
                register_encoder(sub)
            fp = fingerprint(sub, scenes, episodes)
            cached = json.loads(res_path.read_text()) if res_path.is_file() else None
            fresh = cached is not None and cached.get("harness", {}).get("fingerprint") == fp
            if not check and (fresh and not force or not selected):
                if fresh:
                    results.append(cached)
                    if selected:
                        log(f"{d.name}: unchanged, cached results ({res_path.relative_to(root)}); --force re-evaluates")
                else:
                    missing.append(f"{d.name}: results missing or out of date (`crowdbench leaderboard --only {d.name}`)")
                continue
            todo.append((d, sub, fp, res_path))
        except SubmissionError as e:
            reject(e)
    outcomes = _evaluate_all(todo, scenes, episodes, jobs, launcher, address)
    while True:
        try:
            d, sub, res_path, outcome = next(outcomes)
        except StopIteration:
            break
        except LauncherError as e:
            log(f"crowdbench leaderboard: error: {e}")
            return 1
        if isinstance(outcome, SubmissionError):
            reject(outcome)
            continue
        res, seconds = outcome
        log(f"{d.name}: evaluated in {seconds:.1f} s; average success (paper scenes) "
            f"{render.fmt(res.get('average_paper_scenes', {}).get('success_rate'), 3)}")
        results.append(res)
        if not check:
            res_path.parent.mkdir(parents=True, exist_ok=True)
            res_path.write_text(json.dumps(res, indent=1) + "\n")
            if sub.kind == "oracle":
                (res_path.parent / "unavoidable.json").write_text(json.dumps(
                    {"privileged": True, "note": "episodes the privileged oracle fails: candidate unavoidable",
                     "protocol": PROTOCOL_VERSION, "scenes": res["unavoidable"]}, indent=1) + "\n")
    rejected.sort()
    failed = bool(rejected)
    table = render.render_readme(results, rejected, scenes, episodes, missing)
    log(f"leaderboard: {len(results)} evaluated/cached, {len(rejected)} rejected, {time.time() - t_all:.1f} s")
    if check:
        committed = (root / "README.md").read_text() if (root / "README.md").is_file() else ""
        diffs = []
        if committed != table:
            diffs += render.diff_rows(committed, table) or ["(whitespace or layout)"]
        for path, text in targets:
            for name in render.blocks_in(text):
                old, new = render.read_block(text, name), render.BLOCKS[name](results, scenes, episodes)
                if old != new:
                    where = f"{path}" if name == "results" else f"{path} ({name})"
                    diffs += [f"{where}: {m}" for m in render.diff_rows(old, new) or ["(whitespace or layout)"]]
        if diffs:
            log("crowdbench leaderboard --check: FAILED: the generated text differs from a fresh evaluation in "
                f"{len(diffs)} row(s):\n  " + "\n  ".join(diffs))
            return 1
        log("crowdbench leaderboard --check: README.md matches a fresh evaluation"
            + (f" (and the generated blocks of {', '.join(str(p) for p, _ in targets)})" if targets else ""))
        return 1 if failed else 0
    (root / "README.md").write_text(table)
    if results:
        render.plot(results, scenes, root / "leaderboard.png")
    wrote = [str(root / "README.md"), str(root / "leaderboard.png")]
    for path, text in targets:
        new = render.regenerate(text, results, scenes, episodes)
        if new != text:
            path.write_text(new)
        wrote.append(f"the results block of {path}" if render.blocks_in(text) == ["results"] else
                     f"the generated blocks of {path}")
    log(f"wrote {', '.join(wrote)}")
    return 1 if failed else 0
