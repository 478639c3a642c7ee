"""The evaluation half of the ``crowdbench`` command line: policies, output directories, the
per-protocol evaluation runs (replay v1, self-play, CrowdNav) and the training probe."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

from crowdbench import policies
from crowdbench.envs.core import SimConfig


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
    from crowdbench.data.scenes import check_scene
    from crowdbench.envs.core import check_seed
    from crowdbench.envs.protocol import EVAL_SCENES

    try:
        check_seed(cfg.seed)
    except ValueError as e:
        raise UsageError(str(e)) from None
    scenes = list(cfg.eval.scenes) if not isinstance(cfg.eval.scenes, str) else [cfg.eval.scenes]
    if not scenes:
        raise UsageError(f"eval.scenes is empty; evaluation scenes: {', '.join(EVAL_SCENES)}")
    try:
        scenes = [check_scene(s) for s in scenes]
    except ValueError as e:
        raise UsageError(str(e)) from None
    unlisted = [s for s in scenes if s not in EVAL_SCENES]
    if unlisted:
        raise UsageError(f"eval.scenes: {', '.join(unlisted)} has no protocol episode list (the training scene); "
                         f"evaluation scenes: {', '.join(EVAL_SCENES)}")
    episodes = cfg.eval.episodes
    if episodes is not None and (not isinstance(episodes, int) or episodes < 1):
        raise UsageError(f"eval.episodes must be a positive integer or null, got {episodes!r}")
    return scenes, episodes


def protocol_humans(cfg, strict: bool = True) -> str | None:
    """The reactive model protocol v2 evaluates with (``env.humans=reactive_replay``), or None for v1.

    Training may use any ``env.reactive`` values; evaluation uses the protocol's, so ``crowdbench eval``
    (``strict``) refuses different ones rather than silently replace them, while a training run's probe
    and final evaluation (not strict) use the protocol's values for its model."""
    from crowdbench.envs.factory import replay_humans
    from crowdbench.envs.protocol import reactive_params, v2_humans

    for key, value in dict(cfg.env.get("reactive") or {}).items():  # before the dataclass sees them
        if key != "model" and (isinstance(value, bool) or not isinstance(value, int | float)):
            raise UsageError(f"env.reactive.{key} must be a number, got {value!r}")
    try:
        params = replay_humans(cfg.env)
    except (ValueError, TypeError) as e:
        raise UsageError(str(e)) from None
    if params is None or not strict:
        return None if params is None else params.model
    fixed = reactive_params({"humans": v2_humans()}, params.model)[0]
    for key, value in fixed.to_dict().items():
        if getattr(params, key) != value:
            raise UsageError(f"env.reactive.{key}={getattr(params, key)} conflicts with protocol v2 ({value}); "
                             "evaluation always uses the protocol's value")
    return params.model


def run_eval(policy, cfg, out: Path, overrides: list[str], strict: bool = True) -> dict:
    from crowdbench.eval import evaluate, format_table
    from crowdbench.fixed_lists import check_replay

    scenes, episodes = eval_options(cfg)
    sim = SimConfig.fields_of(cfg.env)
    try:
        SimConfig(**sim)  # bad env values (the frame too, replaced by the policy's) are one-line errors
    except ValueError as e:
        raise UsageError(str(e)) from None
    sim["frame"] = policy.frame
    recorders = recorder_factory(policy, cfg, out, scenes)
    humans = protocol_humans(cfg, strict)
    try:
        check_replay("v2" if humans else "v1", scenes)  # the published lists, not look-alikes
        with progress_bar(policy.name, scenes, SimConfig(**sim).time_limit, recorders) as recorders_and_bar:
            results = evaluate(policy, scenes, episodes, out_dir=out, save_episodes=bool(cfg.eval.save_episodes),
                               sim_overrides=sim, meta={"seed": cfg.seed, "overrides": overrides},
                               recorder_factory=recorders_and_bar, humans=humans)
    except ValueError as e:  # e.g. the oracle on protocol v2, a list that is not the published one
        raise UsageError(str(e)) from None
    except OSError as e:
        raise write_error(e, out) from None
    print(format_table(results))
    print(f"results written to {out / 'results.json'}")
    return results


class StepTicker:
    """A recorder for :func:`crowdbench.eval.drive` that advances a progress bar by one per time step and
    passes every call on to the scene's viz recorder, if any. It reads nothing and changes nothing, so the
    evaluation (and crowdbench/eval.py, hashed into the leaderboard's cache) is untouched."""

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
    :func:`crowdbench.eval.evaluate` takes (wrapping ``inner_factory``, the viz recordings)."""
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


def check_protocol_fixed(cfg) -> None:
    """The protocol fixes dt, time limit, time base and start radius; refuse an override of them."""
    from crowdbench.envs.protocol import ProtocolSpec

    spec, env = ProtocolSpec(), SimConfig.fields_of(cfg.env)
    for key in ("dt", "time_limit", "time_base", "start_radius"):
        if str(env[key]) != str(getattr(spec, key)):
            raise UsageError(f"env.{key}={env[key]} conflicts with protocol {spec.version} ({getattr(spec, key)}); "
                             "evaluation always uses the protocol's value")


def check_selfplay_eval(cfg, frame: str = "rotate") -> None:
    """Every ``env.eval_scenarios`` x ``env.eval_n_agents`` setting can be placed: checked before training, so
    that e.g. 32 agents on the default 8 m square fail at once, not after a 30-minute run."""
    from crowdbench.envs.factory import selfplay_config
    from crowdbench.eval_selfplay import settings

    e = cfg.env
    try:
        settings(selfplay_config(e, frame=frame), list(e.eval_scenarios),
                 None if e.eval_n_agents is None else list(e.eval_n_agents))
    except ValueError as err:
        raise UsageError(f"env.eval_n_agents / env.eval_scenarios: {err}") from None


def run_selfplay_eval(policy, cfg, out: Path, overrides: list[str]) -> dict:
    """``env=selfplay``: every agent acts from ``policy`` on the seeded self-play set (docs/selfplay.md)."""
    from crowdbench.envs.factory import selfplay_config
    from crowdbench.eval_selfplay import evaluate_selfplay, format_table

    e = cfg.env
    try:
        sim = selfplay_config(e, frame=policy.frame)
        results = evaluate_selfplay(policy, sim, list(e.eval_scenarios),
                                    None if e.eval_n_agents is None else list(e.eval_n_agents), int(e.eval_episodes),
                                    int(e.eval_seed), out_dir=out, meta={"seed": cfg.seed, "overrides": overrides})
    except ValueError as err:
        raise UsageError(str(err)) from None
    except OSError as err:
        raise write_error(err, out) from None
    print(format_table(results))
    print(f"results written to {out / 'results.json'}")
    return results


def run_crowdnav_eval(policy, cfg, out: Path, overrides: list[str]) -> dict:
    """``env=crowdnav``: CrowdNav's test cases of every ``env.eval_settings`` (docs/crowdnav.md)."""
    from crowdbench.envs.factory import sim_config
    from crowdbench.eval import format_table
    from crowdbench.eval_crowdnav import evaluate_crowdnav
    from crowdbench.fixed_lists import check_crowdnav, crowdnav_digests

    e = cfg.env
    try:
        c = sim_config(e)
        check_crowdnav(crowdnav_digests(c, list(e.eval_settings or [f"{c.scenario}_n{c.n_humans}"])))
        results = evaluate_crowdnav(policy, c, None if e.eval_settings is None else list(e.eval_settings),
                                    e.eval_episodes, out_dir=out, save_episodes=bool(cfg.eval.save_episodes),
                                    meta={"seed": cfg.seed, "overrides": overrides})
    except ValueError as err:
        raise UsageError(str(err)) from None
    except OSError as err:
        raise write_error(err, out) from None
    print(format_table(results))
    print(f"results written to {out / 'results.json'}")
    return results


def make_probe(cfg):
    """Held-out check during training: success on ``probe_episodes`` of ``probe_scene``'s protocol list."""
    from crowdbench.algos.checkpoint import LearnedPolicy
    from crowdbench.data.scenes import check_scene
    from crowdbench.envs.factory import env_name
    from crowdbench.eval import evaluate

    if env_name(cfg.env) == "crowdnav":  # CrowdNav's validation cases (its own held-out set)
        from crowdbench.envs.factory import sim_config
        from crowdbench.eval_crowdnav import evaluate_crowdnav

        sim = sim_config(cfg.env)
        setting = f"{sim.scenario}_n{sim.n_humans}"

        def probe_crowdnav(actor) -> dict[str, float]:
            res = evaluate_crowdnav(LearnedPolicy(actor, frame=cfg.env.frame), sim, [setting],
                                    cfg.train.probe_episodes, phase="val")["scenes"][setting]
            return {f"probe_crowdnav_{setting}_success": res["success_rate"]["mean"],
                    f"probe_crowdnav_{setting}_collision": res["collision_rate"]["mean"]}

        return probe_crowdnav
    scene = check_scene(cfg.train.probe_scene)
    humans = protocol_humans(cfg, strict=False) if env_name(cfg.env) == "replay" else None

    def probe(actor) -> dict[str, float]:
        res = evaluate(LearnedPolicy(actor, frame=cfg.env.frame), [scene], cfg.train.probe_episodes,
                       sim_overrides=SimConfig.fields_of(cfg.env), humans=humans)["scenes"][scene]
        return {f"probe_{scene}_success": res["success_rate"]["mean"],
                f"probe_{scene}_collision": res["collision_rate"]["mean"]}

    return probe
