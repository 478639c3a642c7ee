"""The application layer the commands share (``crowdbench eval`` / ``run`` / ``submit``, sweeps, the API):
usage errors, the checked config, its policy and protocol, output directories, an evaluation run and the
training probe of the config's protocol (crowdbench/protocols/: nothing here asks which)."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

from crowdbench import policies


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit code 2."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C stopped a run at a checkpoint: printed as one line (how to resume), exit code 130. A
    KeyboardInterrupt, so that a sweep stops too instead of recording one failed run and going on."""


def check_config(cfg) -> None:
    """The composed config against its schemas (crowdbench/config_schema.py: types and bounds)."""
    from crowdbench.config_check import validate

    try:
        validate(cfg)
    except ValueError as e:
        raise UsageError(str(e)) from None


def make_policy(name: str, cfg):
    """``policy=NAME``: the registry builds it (crowdbench/policies.py) with this config's env and seed;
    a checkpoint's config (schemas) and weights (finite) are checked first."""
    try:
        if name not in policies.NAMES and Path(name).is_file():
            from crowdbench.config_check import validate_checkpoint

            validate_checkpoint(name)  # ConfigError, CheckpointError: ValueErrors
        return policies.build(name, cfg)
    except (policies.PolicyError, ValueError) as e:
        raise UsageError(str(e)) from None


def output_dir(cfg, command: str, name: str) -> Path:
    if cfg.out:
        return Path(cfg.out)
    base = Path("outputs") / f"{command}-{Path(name).stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    out, n = base, 1
    while out.exists():  # two runs started within one second get their own directories
        n += 1
        out = base.with_name(f"{base.name}-{n}")
    return out


@contextlib.contextmanager
def claimed_output(out: Path):
    """Hold ``out`` (created if needed, locked against a concurrent run or evaluation) for the block;
    an unwritable ``out`` or one in use is a one-line error before any work (crowdbench/outputs.py)."""
    from crowdbench.outputs import OutputError, claim_dir

    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(claim_dir(out))
        except OutputError as e:
            raise UsageError(str(e)) from None
        yield out


@contextlib.contextmanager
def eval_output(cfg, command: str):
    """``crowdbench eval``'s output directory, claimed; its ``results.json`` is never silently replaced."""
    out = output_dir(cfg, command, str(cfg.policy))
    with claimed_output(out):
        results = out / "results.json"
        if results.exists() and not cfg.eval.overwrite:
            raise UsageError(f"{results} already exists (an earlier evaluation or run); choose another out= "
                             "or pass eval.overwrite=true to replace it")
        yield out


def write_error(e: OSError, out: Path) -> UsageError:
    return UsageError(f"cannot write {e.filename or out}: {e.strerror or e}")


def eval_options(cfg) -> tuple[list[str], int | None]:
    """``eval.scenes`` and ``eval.episodes``, checked (every scene with a published list)."""
    from crowdbench.protocols.replay import scenes_of

    try:
        return scenes_of(cfg)
    except ValueError as e:
        raise UsageError(str(e)) from None


def protocol_of(cfg):
    """The protocol of ``cfg.env`` (crowdbench/protocols/ ``of_config``); an unknown one is a one-line error."""
    from crowdbench.protocols import of_config

    try:
        return of_config(cfg.env)
    except (ValueError, TypeError) as e:
        raise UsageError(str(e)) from None


def run_protocol(policy, cfg, out: Path, overrides: list[str], strict: bool = True) -> dict:
    """Evaluate ``policy`` on ``cfg``'s protocol into ``out``, print its table. ``strict=False`` (the end of a
    training run): a reactive replay run trained with other ``env.reactive`` values is evaluated on
    protocol v2's, as its probe was."""
    protocol = protocol_of(cfg)

    def progress(scenes: list[str], steps: int):
        return progress_bar(policy.name, scenes, steps, recorder_factory(policy, cfg, out, scenes))

    try:
        results = protocol.run(policy, cfg, out, overrides, strict, progress)
    except ValueError as e:  # e.g. the oracle on protocol v2, a list that is not the published one
        raise UsageError(str(e)) from None
    except OSError as e:
        raise write_error(e, out) from None
    print(protocol.format_table(results))
    print(f"results written to {out / 'results.json'}")
    return results


class StepTicker:
    """A recorder for :func:`crowdbench.protocols.engine.drive` that advances a progress bar by one per time
    step and passes every call on to the scene's viz recorder, if any. It reads nothing and changes nothing, so
    the evaluation (and crowdbench/protocols/, hashed into the leaderboard's cache) is untouched."""

    def __init__(self, bar, end: int, inner=None):
        self.bar, self.end, self.inner = bar, end, inner

    def __call__(self, world, obs, action) -> None:
        self.bar.update(1)
        if self.inner is not None:
            self.inner(world, obs, action)

    def after_step(self, world, info) -> None:
        if self.inner is not None and hasattr(self.inner, "after_step"):
            self.inner.after_step(world, info)

    def close(self) -> None:
        self.bar.update(self.end - self.bar.n)  # the scene's episodes may all end before the time limit
        if self.inner is not None and hasattr(self.inner, "close"):
            self.inner.close()


@contextlib.contextmanager
def progress_bar(name: str, scenes: list[str], steps: int, inner_factory=None):
    """A progress bar on stderr over ``scenes`` x ``steps`` time steps; yields the recorder factory
    :func:`crowdbench.protocols.replay.evaluate` takes (wrapping ``inner_factory``, the viz recordings)."""
    from tqdm import tqdm

    bar = tqdm(total=len(scenes) * steps, unit="step", desc=f"eval {name}", dynamic_ncols=True)
    done = {"scenes": 0}

    def factory(scene: str):
        bar.set_postfix_str(scene)
        done["scenes"] += 1
        return StepTicker(bar, done["scenes"] * steps, inner_factory(scene) if inner_factory else None)

    try:
        yield factory
    finally:
        bar.close()


def recorder_factory(policy, cfg, out: Path, scenes: list[str]):
    """``viz.record=true``: rerun recordings of ``viz.episodes`` (crowdbench/viz/record.py); else ``None``
    (the viz package, and rerun, are then never imported)."""
    if not cfg.viz.record:
        return None
    from crowdbench.viz.record import make_recorder_factory

    try:
        return make_recorder_factory(policy, cfg, out, scenes)
    except ValueError as e:
        raise UsageError(str(e)) from None


def check_viz(cfg) -> None:
    """Reject bad ``viz.*`` values before anything runs (a training run must not fail at its end)."""
    if cfg.viz.record:
        from crowdbench.viz.record import recorded_episodes

        try:
            recorded_episodes(cfg, eval_options(cfg)[0])
        except ValueError as e:
            raise UsageError(str(e)) from None


def check_protocol(cfg, policy_name: str | None = None):
    """The protocol of ``cfg`` after its checks (``crowdbench eval`` with ``policy_name``; ``crowdbench run``
    without, before training): bad input is a one-line error before any work."""
    protocol = protocol_of(cfg)
    try:
        if policy_name is None:
            protocol.check_run(cfg)
        else:
            protocol.check(cfg, policy_name)
    except ValueError as e:
        raise UsageError(str(e)) from None
    return protocol


def make_probe(cfg):
    """Held-out check during training: the protocol's probe (``probe(actor) -> {name: value}``)."""
    return protocol_of(cfg).probe(cfg)
