"""A sweep checked before Hydra launches it (or writes anything into its directory).

Hydra composes each job only when the job starts, and writes ``multirun.yaml`` and each job's ``.hydra/``
first: a bad value would print its multi-line report after files were written, and a rerun into an
interrupted sweep's directory would overwrite its runs' records. So the jobs are expanded here as
Hydra's basic sweeper expands them (``hydra.sweeper.params`` of the composed config first, then the
command line's overrides; job ``i`` runs in ``<sweep dir>/<i>/``) and checked:

- every combination of config-group choices composes (the one-line error ``crowdbench run`` gives);
- ``hydra.sweep.subdir`` is Hydra's default, the job number (the summary and ``crowdbench submit`` read
  the runs there; another value can even point outside the sweep);
- a job directory that exists holds the same job: finished, it is kept; unfinished, it is continued
  with ``resume=true`` and refused without.
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

JOB_SUBDIR = "${hydra.job.num}"


def sweep_jobs(overrides: list[str]) -> tuple[list[list[str]], dict]:
    """``(jobs, hydra config)``: each job's task overrides in job-number order, as Hydra will run them."""
    from hydra import compose, initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    from crowdbench.app import UsageError
    from crowdbench.compose import CONFIG_DIR, hydra_message

    parser = OverridesParser.create()
    try:
        parsed = parser.parse_overrides(overrides)
        plain = [o.input_line for o in parsed if not o.is_sweep_override()]  # what Hydra composes the sweep with
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
            cfg = compose(config_name="config", overrides=plain, return_hydra_config=True)
        hydra = OmegaConf.to_container(cfg.hydra, resolve=False)
        params = [f"{k}={v}" for k, v in (hydra["sweeper"].get("params") or {}).items()]
        task = [o.input_line for o in parsed if not o.is_hydra_override()]
        (jobs,) = BasicSweeper.split_arguments(parser.parse_overrides(params + task), None)
    except HydraException as e:
        raise UsageError(hydra_message(e, overrides)) from None
    return [list(j) for j in jobs], hydra


def check_sweep(overrides: list[str], sweep_dir: Path, resume: bool) -> int:
    """Refuse (``UsageError``) a sweep that Hydra would fail part-way or that would overwrite runs in
    ``sweep_dir``; return the number of jobs."""
    from crowdbench.app import UsageError

    jobs, hydra = sweep_jobs(overrides)
    if str(hydra["sweep"].get("subdir")) != JOB_SUBDIR:
        raise UsageError(f"hydra.sweep.subdir is fixed to the job number ({sweep_dir}/<job>/: the sweep's summary "
                         f"and crowdbench submit read the runs there); remove hydra.sweep.subdir={hydra['sweep']['subdir']}")
    check_compositions(jobs)
    check_job_dirs(sweep_dir, jobs, resume)
    return len(jobs)


def check_compositions(jobs: list[list[str]]) -> None:
    """Compose one job per combination of config-group choices (``experiment=a,b``, ``method=...``):
    a missing option or an unknown key is the one-line error of ``crowdbench run``, before any run."""
    from crowdbench.compose import CONFIG_DIR, compose

    def is_group(o: str) -> bool:
        key = o.split("=", 1)[0].lstrip("+~")
        return (CONFIG_DIR / key).is_dir() or (Path("configs") / key).is_dir()

    seen = set()
    for job in jobs:
        groups = tuple(o for o in job if is_group(o))
        if groups not in seen:
            seen.add(groups)
            compose(job)


def _plain(overrides) -> list[str]:
    return [o for o in overrides if not o.startswith("resume=")]


def saved_overrides(job_dir: Path) -> list[str] | None:
    """The overrides a job directory's run was started with (its status, else Hydra's record)."""
    status = job_dir / "status.json"
    try:
        if status.is_file():
            return list(json.loads(status.read_text())["overrides"])
        if (job_dir / ".hydra" / "overrides.yaml").is_file():
            return list(OmegaConf.load(job_dir / ".hydra" / "overrides.yaml"))
    except (ValueError, KeyError, TypeError):
        pass
    return None


def finished(job_dir: Path) -> dict | None:
    """The status of a run that ended ``ok`` with its results, else None."""
    try:
        status = json.loads((job_dir / "status.json").read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(status, dict) and status.get("status") == "ok"
    return status if ok and (job_dir / "results.json").is_file() else None


def check_job_dirs(sweep_dir: Path, jobs: list[list[str]], resume: bool) -> None:
    from crowdbench.app import UsageError

    if not sweep_dir.is_dir():
        return
    extra = sorted(int(d.name) for d in sweep_dir.iterdir() if d.is_dir() and d.name.isdigit() and int(d.name) >= len(jobs))
    if extra:
        raise UsageError(f"{sweep_dir} holds runs {extra[0]}.. beyond this sweep's {len(jobs)} jobs: it is another "
                         "sweep's directory; choose another out=")
    for i, job in enumerate(jobs):
        d = sweep_dir / str(i)
        if not d.exists():
            continue
        old = saved_overrides(d)
        if old is None or _plain(old) != _plain(job):
            raise UsageError(f"{d} holds a run of other overrides ({' '.join(old or ['unknown'])}), not "
                             f"{' '.join(_plain(job))}: it is another sweep's directory; choose another out=")
        if not resume and finished(d) is None:
            raise UsageError(f"{d} holds an unfinished run of this sweep; pass resume=true to continue the sweep "
                             "(finished runs are kept), or choose another out=")
