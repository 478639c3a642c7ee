"""``crowdbench run -m ...``: sweeps through Hydra's multirun, its sweeper and its launchers.

Hydra expands the overrides (``encoder=gatedgcn,gcn seed=0,1,2``, or an experiment's
``hydra.sweeper.params``) into runs and hands them to the launcher: ``basic`` (sequential, the default),
``joblib`` (local processes) or ``ray`` (hydra-ray-launcher: a local Ray cluster, or an existing one with
``hydra.launcher.ray.init.address``). Each run is :func:`task` in its own directory
``<sweep dir>/<job number>/``; a run that fails is recorded there (``status.json``) instead of raising, so
the other runs go on, and :class:`SweepSummary` (a Hydra callback, in the launching process) writes
``<sweep dir>/sweep.json`` and prints the table once every run has ended.
"""

from __future__ import annotations

import json
import math
import os
import shlex
import sys
import time
import traceback
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

STATUS = "status.json"
SUMMARY = "sweep.json"


def _local_only(address, value):
    """``${crowdbench_local_only:ADDRESS,VALUE}`` (conf/hydra/launcher/ray.yaml): ``VALUE`` when Ray starts a
    local cluster, null when it joins one (``ADDRESS`` or ``RAY_ADDRESS`` set): ``ray.init`` rejects
    local-cluster settings such as ``object_store_memory`` when connecting to an existing cluster."""
    return None if address or os.environ.get("RAY_ADDRESS") else value


# registered at import: the launching process imports this module before Hydra composes the launcher
if not OmegaConf.has_resolver("crowdbench_local_only"):
    OmegaConf.register_new_resolver("crowdbench_local_only", _local_only)


def task(cfg: DictConfig) -> dict:
    """One run of a sweep: train and evaluate into Hydra's job directory; never raises, so that one
    failed run (bad value, crash, ``SystemExit``) does not stop the sweep."""
    from hydra.core.hydra_config import HydraConfig

    from crowdbench.app import UsageError
    from crowdbench.cli_run import run_one
    from crowdbench.sweep_check import finished

    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    kept = finished(out)
    if kept is not None:  # a run of this sweep that finished before it was interrupted (crowdbench/sweep_check.py)
        print(f"crowdbench: run {kept['job']} finished before: kept ({out})", file=sys.stderr)
        return kept
    # resume=true continues the sweep: not part of what a run is (its row in the summary, its submission)
    overrides = [o for o in hc.overrides.task if not o.startswith("resume=")]
    status = {"job": int(hc.job.num), "overrides": overrides, "dir": str(out)}
    start = time.time()
    try:
        OmegaConf.set_struct(cfg, True)
        cfg.out = str(out)
        cfg.resume = bool(cfg.resume) and (out / "checkpoint.pt").exists()  # else this job starts afresh
        results = run_one(cfg, overrides)
        status |= {"status": "ok", **headline(results)}
    except (Exception, SystemExit) as e:  # noqa: BLE001 - any failure is this run's, reported by name
        message = str(e) if isinstance(e, UsageError | ValueError) else f"{type(e).__name__}: {e}"
        status |= {"status": "failed", "error": " ".join(message.split()) or type(e).__name__}
        (out / "error.txt").write_text(traceback.format_exc())
        print(f"crowdbench: run {status['job']} ({' '.join(overrides)}) failed: {status['error']}", file=sys.stderr)
    status["wall_time_s"] = round(time.time() - start, 1)
    (out / STATUS).write_text(json.dumps(status, indent=1) + "\n")
    return status


def headline(results: dict) -> dict:
    """The figures a sweep table shows: average success and dangers over the evaluated paper scenes
    (all evaluated scenes if none is a paper scene), and the success per scene."""
    avg = results.get("average_paper_scenes") or {}
    scenes = results.get("scenes", {})
    per_scene = {s: r["success_rate"]["mean"] for s, r in scenes.items() if "success_rate" in r}
    success = avg.get("success_rate")
    if success is None and per_scene:
        success = sum(per_scene.values()) / len(per_scene)
    return {"success": success, "dangers": avg.get("dangers_per_episode"), "scene_success": per_scene}


def _mean_sd(values: list[float]) -> tuple[float, float]:
    m = sum(values) / len(values)
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0
    return m, sd


def summarise(sweep_dir: Path) -> dict:
    """Collect every run's ``status.json`` (a run with none never finished: it is reported as failed)
    and group the runs that differ only in ``seed``: mean ± sd across seeds of the final evaluation."""
    runs = []
    for d in sorted((p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)):
        if (d / STATUS).is_file():
            runs.append(json.loads((d / STATUS).read_text()))
        else:
            over = OmegaConf.load(d / ".hydra" / "overrides.yaml") if (d / ".hydra" / "overrides.yaml").is_file() else []
            runs.append({"job": int(d.name), "overrides": list(over), "dir": str(d), "status": "failed",
                         "error": "the run ended without a status (killed?)"})
    common = set.intersection(*(set(r["overrides"]) for r in runs)) if runs else set()
    groups: dict[str, list[dict]] = {}
    for r in runs:  # a group is named by what it sets that not every run of the sweep sets
        key = " ".join(o for o in r["overrides"] if o not in common and not o.startswith("seed=")) or "(all runs)"
        groups.setdefault(key, []).append(r)
    table = []
    for key, members in groups.items():
        ok = [r for r in members if r["status"] == "ok" and r.get("success") is not None]
        row = {"config": key, "runs": len(members), "finished": len(ok),
               "seeds": [next((o[5:] for o in r["overrides"] if o.startswith("seed=")), None) for r in ok]}
        if ok:
            row["success_mean"], row["success_sd"] = _mean_sd([r["success"] for r in ok])
            dangers = [r["dangers"] for r in ok if r.get("dangers") is not None]
            if dangers:
                row["dangers_mean"], row["dangers_sd"] = _mean_sd(dangers)
        table.append(row)
    failed = [{"job": r["job"], "overrides": r["overrides"], "error": r.get("error", "")}
              for r in runs if r["status"] != "ok"]
    return {"sweep_dir": str(sweep_dir), "common_overrides": sorted(common), "runs": runs, "table": table,
            "failed": failed}


def format_summary(summary: dict) -> str:
    lines = [f"sweep {summary['sweep_dir']}; every run: {' '.join(summary['common_overrides']) or '(defaults)'}",
             "| config | runs | success (mean ± sd over seeds) | dangers / episode |", "|---|---|---|---|"]
    for row in summary["table"]:
        succ = f"{row['success_mean']:.3f} ± {row['success_sd']:.3f}" if "success_mean" in row else "-"
        dang = f"{row['dangers_mean']:.3f} ± {row['dangers_sd']:.3f}" if "dangers_mean" in row else "-"
        lines.append(f"| {row['config']} | {row['finished']}/{row['runs']} | {succ} | {dang} |")
    for f in summary["failed"]:
        lines.append(f"FAILED run {f['job']} ({' '.join(f['overrides'])}): {f['error']}")
    return "\n".join(lines)


class SweepSummary(Callback):
    """Hydra callback (``hydra.callbacks.summary`` in conf/config.yaml): the sweep's table at its end."""

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not sweep_dir.is_dir():
            return
        summary = summarise(sweep_dir)
        (sweep_dir / SUMMARY).write_text(json.dumps(summary, indent=1) + "\n")
        print(format_summary(summary))
        print(f"sweep summary written to {sweep_dir / SUMMARY}")


def multirun(overrides: list[str]) -> int:
    """Run Hydra's multirun over ``overrides``; exit code 1 if any run failed (named in the table).

    ``out=DIR`` names the sweep directory (Hydra's ``hydra.sweep.dir``); default
    ``outputs/sweep-<time>``."""
    import hydra

    from crowdbench.app import Interrupted, UsageError
    from crowdbench.compose import CONFIG_DIR, normalise
    from crowdbench.sweep_check import check_sweep

    overrides = normalise(overrides)
    sweep_dir = next((o.split("=", 1)[1] for o in overrides if o.startswith("hydra.sweep.dir=")), None)
    outs = [o for o in overrides if o.startswith("out=")]
    if outs:
        sweep_dir = outs[-1].split("=", 1)[1]
    if sweep_dir is None:
        sweep_dir = f"outputs/sweep-{time.strftime('%Y%m%d-%H%M%S')}"
    # absolute: a run on a Ray node resolves a relative directory against its worker's directory
    sweep_dir = str(Path(sweep_dir).absolute())
    given = [o for o in overrides if not o.startswith(("out=", "hydra.sweep.dir="))]
    quoted = sweep_dir.replace("\\", "\\\\").replace("'", "\\'")  # Hydra's override grammar: any path
    overrides = [*given, f"hydra.sweep.dir='{quoted}'"]
    resume = any(o.split("=", 1)[0] == "resume" and o.split("=", 1)[1].lower() == "true" for o in given)
    if (Path(sweep_dir) / SUMMARY).exists() and not resume:
        raise UsageError(f"{sweep_dir} already holds a finished sweep ({SUMMARY}); choose another out=, or pass "
                         "resume=true to rerun its failed runs (finished runs are kept)")
    check_sweep(overrides, Path(sweep_dir), resume)  # before Hydra writes anything (crowdbench/sweep_check.py)
    app = hydra.main(config_path=str(CONFIG_DIR), config_name="config", version_base="1.3")(task)
    argv, sys.argv = sys.argv, ["crowdbench run", "--multirun", *overrides]
    try:
        app()
    except SystemExit as e:  # Hydra exits on a bad override (composition), after printing the error
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    except KeyboardInterrupt:  # the runs finished so far are kept: say how to continue the whole sweep
        again = shlex.join(["crowdbench", "run", "-m", *[o for o in given if not o.startswith("resume=")],
                            f"out={sweep_dir}", "resume=true"])
        raise Interrupted(f"sweep interrupted; finished runs are kept; continue it with: {again}") from None
    finally:
        sys.argv = argv
    summary_file = Path(sweep_dir) / SUMMARY
    if not summary_file.is_file():
        return 1
    summary = json.loads(summary_file.read_text())
    return 1 if summary["failed"] or not summary["runs"] else 0
