"""algo=value: lookahead candidates, CrowdNav's value networks, targets and the greedy policy, against loop
references computed independently (CrowdNav's formulas written out per action, per human, per step)."""

from __future__ import annotations

import copy
import itertools
import math

import pytest
import torch
from worlds import replay_sim, reset_v1

from crowdbench.algos.value import ValueModel, ValuePolicy, epsilon, gamma_bar
from crowdbench.algos.value_train import discounted_returns, last_steps, td_targets
from crowdbench.data.scenes import load_scene
from crowdbench.envs.crowdnav import CrowdNavConfig
from crowdbench.envs.factory import crowdnav_world
from crowdbench.envs.lookahead import action_set, candidates, lookahead_observation, next_humans
from crowdbench.envs.rules import RUNNING, SUCCESS, SimConfig
from crowdbench.models.value_nets import (
    CADRLValue,
    LSTMRLValue,
    SARLValue,
    joint_state,
    net_input,
    occupancy_maps,
)


def crowd_world(n_cases=6, steps=6, visible=False, seed=0):
    """A CrowdNav circle-5 world a few steps into its test cases (the humans moving), the robot zig-zagging."""
    cfg = CrowdNavConfig(robot_visible=visible)
    world, scen = crowdnav_world(cfg, n_cases)
    world.reset(torch.ones(n_cases, dtype=torch.bool), scen.cases(list(range(seed, seed + n_cases))))
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        world.step(torch.rand(n_cases, 1, 2, generator=g) - 0.3)
    return world


def test_action_set_is_crowdnavs():
    acts = action_set(1.0)
    speeds = [(math.exp((i + 1) / 5) - 1) / (math.e - 1) for i in range(5)]
    ref = [(0.0, 0.0)] + [(s * math.cos(r), s * math.sin(r))
                          for r, s in itertools.product([2 * math.pi * k / 16 for k in range(16)], speeds)]
    assert acts.shape == (81, 2)
    assert torch.allclose(acts, torch.tensor(ref, dtype=torch.float32), atol=1e-7)
    assert abs(acts.norm(dim=-1).max().item() - 1.0) < 1e-6


@pytest.mark.parametrize("model", ["query", "cv"])
def test_candidates_equal_a_loop_over_actions(model):
    """Each candidate = a copy of the world stepped with that action (query: bit for bit, reward included);
    cv: the humans moved at constant velocity, the reward from a dense sampling of the step's motion."""
    world = crowd_world()
    acts = action_set(1.0)[::4]
    c = candidates(world, acts, model)
    h_pos, h_vel, _ = world.humans()
    cfg = world.cfg
    for k in range(len(acts)):
        w = copy.deepcopy(world)
        info = w.step(acts[k].expand(world.B, 1, 2).clone())
        assert torch.equal(c["robot_pos"][:, k], w.pos[:, 0])
        if model == "query":
            assert torch.equal(c["reward"][:, k], info.reward[:, 0])
            assert torch.equal(c["done"][:, k], info.terminated[:, 0])
            continue
        for b in range(world.B):  # CrowdNav's reward on the minimum gap over the step, sampled densely
            s = torch.linspace(0, 1, 2001).unsqueeze(-1)
            r = world.pos[b, 0] + s * (w.pos[b, 0] - world.pos[b, 0])
            gaps = [((h_pos[b, j] + s * h_vel[b, j] * cfg.dt) - r).norm(dim=-1).min() - 0.6 for j in range(5)]
            d = min(float(x) for x in gaps)
            at_goal = (w.pos[b, 0] - world.goal[b, 0]).norm() < cfg.robot_radius
            ref = -0.25 if d < 0 else 1.0 if at_goal else (d - 0.2) * 0.5 * cfg.dt if d < 0.2 else 0.0
            assert abs(float(c["reward"][b, k]) - ref) < 2e-4, (b, k)


def test_query_next_humans_are_the_worlds_bit_for_bit():
    world = crowd_world(steps=3)
    g = torch.Generator().manual_seed(1)
    for _ in range(8):
        pos, vel, _ = next_humans(world, "query")
        before = world.humans()[0].clone()
        world.step(torch.rand(world.B, 1, 2, generator=g) * 2 - 1)
        assert torch.equal(pos, world.humans()[0]) and torch.equal(vel, world.humans()[1])
        assert not torch.equal(pos, before)  # the humans moved: the check is not vacuous
    with pytest.raises(ValueError, match="invisible"):
        next_humans(crowd_world(visible=True, steps=0), "query")


def test_query_on_recorded_pedestrians_is_the_next_frame():
    """On a replay world (protocol v1: the humans never see the robot) ``query`` is the recorded next frame,
    position, velocity and presence, and reading it leaves the world's clock where it was."""
    scene = load_scene("zara1")
    world = replay_sim(scene, 4, SimConfig(dt=scene.dt, frame="rotate"))
    t0 = torch.tensor([0, 40, 200, 400])
    reset_v1(world, torch.ones(4, dtype=torch.bool), t0, torch.tensor([0.0, 1.0, 2.0, 3.0]))
    for _ in range(5):
        pos, vel, valid = next_humans(world, "query")
        t = world.crowd.t.clone()
        t1 = torch.where((world.outcome == RUNNING).any(-1), t + 1, t)  # a finished episode's clock stops
        assert torch.equal(pos, scene.pos[t1]) and torch.equal(vel, scene.vel[t1])
        assert torch.equal(valid, scene.valid[t1]) and torch.equal(world.crowd.t, t)
        world.step(torch.zeros(4, 1, 2))
        assert torch.equal(pos, world.humans()[0]) and torch.equal(vel, world.humans()[1])
    assert valid.any() and vel.abs().sum() > 0  # pedestrians present and walking: not a vacuous comparison
    c = candidates(world, action_set(1.0), "query")
    assert c["humans_pos"].shape == (4, scene.max_humans, 2)


def test_lookahead_observation_is_the_candidates_in_the_robot_frame():
    world = crowd_world()
    acts = action_set(1.0)
    c, o = candidates(world, acts, "cv"), lookahead_observation(world, acts, "cv")
    h = world.heading[:, 0]
    rel = o["cand_robot"][:, 0, :, :2]
    back = torch.stack((h[:, None, 0] * rel[..., 0] - h[:, None, 1] * rel[..., 1],
                        h[:, None, 1] * rel[..., 0] + h[:, None, 0] * rel[..., 1]), -1) + world.pos[:, :1]
    assert torch.allclose(back, c["robot_pos"], atol=1e-5)
    assert torch.equal(o["cand_reward"][:, 0], c["reward"])


def test_returns_and_targets_equal_crowdnavs_loops():
    g = gamma_bar(0.9, 0.25, 1.0)
    assert g == 0.9**0.25
    gen = torch.Generator().manual_seed(0)
    T, B = 9, 3
    lengths = [9, 4, 6]
    reward = torch.rand(T, B, generator=gen, dtype=torch.float64) - 0.5
    active = torch.tensor([[t < n for n in lengths] for t in range(T)])
    reward = reward * active
    ret = discounted_returns(reward, g)
    nv = torch.rand(T, B, generator=gen, dtype=torch.float64)
    tgt = td_targets(reward, nv, last_steps(active), g)
    for b, n in enumerate(lengths):
        rs = reward[:n, b].tolist()
        for i in range(n):  # explorer.update_memory, imitation_learning=True / False
            ref = sum(pow(0.9, max(t - i, 0) * 0.25 * 1.0) * r * (1 if t >= i else 0) for t, r in enumerate(rs))
            assert abs(float(ret[i, b]) - ref) < 1e-12
            ref_td = rs[i] if i == n - 1 else rs[i] + g * float(nv[i, b])
            assert abs(float(tgt[i, b]) - ref_td) < 1e-12


def test_epsilon_schedule():
    e = epsilon(torch.tensor([0, 1000, 2000, 4000, 9000]), 0.5, 0.1, 4000)
    assert torch.allclose(e, torch.tensor([0.5, 0.4, 0.3, 0.1, 0.1], dtype=torch.float64))


def crowdnav_rotate(s):
    """CrowdNav's ``CADRL.rotate`` on one unrotated joint state (px py vx vy r gx gy vpref theta px1 py1 vx1 vy1 r1)."""
    px, py, vx, vy, r, gx, gy, vp, _, px1, py1, vx1, vy1, r1 = s
    rot = math.atan2(gy - py, gx - px)
    c, sn = math.cos(rot), math.sin(rot)
    return [math.hypot(gx - px, gy - py), vp, 0.0, r, vx * c + vy * sn, vy * c - vx * sn,
            (px1 - px) * c + (py1 - py) * sn, (py1 - py) * c - (px1 - px) * sn, vx1 * c + vy1 * sn,
            vy1 * c - vx1 * sn, r1, math.hypot(px - px1, py - py1), r + r1]


def random_states(n=4, m=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g) * 8 - 4
    return r(n, 2), r(n, 2) / 4, r(n, 2), r(n, m, 2), r(n, m, 2) / 4


def test_joint_state_is_crowdnavs_rotate():
    rp, rv, goal, hp, hv = random_states()
    js = joint_state(rp, rv, goal, hp, hv, 0.3, 0.3, 1.0)
    for b, j in itertools.product(range(4), range(5)):
        s = [*rp[b].tolist(), *rv[b].tolist(), 0.3, *goal[b].tolist(), 1.0, 0.0, *hp[b, j].tolist(), *hv[b, j].tolist(), 0.3]
        assert torch.allclose(js[b, j], torch.tensor(crowdnav_rotate(s)), atol=1e-5)


def sarl_loop(net: SARLValue, x: torch.Tensor) -> float:
    """SARL's forward for one state ``[M, 13]``, human by human."""
    e = [net.mlp1(x[j]) for j in range(len(x))]
    gs = sum(e) / len(e)
    sc = [float(net.attention(torch.cat((ej, gs)))) for ej in e]
    w = [math.exp(s) / sum(math.exp(t) for t in sc) for s in sc]
    c = sum(wj * net.mlp2(ej) for wj, ej in zip(w, e, strict=True))
    return float(net.mlp3(torch.cat((x[0, :6], c))))


def test_sarl_equals_loop_and_is_permutation_invariant():
    torch.manual_seed(0)
    net = SARLValue()
    rp, rv, goal, hp, hv = random_states()
    x = joint_state(rp, rv, goal, hp, hv, 0.3, 0.3, 1.0)
    mask = torch.ones(4, 5, dtype=torch.bool)
    with torch.no_grad():
        v = net(x, mask)
        assert v.shape == (4, 1)
        for b in range(4):
            assert abs(float(v[b]) - sarl_loop(net, x[b])) < 1e-5
        perm = torch.tensor([3, 0, 4, 2, 1])
        assert torch.allclose(net(x[:, perm], mask), v, atol=1e-6)
        # a padded human changes nothing
        pad = torch.cat((x, x[:, :1]), 1)
        assert torch.allclose(net(pad, torch.cat((mask, torch.zeros(4, 1, dtype=torch.bool)), 1)), v, atol=1e-6)


def test_cadrl_and_lstm_rl_references():
    torch.manual_seed(0)
    rp, rv, goal, hp, hv = random_states()
    x = joint_state(rp, rv, goal, hp, hv, 0.3, 0.3, 1.0)
    mask = torch.ones(4, 5, dtype=torch.bool)
    cadrl, lstm = CADRLValue(), LSTMRLValue()
    perm = torch.tensor([2, 4, 0, 1, 3])
    with torch.no_grad():
        v = cadrl(x, mask)
        for b in range(4):  # CADRL.predict: the minimum over the pairwise values
            assert abs(float(v[b]) - min(float(cadrl.net(x[b, j])) for j in range(5))) < 1e-6
        v = lstm(x, mask)
        for b in range(4):  # LstmRL.predict: humans by decreasing distance, the closest read last
            order = sorted(range(5), key=lambda j: -float(x[b, j, 11]))
            h = c = torch.zeros(1, 50)
            cell = torch.nn.LSTMCell(13, 50)
            cell.weight_ih, cell.weight_hh = lstm.lstm.weight_ih_l0, lstm.lstm.weight_hh_l0
            cell.bias_ih, cell.bias_hh = lstm.lstm.bias_ih_l0, lstm.lstm.bias_hh_l0
            for j in order:
                h, c = cell(x[b, j].unsqueeze(0), (h, c))
            assert abs(float(v[b]) - float(lstm.net(torch.cat((x[b, 0, :6], h[0]))))) < 1e-5
        assert torch.allclose(lstm(x[:, perm], mask), v, atol=1e-6)
        assert torch.allclose(cadrl(x[:, perm], mask), cadrl(x, mask))


def test_occupancy_maps_equal_crowdnavs_loop():
    _, _, _, hp, hv = random_states(n=3, m=6, seed=2)
    hp = hp / 2  # close enough for the 4 m map to hold neighbours
    om = occupancy_maps(hp, hv, torch.ones(3, 6, dtype=torch.bool))
    assert om.shape == (3, 6, 48) and om[..., 0::3].sum() > 0
    for b, i in itertools.product(range(3), range(6)):
        ang = math.atan2(float(hv[b, i, 1]), float(hv[b, i, 0]))
        cells = {}
        for j in range(6):
            if j == i:
                continue
            dx, dy = (hp[b, j] - hp[b, i]).tolist()
            rot, dist = math.atan2(dy, dx) - ang, math.hypot(dx, dy)
            ix, iy = math.floor(math.cos(rot) * dist + 2), math.floor(math.sin(rot) * dist + 2)
            if 0 <= ix < 4 and 0 <= iy < 4:
                vr = math.atan2(float(hv[b, j, 1]), float(hv[b, j, 0])) - ang
                sp = float(hv[b, j].norm())
                cells.setdefault(4 * iy + ix, []).append((math.cos(vr) * sp, math.sin(vr) * sp))
        ref = torch.zeros(48)
        for cell, vs in cells.items():
            ref[3 * cell:3 * cell + 3] = torch.tensor([1.0, sum(v[0] for v in vs) / len(vs), sum(v[1] for v in vs) / len(vs)])
        assert torch.allclose(om[b, i], ref, atol=1e-5), (b, i)


def value_model(net="sarl", lookahead="query"):
    from types import SimpleNamespace

    a = SimpleNamespace(net=net, lookahead=lookahead, speeds=5, headings=16, kinematics="holonomic", gamma=0.9,
                        terminal_value=True)
    torch.manual_seed(0)
    return ValueModel(a, CrowdNavConfig())


@pytest.mark.parametrize("net", ["sarl", "lm_sarl", "lstm_rl", "cadrl"])
def test_candidate_values_equal_a_loop_over_actions(net):
    """One batched forward pass = the value of each action computed alone (CrowdNav's predict loop)."""
    model = value_model(net)
    world = crowd_world(n_cases=3)
    obs = world.observe()
    look = lookahead_observation(world, model.actions, "query")
    with torch.no_grad():
        vals = model.candidate_values({**obs, **look})
        for b, k in itertools.product(range(3), range(0, 81, 7)):
            cr, ch = look["cand_robot"][b, 0, k], look["cand_humans"][b, 0]
            m = look["cand_humans_mask"][b, 0]
            x = net_input(net, cr[:2], cr[2:], obs["robot"][b, 0, 4:6], ch[:, :2], ch[:, 2:], m, model.radii, 1.0)
            ref = float(look["cand_reward"][b, 0, k]) + model.gamma_bar * float(model.net(x.unsqueeze(0), m.unsqueeze(0)))
            assert abs(float(vals[b, k]) - ref) < 1e-5


def test_greedy_evaluation_is_deterministic_and_labelled_privileged():
    from crowdbench.protocols.crowdnav import evaluate_crowdnav

    short = CrowdNavConfig(time_limit=30)  # an untrained network rarely arrives: keep its episodes short
    runs = [evaluate_crowdnav(ValuePolicy(value_model()), short, episodes=4, save_episodes=True) for _ in range(2)]
    a, b = (r["scenes"]["circle_n5"] for r in runs)
    assert a == b
    assert runs[0]["privileged"] is True and runs[0]["lookahead"] == "query"
    assert "(privileged)" in runs[0]["policy"]
    cv = evaluate_crowdnav(ValuePolicy(value_model(lookahead="cv")), short, episodes=2)
    assert "privileged" not in cv and cv["lookahead"] == "cv"
    assert SUCCESS == 1


def test_memory_keeps_crowdnavs_episodes():
    """Success and collision episodes are stored whole; a timeout only with store_timeouts, without its last step."""
    from crowdbench.algos.value_train import make_memory, store
    from crowdbench.envs.rules import COLLISION, TIMEOUT

    lengths, outcome = [3, 5, 2], torch.tensor([SUCCESS, TIMEOUT, COLLISION])
    T, B = 5, 3
    active = torch.tensor([[t < n for n in lengths] for t in range(T)])
    r = {"x": torch.arange(T * B, dtype=torch.float32).reshape(T, B, 1, 1).expand(T, B, 5, 13),
         "mask": torch.ones(T, B, 5, dtype=torch.bool), "active": active, "outcome": outcome}
    values = torch.arange(T * B, dtype=torch.float32).reshape(T, B)
    for timeouts, expect in ((False, [(t, b) for b in (0, 2) for t in range(lengths[b])]),
                             (True, [(t, b) for b in range(3) for t in range(lengths[b] - (b == 1))])):
        mem = make_memory(100, 10)
        assert store(mem, r, values, timeouts) == len(expect)
        got = sorted(mem[:len(mem)]["value"].squeeze(-1).tolist())
        assert got == sorted(float(values[t, b]) for t, b in expect)
        assert torch.equal(mem[:len(mem)]["x"][:, 0, 0], mem[:len(mem)]["value"].squeeze(-1))  # pairs stay paired
    assert COLLISION != TIMEOUT


def test_run_trains_evaluates_and_the_checkpoint_evaluates_again(tmp_path):
    """``crowdbench run env=crowdnav algo=value`` (a tiny budget): a checkpoint, results labelled privileged;
    ``crowdbench eval policy=checkpoint`` of it gives the same outcomes."""
    import json

    from crowdbench.cli import main

    tiny = ["env=crowdnav", "algo=value", "algo.batch=4", "algo.il_episodes=4", "algo.il_steps=3", "algo.episodes=4",
            "algo.train_batches=1", "algo.batch_size=8", "algo.val_every=0", "env.time_limit=20", "env.eval_episodes=3"]
    assert main(["run", *tiny, f"out={tmp_path / 'run'}"]) == 0
    res = json.loads((tmp_path / "run" / "results.json").read_text())
    assert res["privileged"] is True and res["lookahead"] == "query"
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    assert log[0]["il_episodes"] == 4 and log[1]["episodes"] == 4 and log[-1]["done"]
    assert main(["eval", "env=crowdnav", "env.time_limit=20", "env.eval_episodes=3",
                 f"policy={tmp_path / 'run' / 'checkpoint.pt'}", f"out={tmp_path / 'eval'}"]) == 0
    again = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert again["scenes"] == res["scenes"] and again["privileged"] is True


def test_keep_best_restores_the_best_validated_network():
    from crowdbench.algos.value_train import Best

    model = value_model("cadrl")
    best = Best(model, None, None, print)
    best.active = True  # scored by hand below (no validation round)
    first = copy.deepcopy(model.net.state_dict())
    best.offer({"success": 0.9, "nav_time": 12.0}, 0)
    with torch.no_grad():
        for p in model.net.parameters():
            p.add_(1.0)
    best.offer({"success": 0.9, "nav_time": 12.5}, 32)  # as successful but slower: not kept
    best.offer({"success": 0.8, "nav_time": 10.0}, 64)  # faster but less successful: not kept
    best.restore()
    assert best.episode == 0 and all(torch.equal(v, first[k]) for k, v in model.net.state_dict().items())


@pytest.mark.parametrize("net", ["sarl", "lm_sarl"])
def test_a_candidate_is_the_state_the_step_leads_to(net):
    """V is trained on observed states and queried on candidates: with ``query`` the candidate of the action
    taken is the next observed state, as the network reads it."""
    model = value_model(net)
    world = crowd_world(n_cases=4)
    obs = world.observe()
    look = lookahead_observation(world, model.actions, "query")
    for k in (0, 5, 40, 77):
        w = copy.deepcopy(world)
        w.step(model.actions[k].expand(4, 1, 2).clone())
        x_next, m_next = model.state(w.observe())
        cr, ch = look["cand_robot"][:, 0, k], look["cand_humans"][:, 0]
        x_cand = net_input(net, cr[:, :2], cr[:, 2:], obs["robot"][:, 0, 4:6], ch[..., :2], ch[..., 2:],
                           look["cand_humans_mask"][:, 0], model.radii, 1.0)
        assert torch.equal(m_next, look["cand_humans_mask"][:, 0])
        assert torch.allclose(x_cand, x_next, atol=1e-5), (k, (x_cand - x_next).abs().max())


@pytest.mark.slow
def test_a_value_submission_in_a_worker_gives_the_in_process_outcomes(tmp_path):
    """The isolated worker declares its lookahead; the harness computes the candidates and sends them with
    each observation: the same outcomes as the policy evaluated in-process, labelled privileged."""
    from omegaconf import OmegaConf

    from crowdbench.algos.checkpoint import policy_from_checkpoint, save_checkpoint
    from crowdbench.cli import compose
    from crowdbench.leaderboard.sandbox import Limits
    from crowdbench.leaderboard.worker import WorkerPolicy
    from crowdbench.protocols.crowdnav import evaluate_crowdnav

    sub = tmp_path / "value_s0"
    sub.mkdir()
    cfg = OmegaConf.to_container(compose(["env=crowdnav", "algo=value", "algo.net=cadrl"]), resolve=True)
    model = value_model("cadrl")
    save_checkpoint(sub / "checkpoint.pt", {"config": cfg, "actor": model.net.state_dict(), "frames": 0})
    (sub / "submission.yaml").write_text(f"name: value_s0\nkind: learned\nentry: CADRL (value)\nencoder: "
                                         f"{cfg['encoder']['name']}\nalgo: value\nlookahead: query\nnet: cadrl\nprivileged: true\n"
                                         "track: crowdnav-circle5\nauthors: [t]\n")
    short = CrowdNavConfig(time_limit=25)
    local = evaluate_crowdnav(policy_from_checkpoint(sub / "checkpoint.pt"), short, episodes=3)
    with WorkerPolicy(sub, "value_s0", Limits(step_s=30, load_s=60)) as remote:
        assert remote.lookahead[0] == "query" and torch.equal(remote.lookahead[1], model.actions)
        res = evaluate_crowdnav(remote, short, episodes=3)
    assert res["scenes"] == local["scenes"] and res["privileged"] is True and res["lookahead"] == "query"


@pytest.mark.parametrize("name", ["gatedgcn", "rgl"])
def test_an_existing_encoder_as_the_value_network(name):
    """``algo.net=encoder``: the encoder reads the joint state as its observation (robot at the origin, goal at
    (dg, 0)); its value equals the encoder + head on that observation built by hand, and is permutation-invariant."""
    import yaml

    from crowdbench.cli import CONFIG_DIR
    from crowdbench.models.value_nets import EncoderValue

    torch.manual_seed(0)
    net = EncoderValue(yaml.safe_load((CONFIG_DIR / "encoder" / f"{name}.yaml").read_text()))
    rp, rv, goal, hp, hv = random_states()
    x = joint_state(rp, rv, goal, hp, hv, 0.3, 0.3, 1.0)
    mask = torch.ones(4, 5, dtype=torch.bool)
    with torch.no_grad():
        v = net(x, mask)
        for b in range(4):
            u = (goal[b] - rp[b]) / (goal[b] - rp[b]).norm()
            def rot(w, u=u):
                return torch.stack((w[..., 0] * u[0] + w[..., 1] * u[1], w[..., 1] * u[0] - w[..., 0] * u[1]), -1)

            robot = torch.cat((torch.zeros(2), rot(rv[b]), (goal[b] - rp[b]).norm().reshape(1), torch.zeros(1)))
            humans = torch.cat((rot(hp[b] - rp[b]), rot(hv[b])), -1)
            self_state = torch.cat((robot[4:5], torch.tensor([1.0, 0.0, 0.3]), robot[2:4]))  # dg, v_pref, theta, r, v
            ref = net.head(torch.cat((self_state, net.encoder(robot[None], humans[None], mask[:1])[1][0]))[None])
            assert torch.allclose(v[b], ref[0], atol=1e-5)
        assert torch.allclose(net(x[:, [4, 2, 0, 3, 1]], mask), v, atol=1e-5)


def test_resume_continues_deep_v_learning_bit_for_bit(tmp_path, monkeypatch):
    """Ctrl-C during deep V-learning writes a snapshot; ``resume`` continues from it without repeating the
    imitation and ends with the weights of the run that was never stopped. Another recipe is refused."""
    import crowdbench.algos.value_train as vt
    from crowdbench.algos.checkpoint import load_checkpoint
    from crowdbench.cli import compose

    cfg = compose(["env=crowdnav", "algo=value", "algo.net=cadrl", "algo.batch=4", "algo.il_episodes=4",
                   "algo.il_steps=3", "algo.episodes=24", "algo.train_batches=2", "algo.batch_size=8",
                   "algo.val_every=0", "algo.target_update=8", "env.time_limit=20"])
    vt.train_value(cfg, tmp_path / "whole", log=lambda d: None)
    calls, real = [], vt.rl_round

    def stopped(*a, **k):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(vt, "rl_round", stopped)
    with pytest.raises(KeyboardInterrupt):
        vt.train_value(cfg, tmp_path / "part", log=lambda d: None)
    monkeypatch.setattr(vt, "rl_round", real)
    snap = load_checkpoint(tmp_path / "part" / vt.RESUME_FILE)
    assert snap["learner"]["done"] == 12 and not (tmp_path / "part" / "checkpoint.pt").exists()
    monkeypatch.setattr(vt, "imitation", lambda *a, **k: pytest.fail("the imitation ran again"))
    vt.train_value(cfg, tmp_path / "part", log=lambda d: None, resume=True)
    whole, part = (load_checkpoint(tmp_path / d / "checkpoint.pt") for d in ("whole", "part"))
    assert part["episodes"] == whole["episodes"] == 24
    assert all(torch.equal(whole["actor"][k], v) for k, v in part["actor"].items())
    other = compose(["env=crowdnav", "algo=value", "algo.net=cadrl", "algo.batch=4", "algo.lr=0.5"])
    with pytest.raises(ValueError, match="written with other algo"):
        vt.train_value(other, tmp_path / "part", log=lambda d: None, resume=True)
    with pytest.raises(ValueError, match="not found"):
        vt.train_value(cfg, tmp_path / "none", log=lambda d: None, resume=True)
