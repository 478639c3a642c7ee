"""algo=value on the replay protocol: the candidates read only the humans the robot senses, the validation
list is the training scene's, and a tiny run trains, evaluates on protocol v1 and evaluates again."""

from __future__ import annotations

import json

import pytest
import torch
from worlds import replay_sim, reset_v1

from crowdbench.compose import compose
from crowdbench.data.scenes import load_scene
from crowdbench.envs.lookahead import action_set, candidates, lookahead_observation
from crowdbench.envs.rules import SimConfig
from crowdbench.envs.scenarios import VAL_EPISODES, ReplayScenario, replay_scene


def students_world(sensing: float):
    scene = load_scene("students001")
    world = replay_sim(scene, 3, SimConfig(dt=scene.dt, frame="rotate", sensing_range=sensing))
    reset_v1(world, torch.ones(3, dtype=torch.bool), torch.tensor([100, 300, 500]), torch.tensor([0.0, 2.0, 4.0]))
    for _ in range(3):
        world.step(torch.full((3, 1, 2), 0.5))
    return world


@pytest.mark.parametrize("model", ["cv", "query"])
def test_candidate_humans_are_the_ones_the_robot_senses(model):
    """V(s') reads the humans present now and next and within the sensing range now (a loop per human);
    the candidate reward is the world's, whatever the range (a human farther away cannot be reached in a step)."""
    world = students_world(5.0)
    c = candidates(world, action_set(1.0), model)
    pos, _, valid = world.humans()
    nxt_valid = valid if model == "cv" else world.crowd.scene.valid[world.crowd.t + 1]
    far = 0
    for b in range(world.B):
        for j in range(world.Mh):
            d = float((pos[b, j] - world.pos[b, 0]).norm())
            expect = bool(valid[b, j]) and bool(nxt_valid[b, j]) and d <= 5.0
            far += bool(valid[b, j]) and d > 5.0
            assert bool(c["humans_valid"][b, j]) == expect, (b, j)
    assert far > 0 and c["humans_valid"].any()  # students001 has humans on both sides of 5 m: not vacuous
    wide = candidates(students_world(100.0), action_set(1.0), model)
    assert torch.equal(wide["reward"], c["reward"]) and torch.equal(wide["done"], c["done"])
    o = lookahead_observation(world, action_set(1.0), model)
    assert torch.equal(o["cand_humans_mask"][:, 0], c["humans_valid"])
    assert not o["cand_humans"][:, 0][~c["humans_valid"]].any()  # unseen humans are zero in the observation


def test_the_validation_list_is_the_training_scenes_and_fixed():
    cfg = SimConfig()
    scen = ReplayScenario(replay_scene("students001", cfg), cfg)
    val, again = scen.test_list("val"), scen.test_list("val")
    assert len(val["t0"]) == VAL_EPISODES and all(torch.equal(val[k], again[k]) for k in val)
    assert scen.start_is_free(val["t0"], val["angle"]).all()
    for seed in range(3):  # not the first draws of a training run's stream
        assert not torch.equal(scen.sampler(seed)(VAL_EPISODES)["t0"], val["t0"])
    with pytest.raises(ValueError, match="only the 'val' list"):
        scen.test_list("test")


def test_the_value_replay_experiment_composes_to_its_recipe():
    cfg = compose(["experiment=value_replay"])
    assert (cfg.env.name, cfg.env.scene, cfg.env.humans) == ("replay", "students001", "replay")
    assert (cfg.algo.name, cfg.algo.net, cfg.encoder.name, cfg.algo.lookahead) == ("value", "encoder", "gatedgcn", "cv")
    assert (cfg.algo.il_episodes, cfg.algo.max_minutes, cfg.algo.keep_best, cfg.algo.thin, cfg.cpus) == (960, 7, True, 0.8, 1)
    assert cfg.submission.name == "gatedgcn_value_cv_replay_s0"
    assert cfg.submission.entry == "MP-GatedGCN (value, cv lookahead, replay)"


def test_a_value_run_on_replay_trains_evaluates_v1_and_the_checkpoint_again(tmp_path, monkeypatch):
    import crowdbench.envs.scenarios
    from crowdbench.cli import main

    monkeypatch.setattr(crowdbench.envs.scenarios, "VAL_EPISODES", 4)  # the validation rounds, not their length

    tiny = ["env=replay", "method=sarl_value", "algo.lookahead=cv", "algo.batch=4", "algo.il_episodes=4",
            "algo.il_steps=3", "algo.episodes=4", "algo.train_batches=1", "algo.batch_size=8", "algo.val_every=4",
            "algo.keep_best=true", "eval.scenes=[hotel]", "eval.episodes=3"]
    assert main(["run", *tiny, f"out={tmp_path / 'run'}"]) == 0
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    assert res["lookahead"] == "cv" and not res.get("privileged") and list(res["scenes"]) == ["hotel"]
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    assert log[1]["episodes"] == 0 and "val_success" in log[1]  # the imitation network, validated on students001
    assert main(["eval", "eval.scenes=[hotel]", "eval.episodes=3", f"policy={tmp_path / 'run' / 'checkpoint.pt'}",
                 f"out={tmp_path / 'eval'}"]) == 0
    again = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert again["scenes"] == res["scenes"]


def test_value_refuses_self_play_in_one_line(tmp_path, capsys):
    from crowdbench.cli import main

    assert main(["run", "env=selfplay", "algo=value", "algo.il_episodes=0", "algo.episodes=0",
                 f"out={tmp_path / 'run'}"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert "env=crowdnav or env=replay" in err[-1] and "env=selfplay" in err[-1]


def test_query_is_refused_where_the_recorded_humans_yield():
    from crowdbench.envs.factory import replay_world
    from crowdbench.envs.humans.reactive_replay import ReactiveParams
    from crowdbench.envs.lookahead import next_humans

    cfg = SimConfig()
    world, scen = replay_world("zara1", 2, cfg, reactive=ReactiveParams())
    world.reset(torch.ones(2, dtype=torch.bool), scen.sampler(0)(2))
    with pytest.raises(ValueError, match="invisible robot"):
        next_humans(world, "query")
    assert next_humans(world, "cv")[2].shape == (2, world.Mh)


def test_thinning_removes_humans_from_the_world_for_the_episode():
    """``algo.thin``: a removed human is neither seen nor hit for the whole episode; validation rounds see all."""
    from types import SimpleNamespace

    from crowdbench.algos.value_train import run_round, thin_draw

    scene = load_scene("students001")
    world = replay_sim(scene, 4, SimConfig(dt=scene.dt, frame="rotate"))
    keep = thin_draw(world, 1.0, torch.Generator().manual_seed(0))
    assert keep.shape == (4, world.Mh) and not keep.all() and keep.any()
    assert thin_draw(world, 0.0, torch.Generator()) is None
    model = SimpleNamespace(state=lambda obs: (obs["humans"][:, 0], obs["humans_mask"][:, 0]))
    eps = world.scenario.sampler(0)(4)
    seen = []
    act = lambda obs, running: seen.append(obs["humans_mask"][:, 0].clone()) or torch.zeros(4, 1, 2)
    run_round(model, world, eps, act, keep)
    assert all(not (s & ~keep).any() for s in seen)  # never seen ...
    assert not (world.humans()[2] & ~keep).any()  # ... nor present (the world's collision test reads these)
    seen.clear()
    run_round(model, world, eps, act)
    assert world.crowd.keep is None and any((s & ~keep).any() for s in seen)


@pytest.mark.parametrize("name", ["cadrl", "sarl", "lm_sarl", "gatedgcn", "rgl", "gcn", "gat", "dsrnn"])
def test_dropping_absent_slots_leaves_the_values(name):
    """The networks cut the slots no row holds (``compact``); a batch with one full row is not cut: the other
    rows' values agree with and without the cut (absent humans, rows without any human included)."""
    from omegaconf import OmegaConf

    from crowdbench.models.value_nets import JOINT_DIM, build_value_net, compact

    torch.manual_seed(0)
    net_name, enc = (name, None) if name in ("cadrl", "sarl", "lm_sarl") else ("encoder", None)
    if net_name == "encoder":
        enc = OmegaConf.to_container(compose([f"encoder={name}"]).encoder, resolve=True)
    net = build_value_net(net_name, enc).eval()
    N, M = 32, 24
    D = JOINT_DIM + (48 if name == "lm_sarl" else 0)
    x, mask = torch.randn(N, M, D), torch.rand(N, M) < 0.25
    mask[:4] = False  # rows that sense nobody
    x[:, :, :6] = x[:, :1, :6]  # the self-state is every slot's
    cut_x, cut_m = compact(x, mask)
    assert cut_m.shape[1] == int(mask.sum(-1).max()) < M and torch.equal(cut_m.sum(-1), mask.sum(-1))
    for i in range(N):  # each row's sensed humans first, in their order
        k = int(mask[i].sum())
        assert torch.equal(cut_x[i, :k], x[i, mask[i]]) and cut_m[i, :k].all() and not cut_m[i, k:].any()
    with torch.no_grad():
        got = net(x, mask)
        full = net(torch.cat((x, x[:1])), torch.cat((mask, torch.ones(1, M, dtype=torch.bool))))[:N]
    assert torch.allclose(got, full, atol=1e-6, rtol=0), float((got - full).abs().max())


def test_candidates_valued_in_chunks_equal_one_pass():
    """Where slots go unsensed the candidates are valued CHUNK environments at a time, densest last; the values
    are those of one pass over the batch (to float rounding) and the greedy choices the same."""
    from omegaconf import OmegaConf

    from crowdbench.algos.value import CHUNK, ValueModel

    cfg = compose(["experiment=value_replay", "env.scene=students003"])
    torch.manual_seed(0)
    model = ValueModel(cfg.algo, cfg.env, OmegaConf.to_container(cfg.encoder, resolve=True))
    scene = load_scene("students003")
    B = 2 * CHUNK + 5
    world = replay_sim(scene, B, SimConfig(dt=scene.dt, frame="rotate"))
    world.reset(torch.ones(B, dtype=torch.bool), world.scenario.sampler(3)(B))
    obs = {**world.observe(), **lookahead_observation(world, model.actions, "cv")}
    assert not obs["cand_humans_mask"].all() and obs["cand_humans_mask"].sum(-1).unique().numel() > 3
    with torch.no_grad():
        chunked, whole = model.candidate_values(obs), model._values(obs)
    assert torch.allclose(chunked, whole, atol=1e-6, rtol=0)
    assert torch.equal(chunked.argmax(-1), whole.argmax(-1))
