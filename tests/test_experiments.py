"""Named experiments and methods compose, and reproduce the training configs of the shipped rows."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from crowdbench.algos.checkpoint import load_checkpoint
from crowdbench.cli import CONFIG_DIR, compose, main

ROOT = Path(__file__).resolve().parents[1]
SUBMISSIONS = ROOT / "leaderboard" / "submissions"
EXPERIMENTS = sorted(p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml"))
LEARNED = sorted(d.name for d in SUBMISSIONS.iterdir()
                 if yaml.safe_load((d / "submission.yaml").read_text())["kind"] == "learned")
TRAINING = ("algo", "encoder", "env", "train")  # what decides the trained weights (with the seed)


def training_config(cfg: dict) -> dict:
    out = {g: dict(cfg[g]) for g in TRAINING}
    out["train"].pop("max_minutes", None)  # a wall-time cap, not a training setting
    out["train"].pop("budget_warm_start", None)  # what the cap counts
    out["train"].pop("save_buffer", None)  # what a checkpoint holds, not how the run trains
    out["env"].pop("orca_backend", None)  # which ORCA solver computes the crowd (the same numbers), not what
    if out["algo"].get("thin") == 0.0:  # algo=value's default, absent from checkpoints made before the option
        out["algo"].pop("thin")
    if out["train"].get("human_thinning") == 0.0:  # the default, absent from checkpoints made before the option
        out["train"].pop("human_thinning")
    if out["train"].get("playback_speeds") in ([1.0], None):  # as recorded: absent from checkpoints made before the option
        out["train"].pop("playback_speeds", None)
    for key in ("curriculum_agents", "curriculum_frames"):  # no curriculum: absent from checkpoints made before it
        if out["train"].get(key) == []:
            out["train"].pop(key)
    if out["env"].get("reward", "paper") == "paper":  # the default of replay and self-play, absent from their
        out["env"].pop("reward", None)  # checkpoints made before their YAMLs named it (with the discomfort factor,
        out["env"].pop("discomfort_factor", None)  # which the paper's reward does not read)
    if out["env"].get("sfm_backend") == "torch":  # the default, absent from checkpoints made before the option
        out["env"].pop("sfm_backend")  # (numba's social force is not torch's bit for bit: kept when set)
    if out["encoder"].get("robot_radius2", 0) is None:  # the default, absent from checkpoints made before the option
        out["encoder"].pop("robot_radius2")
    if out["encoder"].get("edge_dist") is False:  # the default, absent from checkpoints made before the option
        out["encoder"].pop("edge_dist")
    if out["algo"].get("actor_base", "none") == "none":  # no base: its residual's size trains nothing (and the
        out["algo"].pop("actor_base", None)  # on-policy algorithms' checkpoints before the option lack both)
        out["algo"].pop("actor_residual", None)
    if cfg["algo"].get("actor_base") == "orca" or cfg["train"].get("pretrain") == "orca":
        out["orca"] = dict(cfg["orca"])  # the residual's base and the demonstrator: their ORCA trains the weights too
    return {**out, "seed": cfg["seed"]}


def sweep_points(name: str) -> list[list[str]]:
    """Every run of the experiment's ``hydra.sweeper.params`` as override lists (Hydra's basic sweeper
    takes the cartesian product of the comma-separated values)."""
    params = (yaml.safe_load((CONFIG_DIR / "experiment" / f"{name}.yaml").read_text()).get("hydra") or {}) \
        .get("sweeper", {}).get("params", {})
    axes = [[f"{k}={v}" for v in str(vals).split(",")] for k, vals in params.items()]
    return [[f"experiment={name}", *point] for point in itertools.product(*axes)]


def test_the_three_named_experiments_exist():
    assert {"paper", "leaderboard", "leaderboard_long"} <= set(EXPERIMENTS)


# value_crowdnav's 36 runs compose for ~7 s: the full suite only
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "value_crowdnav" else n
                                  for n in EXPERIMENTS])
def test_every_run_of_every_experiment_composes(name):
    points = sweep_points(name)
    seen = set()
    for overrides in points:
        cfg = compose(overrides)
        assert cfg.submission.experiment == name
        if len(points) > 1:  # a sweep's runs become distinct submissions with row labels
            assert cfg.submission.entry, overrides
            seen.add(cfg.submission.name)
    assert len(seen) == (len(points) if len(points) > 1 else 0)


@pytest.mark.slow
def test_leaderboard_sweeps_train_every_row():
    assert len(sweep_points("leaderboard")) == 15  # 5 encoders x 3 seeds
    assert len(sweep_points("leaderboard_scratch")) == 15  # 5 methods x 3 seeds
    assert len(sweep_points("leaderboard_long")) == 9  # 3 encoders x 3 seeds
    names = {compose(p).submission.name for p in sweep_points("leaderboard")}
    assert {"gatedgcn_td3_residual_sigma045_s0", "gcn_td3_residual_sigma045_s1", "mlp_td3_residual_sigma045_s2",
            "rgl_td3_residual_sigma045_s0", "sarl_td3_residual_sigma045_s2"} <= names
    scratch = {compose(p).submission.name for p in sweep_points("leaderboard_scratch")}
    assert {"gatedgcn_td3_s0", "gatedgcn_sac_s2", "gatedgcn_ddpg_s1", "gcn_td3_s0", "mlp_td3_s2"} <= scratch
    long = {compose(p).submission.name for p in sweep_points("leaderboard_long")}
    assert {"gatedgcn_td3_uniform_5x_s0", "gcn_td3_uniform_5x_s1", "mlp_td3_uniform_5x_s2"} <= long


def test_paper_experiment_is_table_one():
    cfg = compose(["experiment=paper"])
    assert (cfg.encoder.name, cfg.encoder.dim, cfg.encoder.layers) == ("gatedgcn", 256, 2)
    assert (cfg.algo.name, cfg.algo.replay, cfg.algo.exploration_sigma, cfg.algo.critic_lookahead) == \
        ("td3", "prioritized", 0.1, 0.0)
    assert (cfg.algo.batch_size, cfg.algo.buffer_size, cfg.algo.warmup, cfg.algo.gamma, cfg.algo.lr_actor) == \
        (100, 100000, 2000, 0.99, 1e-3)
    assert (cfg.train.total_frames, cfg.train.utd, cfg.train.progress_reward) == (1_000_000, 1.0, 0.0)
    assert compose(["experiment=paper", "encoder=mlp"]).encoder.dim == 256


def test_encoder_names_mean_the_cpu_width():
    for name in ("gatedgcn", "gcn", "mlp"):
        assert compose([f"encoder={name}"]).encoder.dim == 32
    assert compose(["encoder=gatedgcn", "encoder.dim=256"]).encoder.dim == 256


def test_the_card_command_is_the_shipped_residual_recipe():
    """``crowdbench run algo=td3 encoder=gatedgcn`` trains exactly the config of the shipped
    gatedgcn_td3_residual_sigma045_s* rows (a seed reproduces its run bit for bit): ORCA's demonstrations, then
    28,672 frames of TD3 (uniform replay, exploration sigma 0.45) with an actor that adds a residual of at most
    0.15 m/s to ORCA's velocity and the cloning term kept at weight 1; with ``algo.exploration_sigma=0.3`` it is
    the previous default, the gatedgcn_td3_residual_s* rows; ``train=scratch algo.replay=uniform
    algo.actor_base=none`` is RL from scratch, the gatedgcn_td3_uniform_5x_s0 row."""
    card = OmegaConf.to_container(compose(["algo=td3", "encoder=gatedgcn"]), resolve=True)
    t, a = card["train"], card["algo"]
    assert (t["pretrain"], t["pretrain_frames"], t["pretrain_bc_weight"], t["pretrain_bc_updates"]) == ("orca", 20000, 1.0, 0)
    assert (t["total_frames"], a["replay"], card["encoder"]["name"], card["encoder"]["dim"]) == (28672, "uniform", "gatedgcn", 32)
    assert (a["actor_base"], a["actor_residual"], a["exploration_sigma"]) == ("orca", 0.15, 0.45)
    for seed in (0, 1, 2):
        for row, extra in ((f"gatedgcn_td3_residual_sigma045_s{seed}", []),
                           (f"gatedgcn_td3_residual_s{seed}", ["algo.exploration_sigma=0.3"])):
            shipped = load_checkpoint(SUBMISSIONS / row / "checkpoint.pt")["config"]
            composed = compose(["algo=td3", "encoder=gatedgcn", *extra, f"seed={seed}"])
            assert training_config(OmegaConf.to_container(composed, resolve=True)) == training_config(shipped), row
    assert training_config(OmegaConf.to_container(compose([]), resolve=True)) == training_config(card)
    # experiment=leaderboard is the card's recipe for every encoder: only the encoder (and the row's name) differ
    for method, encoder in (("gatedgcn_td3", "gatedgcn"), ("gcn_td3", "gcn"), ("mlp_td3", "mlp"), ("rgl_td3", "rgl"),
                            ("sarl_td3", "sarl")):
        row = OmegaConf.to_container(compose(["experiment=leaderboard", f"method={method}"]), resolve=True)
        alone = OmegaConf.to_container(compose(["algo=td3", f"encoder={encoder}"]), resolve=True)
        assert training_config(row) == training_config(alone), method
    scratch = load_checkpoint(SUBMISSIONS / "gatedgcn_td3_uniform_5x_s0" / "checkpoint.pt")["config"]
    composed = compose(["algo=td3", "encoder=gatedgcn", "train=scratch", "algo.actor_base=none", "algo.exploration_sigma=0.3"])
    assert training_config(OmegaConf.to_container(composed, resolve=True)) == training_config(scratch)
    # the previous default, a plain actor with the cloning term over 10,000 updates: the warm-start rows
    warm = load_checkpoint(SUBMISSIONS / "gatedgcn_td3_warmstart_s0" / "checkpoint.pt")["config"]
    composed = compose(["algo=td3", "encoder=gatedgcn", "algo.actor_base=none", "train.pretrain_bc_updates=10000",
                        "algo.exploration_sigma=0.3"])
    assert training_config(OmegaConf.to_container(composed, resolve=True)) == training_config(warm)


@pytest.mark.parametrize("name", LEARNED)
def test_shipped_rows_name_their_experiment_and_overrides_reproduce_the_checkpoint(name):
    sub = yaml.safe_load((SUBMISSIONS / name / "submission.yaml").read_text())
    assert sub["experiment"] in EXPERIMENTS
    assert f"experiment={sub['experiment']}" in sub["overrides"]
    shipped = load_checkpoint(SUBMISSIONS / name / "checkpoint.pt")["config"]
    composed = OmegaConf.to_container(compose(sub["overrides"]), resolve=True)
    assert training_config(composed) == training_config(shipped)


def test_a_wrong_experiment_is_a_one_line_error(capsys):
    assert main(["eval", "experiment=nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "experiment" in err and "leaderboard_long" in err and "paper" in err


def test_plus_syntax_is_accepted():
    assert compose(["+experiment=leaderboard_scratch", "+method=gcn_td3"]).submission.name == "gcn_td3_s0"


def test_the_default_recipe_says_what_to_expect_at_its_start(monkeypatch, capsys, tmp_path):
    from crowdbench.algos import train as train_module
    from crowdbench.cli_run import EXPECTATION, is_default_recipe

    assert is_default_recipe([]) and is_default_recipe(["algo=td3", "encoder=gatedgcn", "seed=2", "cpus=2", "out=x"])
    assert not is_default_recipe(["encoder=gcn"]) and not is_default_recipe(["train.total_frames=256"])
    assert not is_default_recipe(["train=scratch"]) and not is_default_recipe(["train.max_minutes=3"])

    def stop(*a, **kw):
        raise ValueError("stopped before training")

    monkeypatch.setattr(train_module, "train", stop)
    for args, shown in ((["seed=1"], True), (["train.total_frames=256"], False)):
        assert main(["run", *args, "eval.episodes=1", "eval.scenes=[hotel]", f"out={tmp_path / str(shown)}"]) == 2
        out, err = capsys.readouterr()
        assert (EXPECTATION in out) == shown and "stopped before training" in err
