"""Config schemas (crowdbench/config_schema.py) and their validation (crowdbench/config_check.py): every
shipped config validates, bad values give one-line errors naming the key before anything runs."""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from omegaconf import OmegaConf

from crowdbench.algos.ppo import PPOConfig
from crowdbench.cli import CONFIG_DIR, compose, main
from crowdbench.config_check import ConfigError, short, unknown_keys, validate, validate_checkpoint
from crowdbench.config_schema import ALGO_SCHEMAS, ENCODER_SCHEMAS, ENV_SCHEMAS, RootConfig

ROOT = Path(__file__).resolve().parents[1]
OPTIONS = {g: sorted(p.stem for p in (CONFIG_DIR / g).glob("*.yaml"))
           for g in ("experiment", "method", "env", "algo", "encoder", "train")}


def composed_combinations(part: str):
    """The compositions of one part of the shipped configs. ``exp:NAME``: every method with experiment
    NAME (``-``: none) on the experiment's own env, then NAME on each env without a method.
    ``env:NAME``: every method, encoder and train on env NAME. ``algo:NAME``: NAME with every encoder x
    train on the default env, then NAME on each env. Together: every experiment x method pair, and every
    pair of any two of the six groups; each rule below involves two groups, and the full product
    (about 1,400 compositions at 0.14 s each) is 2.2 times as many."""
    kind, name = part.split(":")
    if kind == "exp":
        exp = [f"experiment={name}"] * (name != "-")
        yield from (exp + [f"method={m}"] * bool(m) for m in [None, *OPTIONS["method"]])
        yield from (exp + [f"env={env}"] for env in OPTIONS["env"])
    elif kind == "env":
        yield from ([f"{group}={o}", f"env={name}"] for group in ("method", "encoder", "train") for o in OPTIONS[group])
    else:
        yield from ([f"algo={name}", f"encoder={enc}", f"train={train}"]
                    for enc, train in itertools.product(OPTIONS["encoder"], OPTIONS["train"]))
        yield from ([f"algo={name}", f"env={env}"] for env in OPTIONS["env"])


PARTS = [f"{kind}:{o}" for kind, group in (("exp", "experiment"), ("env", "env"), ("algo", "algo"))
         for o in ["-"] * (kind == "exp") + OPTIONS[group]]


RADIUS_ENCODERS = ('gat', 'gatedgcn', 'gcn')  # the encoders with an edge radius (encoder.radius2)
# they set algo.replay or algo.actor_base
OFF_POLICY_EXPERIMENTS = ("paper", "leaderboard_scratch", "baselines", "crowdnav", "crowdnav_distill", "reactive", "warmstart",
                          "leaderboard_long", "selfplay_warmstart", "selfplay_residual")
ACTOR_CRITIC_EXPERIMENTS = (*OFF_POLICY_EXPERIMENTS, "selfplay_ppo_residual")  # their algo keys are no value keys
SELFPLAY_EXPERIMENTS = ("selfplay", "selfplay_warmstart", "selfplay_residual", "selfplay_ppo_residual")


def _experiment_algo_keys(name: str) -> set[str]:
    """The ``algo`` keys an experiment's yaml sets (its own, not its defaults')."""
    return set((yaml.safe_load((CONFIG_DIR / "experiment" / f"{name}.yaml").read_text()) or {}).get("algo") or {})


PPO_KEYS = {f.name for f in fields(PPOConfig)}


def _algo_of(method: str) -> str:
    """The algorithm a method's yaml selects (its ``override /algo`` default)."""
    defaults = yaml.safe_load((CONFIG_DIR / "method" / f"{method}.yaml").read_text())["defaults"]
    return next(d["override /algo"] for d in defaults if isinstance(d, dict) and "override /algo" in d)


ON_POLICY_METHODS = tuple(m for m in OPTIONS["method"] if _algo_of(m) in ("ppo", "ippo", "mappo"))


@pytest.mark.slow  # 24 parts of 19-34 compositions each, spread over the xdist workers
@pytest.mark.parametrize("part", PARTS)
def test_every_shipped_config_combination_validates_and_every_key_has_a_schema_field(part):
    seen = 0
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        for overrides in composed_combinations(part):
            cfg = hydra_compose(config_name="config", overrides=overrides)
            seen += 1
            env = cfg.env.name
            exp = next((o.split("=", 1)[1] for o in overrides if o.startswith("experiment=")), None)
            if any(f"method={m}" in overrides for m in ON_POLICY_METHODS) and exp in OFF_POLICY_EXPERIMENTS \
                    and not _experiment_algo_keys(exp) <= PPO_KEYS:
                # an off-policy recipe's replay settings are no PPO-family keys (its ORCA base is one)
                with pytest.raises(ConfigError,
                                   match=r"^algo\.(replay|exploration_sigma|actor_base): algo='(ppo|ippo|mappo)' has no such key"):
                    validate(cfg)
                continue
            value_method = any(o.startswith("method=") and o.endswith("_value") for o in overrides)
            value_exp = any(f"experiment={e}" in overrides for e in ("value_crowdnav", "value_replay"))
            other_exp = exp in ACTOR_CRITIC_EXPERIMENTS
            if value_method and other_exp or value_exp and not value_method and any(
                    o.startswith("method=") for o in overrides):
                # an actor-critic recipe's keys are no value keys, and the value recipe's none of theirs
                with pytest.raises(ConfigError, match=r"^algo\.\w+: algo='\w+' has no such key"):
                    validate(cfg)
                continue
            if exp in SELFPLAY_EXPERIMENTS and env != "selfplay":
                # a self-play recipe's env keys (mixed crossings, agent counts) are env=selfplay's alone
                try:
                    validate(cfg)
                except ConfigError as e:
                    assert str(e).startswith("env."), (overrides, e)
                else:
                    assert unknown_keys(cfg) and all(k.startswith("env.") for k in unknown_keys(cfg)), overrides
                continue
            if "experiment=reactive" in overrides and env != "replay":
                with pytest.raises(ConfigError, match="^env.humans: must be one of orca, sfm"):
                    validate(cfg)  # reactive replay is the replay env's (env.humans=reactive_replay)
                continue
            if "method=gatedgcn_sac" in overrides and cfg.algo.get("actor_base") == "orca":
                # an ORCA base under SAC: its loss scores the action the env received, not a residual
                with pytest.raises(ConfigError, match="^algo.actor_base: must be one of none"):
                    validate(cfg)
                continue
            if "experiment=paper" in overrides and "method=gatedgcn_sac" in overrides:
                # Table I's Gaussian exploration is TD3's; SAC explores by sampling its policy
                with pytest.raises(ConfigError, match="^algo.exploration_sigma: algo='sac' has no such key"):
                    validate(cfg)
                continue
            validate(cfg)
            if "experiment=crowdnav_distill" in overrides and cfg.encoder.name not in RADIUS_ENCODERS:
                # its edge radius is the graph encoders' (gatedgcn, gcn, gat): another encoder has no such key
                assert unknown_keys(cfg) == ["encoder.radius2"], overrides
                continue
            assert unknown_keys(cfg) == [], overrides
    n = {g: len(v) for g, v in OPTIONS.items()}
    expected = {"exp": n["method"] + 1 + n["env"], "env": n["method"] + n["encoder"] + n["train"],
                "algo": n["encoder"] * n["train"] + n["env"]}
    assert seen == expected[part.split(":")[0]]
    assert n["method"] >= 8 and n["encoder"] >= 6
    assert {"gatedgcn_ppo", "gatedgcn_ippo", "gatedgcn_mappo"} <= set(ON_POLICY_METHODS)


@pytest.mark.parametrize("group, schemas", [("env", ENV_SCHEMAS), ("algo", ALGO_SCHEMAS), ("encoder", ENCODER_SCHEMAS)])
def test_each_option_has_its_schema_with_the_yamls_keys_and_defaults(group, schemas):
    assert sorted(schemas) == OPTIONS[group]
    for name, cls in schemas.items():
        shipped = yaml.safe_load((CONFIG_DIR / group / f"{name}.yaml").read_text())
        shipped = shipped.get(group, shipped)  # env/crowdnav.yaml is a _global_ package
        assert OmegaConf.to_container(OmegaConf.structured(cls)) == shipped, (group, name)


def test_schemas_are_in_hydras_config_store():
    from hydra.core.config_store import ConfigStore

    repo = ConfigStore.instance().repo["schema"]
    assert {"root.yaml", "env", "algo", "encoder", "train"} <= set(repo)
    assert set(repo["algo"]) == {"td3.yaml", "ddpg.yaml", "sac.yaml", "ppo.yaml", "matd3.yaml", "ippo.yaml", "mappo.yaml", "value.yaml"}
    node = ConfigStore.instance().load("schema/algo/sac.yaml").node
    assert OmegaConf.get_type(node).__name__ == "SACConfig" and node.alpha_init == 0.005
    root = OmegaConf.to_container(OmegaConf.structured(RootConfig))
    assert root["seed"] == 0 and root["orca"]["pref_rule"] == "reach"


@pytest.fixture
def no_work(monkeypatch, tmp_path):
    """Run in an empty directory where training or an evaluation starting fails the test."""
    import crowdbench.algos.train

    def started(*args, **kwargs):
        raise AssertionError("work started before the config was refused")

    monkeypatch.setattr(crowdbench.algos.train, "train", started)
    import crowdbench.cli_run

    monkeypatch.setattr(crowdbench.cli_run, "run_protocol", started)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return work


def refused(args, capsys) -> str:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("crowdbench: error: ") and err.count("\n") == 1, err
    return err


# the reliability findings (18, 20): each command, its key and the message
FINDINGS = [
    (["eval", "seed=abc"], "seed: must be an integer in [0, 2**63) (got 'abc')"),
    (["eval", "orca.safety_margin=abc"], "orca.safety_margin: must be a number >= 0 (got 'abc')"),
    (["run", "encoder.dim=0"], "encoder.dim: must be >= 1 (got 0)"),
    (["run", "train.frames_per_batch=0"], "train.frames_per_batch: must be >= 1 (got 0)"),
    (["run", "env.batch=0"], "env.batch: must be in [1, 65536] (got 0)"),
    (["run", "algo.lr_actor=abc"], "algo.lr_actor: must be a number > 0 (got 'abc')"),
    (["eval", "eval.scenes=[students001]"], "eval.scenes: students001 has no protocol episode list"),
    (["run", "algo.gamma=2"], "algo.gamma: must be in (0, 1] (got 2)"),
    (["eval", "eval.scenes=[]"], "eval.scenes: must not be empty (got [])"),
    (["eval", "env.frame=polar"], "env.frame: must be one of rotate, translate, world (got 'polar')"),
    (["run", "train.total_frames=-5"], "train.total_frames: must be >= 1 (got -5)"),
    (["run", "seed=abc"], "seed: must be an integer in [0, 2**63) (got 'abc')"),
    (["run", "algo=sac", "algo.alpha_init=0"], "algo.alpha_init: must be > 0 (got 0)"),
    (["run", "train.human_dropout=1.5"], "train.human_dropout: must be in [0, 1] (got 1.5)"),
    (["run", "algo.tau=nan"], "algo.tau: must be a finite number (got nan)"),
    (["run", "encoder=mlp", "encoder.hidden=[64,0]"], "encoder.hidden: each item must be >= 1 (got [64, 0])"),
    (["eval", "env=crowdnav", "env.n_humans=many"], "env.n_humans: must be an integer >= 1 (got 'many')"),
    (["eval", "env=selfplay", "env.eval_n_agents=[4,0]"], "env.eval_n_agents: each item must be >= 1"),
    (["eval", "oracle.speeds=[1.0,1.5]"], "oracle.speeds: each item must be in (0, 1] (got [1.0, 1.5])"),
    (["run", "seed=" + "9" * 200], "seed: must be in [0, 2**63) (got 99999"),
]


@pytest.mark.parametrize("args, message", FINDINGS)
def test_bad_values_are_refused_in_one_line_before_anything_is_written(args, message, no_work, capsys):
    err = refused(args, capsys)
    assert message in err and len(err) < 300, err
    assert list(no_work.iterdir()) == []  # no outputs/ directory, nothing else


def test_plot_smooth_must_be_positive(tmp_path, capsys):
    err = refused(["plot", str(tmp_path), "--smooth", "-5"], capsys)
    assert "--smooth: must be an integer >= 1 (got -5)" in err


@pytest.mark.slow
def test_a_sweep_validates_each_run(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}  # this tree's crowdbench
    p = subprocess.run([sys.executable, "-m", "crowdbench.cli", "run", "-m", "algo.gamma=2,3", "out=sweep"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert p.returncode == 1, p.stderr[-2000:]
    errors = [r["error"] for r in yaml.safe_load((tmp_path / "sweep" / "sweep.json").read_text())["failed"]]
    assert errors == ["algo.gamma: must be in (0, 1] (got 2)", "algo.gamma: must be in (0, 1] (got 3)"]
    assert not any((tmp_path / "sweep" / str(job) / "logs").exists() for job in (0, 1))  # nothing trained


def test_a_bad_value_in_a_yaml_is_caught(tmp_path, monkeypatch, capsys):
    conf = tmp_path / "conf"
    shutil.copytree(CONFIG_DIR, conf)
    td3 = (conf / "algo" / "td3.yaml").read_text()
    (conf / "algo" / "td3.yaml").write_text(td3.replace("batch_size: 100", "batch_size: many"))
    (conf / "experiment" / "broken.yaml").write_text("# @package _global_\nenv:\n  v_max: 0.0\n")
    import crowdbench.compose

    monkeypatch.setattr(crowdbench.compose, "CONFIG_DIR", conf)
    with pytest.raises(ConfigError, match=r"^algo\.batch_size: must be an integer >= 1 \(got 'many'\)$"):
        validate(compose([]))
    with pytest.raises(ConfigError, match=r"^env\.v_max: must be > 0 \(got 0\.0\)$"):
        validate(compose(["algo=ddpg", "experiment=broken"]))
    monkeypatch.chdir(tmp_path)
    assert "algo.batch_size" in refused(["run", "out=run"], capsys) and not (tmp_path / "run").exists()


def test_keys_added_with_plus_are_accepted_as_hydra_accepts_them():
    cfg = compose(["+env.note=calibration", "+tags=[a,b]"])
    validate(cfg)
    assert unknown_keys(cfg) == ["env.note", "tags"]


def test_a_long_value_is_truncated_in_the_message():
    nested = [[list(range(1000))] * 1000] * 1000  # 10**9 leaves if it were expanded
    assert len(short(nested)) <= 60 and len(short("x" * 10**6)) <= 60


# --------------------------------------------------------------------------------------------- checkpoints
@pytest.fixture
def checkpoints(tmp_path):
    """A valid tiny checkpoint and the findings' bad ones (in ``ck/``, outside the working directory)."""
    from crowdbench.algos.actors import build_actor
    from crowdbench.algos.checkpoint import save_checkpoint

    cfg = OmegaConf.to_container(compose(["encoder=mlp", "encoder.dim=8", "encoder.hidden=[8]"]), resolve=True)
    actor = build_actor("td3", cfg["encoder"], 1.0, squash="radial").state_dict()
    base = {"config": cfg, "actor": actor, "frames": 0, "updates": 0}
    d = tmp_path / "ck"
    d.mkdir()

    def write(name, edit=None, weights=None):
        state = {**base, "config": OmegaConf.to_container(OmegaConf.create(cfg)), "actor": weights or actor}
        if edit:
            edit(state["config"])
        save_checkpoint(d / f"{name}.pt", state)
        return str(d / f"{name}.pt")

    return {"good": write("good"),
            "no_frame": write("no_frame", lambda c: c["env"].pop("frame")),
            "polar": write("polar", lambda c: c["env"].update(frame="polar")),
            "fast": write("fast", lambda c: c["env"].update(v_max="fast")),
            "gamma": write("gamma", lambda c: c["algo"].update(gamma=2.0)),
            "nan": write("nan", weights={k: torch.full_like(v, float("nan")) for k, v in actor.items()})}


@pytest.mark.parametrize("name, message", [
    ("no_frame", "env.frame: missing from its config"),
    ("polar", "env.frame: must be one of rotate, translate, world (got 'polar')"),
    ("fast", "env.v_max: must be a number > 0 (got 'fast')"),
    ("gamma", "algo.gamma: must be in (0, 1] (got 2.0)"),
    ("nan", "must be finite (got 1968 of 1968 values NaN or inf)"),  # (1 + 40) x 6 inputs x 8
])
def test_bad_checkpoints_are_refused_in_one_line(name, message, checkpoints, no_work, capsys):
    err = refused(["eval", f"policy={checkpoints[name]}"], capsys)
    assert f"checkpoint {checkpoints[name]}: " in err and message in err, err
    if name == "nan":
        assert "actor.module.encoder.net.0.weight" in err  # the tensor
    assert list(no_work.iterdir()) == []


def test_a_valid_checkpoint_validates(checkpoints):
    assert validate_checkpoint(checkpoints["good"])["config"]["encoder"]["dim"] == 8


def test_the_env_schemas_are_the_runtime_settings_classes():
    """One declaration per setting: each env schema subclasses the class the simulator runs with and adds only
    keys that are not simulator settings; env.reactive's schema is ReactiveParams, orca's the baseline's."""
    from crowdbench.baselines.params import OrcaSettings
    from crowdbench.config_schema import OrcaConfig
    from crowdbench.envs.crowdnav import CrowdNavConfig
    from crowdbench.envs.humans.reactive_replay import ReactiveParams
    from crowdbench.envs.rules import SimConfig
    from crowdbench.envs.selfplay import SelfPlayConfig

    runtime = {"replay": SimConfig, "selfplay": SelfPlayConfig, "crowdnav": CrowdNavConfig}
    for name, schema in ENV_SCHEMAS.items():
        assert issubclass(schema, runtime[name]), name
        own = {f.name for f in fields(schema)} - {f.name for f in fields(runtime[name])}
        assert all(k in ("name", "batch", "scene", "humans", "reactive") or k.startswith("eval_") for k in own), own
        for f in fields(runtime[name]):  # not re-declared: the same default and bounds
            g = next(g for g in fields(schema) if g.name == f.name)
            assert (g.default, g.metadata) == (f.default, f.metadata), (name, f.name)
    assert {f.name: f.type for f in fields(ENV_SCHEMAS["replay"])}["reactive"] in (ReactiveParams, "ReactiveParams")
    assert OrcaConfig is OrcaSettings


@pytest.mark.parametrize("args, cls, kwargs", [
    (["env.v_max=-1"], "crowdbench.envs.rules:SimConfig", {"v_max": -1}),
    (["env.frame=polar"], "crowdbench.envs.rules:SimConfig", {"frame": "polar"}),
    (["env=selfplay", "env.n_agents=0"], "crowdbench.envs.selfplay:SelfPlayConfig", {"n_agents": 0}),
    (["env=crowdnav", "env.orca_backend=fortran"], "crowdbench.envs.crowdnav:CrowdNavConfig", {"orca_backend": "fortran"}),
    (["env.humans=reactive_replay", "env.reactive.responsibility=2"],
     "crowdbench.envs.humans.reactive_replay:ReactiveParams", {"responsibility": 2}),
    (["orca.max_neighbors=-1"], "crowdbench.baselines.orca:ORCA", {"max_neighbors": -1}),
])
def test_a_bad_value_is_refused_in_the_same_words_from_python_and_the_command_line(args, cls, kwargs, capsys, tmp_path):
    import importlib

    module, name = cls.split(":")
    with pytest.raises(ValueError) as python:
        getattr(importlib.import_module(module), name)(**kwargs)
    assert main(["eval", "policy=straight", *args, f"out={tmp_path}"]) == 2
    assert capsys.readouterr().err.strip() == f"crowdbench: error: {python.value}"
