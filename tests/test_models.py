"""Graph construction, encoders and heads (crowdbench.models)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
import yaml
from tensordict import TensorDict
from worlds import SMALL_ENCODERS, students_obs

from crowdbench.envs.observation import ACTION, OBS
from crowdbench.models import ENCODERS, make_encoder
from crowdbench.models.graph import build_graph, cap_binding
from crowdbench.models.heads import (
    Actor,
    Critic,
    TwinCritic,
    actor_module,
    critic_module,
    prepare_batch,
)

CONFIGS = Path(__file__).resolve().parents[1] / "crowdbench" / "conf" / "encoder"
SMALL = SMALL_ENCODERS


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def real_obs():
    """Real STUDENTS001 observations a few steps into episodes: [B=12, A=1, ...]."""
    torch.manual_seed(0)
    return students_obs(12, 6)


def obs_args(o):
    return o["robot"], o["humans"], o["humans_mask"]


Y2 = 1.00498756  # 2^2 + Y2^2 = 5.01


def hand_obs(offset=(0.0, 0.0)):
    """Robot R at (0,0) + offset with goal (3,0) + offset; humans (slot: position):
    H1 (1,2) [d2(R)=5, included], H2 (2,-Y2) [d2(R)=5.01, excluded], H3 (3,2), H4 unobserved
    (garbage values), H5 (1,0). World-frame style: absolute positions, goal absolute."""
    ox, oy = offset
    robot = torch.tensor([[ox, oy, 0.3, -0.1, 3.0 + ox, oy]])
    pos = torch.tensor([[1.0, 2.0], [2.0, -Y2], [3.0, 2.0], [0.5, 0.0], [1.0, 0.0]]) + torch.tensor([ox, oy])
    vel = torch.tensor([[0.1, 0.0], [0.0, 0.2], [-0.3, 0.0], [9.0, 9.0], [0.0, -0.4]])
    humans = torch.cat((pos, vel), -1).unsqueeze(0)
    mask = torch.tensor([[True, True, True, False, True]])
    return robot[:, None], humans[:, None], mask[:, None]  # A = 1


def rows_as_sets(g, b=0):
    """{receiving node id: {sender id: attr}} from the documented K+1 slot layout (in the
    receptive layout only row 0 and the rows of the robot's valid slots are real)."""
    nbr, mask, attr = g.slots()
    rows = range(nbr.shape[1])
    if not g.full:
        rows = [0] + [1 + s for s in range(g.nbr.shape[2]) if g.nbr_mask[b, 0, s]]
    out = {}
    for r in rows:
        node = int(g.targets[b, r])
        out[node] = {
            int(nbr[b, r, s]): tuple(round(float(v), 4) for v in attr[b, r, s])
            for s in range(nbr.shape[2])
            if mask[b, r, s]
        }
    return out


EXPECTED = {  # receiving node -> {sender: p_j - p_i}; ids: 0 R, 1..5 H1..H5, 6 goal
    0: {6: (3.0, 0.0), 5: (1.0, 0.0), 1: (1.0, 2.0)},
    1: {0: (-1.0, -2.0), 3: (2.0, 0.0), 5: (0.0, -2.0)},
    2: {5: (-1.0, round(Y2, 4))},
    3: {1: (-2.0, 0.0)},
    4: {},
    5: {0: (-1.0, 0.0), 2: (1.0, round(-Y2, 4)), 1: (0.0, 2.0)},
}


# --------------------------------------------------------------------------- graph
@pytest.mark.parametrize("offset", [(0.0, 0.0), (10.0, -4.0)])
def test_hand_built_graph_full_layout(offset):
    g = build_graph(*hand_obs(offset), k=8, layers=2, receptive_field=False)
    assert g.full and g.nbr.shape == (1, 6, 8)  # rows: every node but the goal
    assert rows_as_sets(g) == EXPECTED


def test_hand_built_graph_cap_keeps_nearest():
    g = build_graph(*hand_obs(), k=2, layers=2, receptive_field=False)
    got = rows_as_sets(g)
    assert got[0] == EXPECTED[0]  # 2 humans + the goal on top of the cap
    assert set(got[5]) == {0, 2}  # R (d2=1), H2 (2.01); H1 (4) dropped
    assert set(got[1]) == {3, 5}  # H3, H5 (4); R (5) dropped
    assert got[3] == EXPECTED[3]
    stats = cap_binding(*hand_obs(), k=2)
    assert stats["nodes"] == pytest.approx(2 / 5)  # H1 and H5 of R, H1, H2, H3, H5
    assert stats["robot"] == 0.0
    assert stats["max_degree"] == 3
    assert cap_binding(*hand_obs(), k=8)["nodes"] == 0.0


def test_receptive_layout_rows_are_robot_and_its_neighbours():
    g = build_graph(*hand_obs(), k=3, layers=2, receptive_field=True)
    assert not g.full and g.sizes == (4, 1)
    got = rows_as_sets(g)
    assert got[0] == EXPECTED[0]
    assert got[5] == EXPECTED[5] and got[1] == EXPECTED[1]
    assert [int(t) for t in g.targets[0, :3]] == [0, 5, 1]  # robot, then its neighbours nearest first
    assert g.nbr_mask[0, 0].tolist() == [True, True, False]


@pytest.mark.parametrize("rf", [False, True])
def test_robot_radius_widens_only_the_robots_incoming_edges(rf):
    # robot_radius2 = 9 (3 m): H2 (d2 = 5.01) now sends to the robot; H3 (d2 = 13) still does not;
    # H2 still receives nothing from the robot, and the edges between humans are the sqrt(5) m ones
    g = build_graph(*hand_obs(), k=3, layers=2, receptive_field=rf, robot_radius2=9.0)
    assert g.full != rf
    got = rows_as_sets(g)
    assert got[0] == {**EXPECTED[0], 2: (2.0, round(-Y2, 4))}
    assert all(got[node] == EXPECTED[node] for node in got if node != 0)
    assert set(got) == ({0, 1, 2, 5} if rf else set(EXPECTED))


@pytest.mark.parametrize("name", ["gatedgcn", "gcn", "gat"])
def test_receptive_field_equals_full_computation_with_a_robot_radius(real_obs, name):
    torch.manual_seed(0)
    full = make_encoder(name, dim=16, receptive_field=False, robot_radius2=25.0)
    rf = make_encoder(name, dim=16, receptive_field=True, robot_radius2=25.0)
    rf.load_state_dict(full.state_dict())
    paper = make_encoder(name, dim=16, receptive_field=True)
    paper.load_state_dict(full.state_dict())
    with torch.no_grad():
        a, b, c = full(*obs_args(real_obs))[1], rf(*obs_args(real_obs))[1], paper(*obs_args(real_obs))[1]
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(b, c, atol=1e-3)  # the farther humans reach the robot
    assert full.prep_key != paper.prep_key  # prepared graphs of the two radii are never mixed


def test_goal_edge_attribute_is_goal_minus_position(real_obs):
    g = build_graph(*obs_args(real_obs))
    robot = real_obs["robot"].reshape(-1, 6)
    _, mask, attr = g.slots()
    torch.testing.assert_close(attr[:, 0, 0], robot[:, 4:6] - robot[:, 0:2])
    assert mask[:, 0, 0].all() and not mask[:, 1:, 0].any()


def test_graph_tensors_roundtrip(real_obs):
    from crowdbench.models.graph import Graph

    for rf in (True, False):
        g = build_graph(*obs_args(real_obs), receptive_field=rf)
        g2 = Graph.from_tensors(g.tensors(), k=8, layers=2)
        assert g2.full == g.full and g2.sizes == g.sizes and g2.lead_shape == g.lead_shape
        for f in ("nbr", "nbr_mask", "z_t", "edge_in", "goal_in", "valid"):
            assert torch.equal(getattr(g2, f), getattr(g, f))


# --------------------------------------------------------------------------- reference
def reference_gated(enc, robot, humans, mask, eps, edge_dist=False):
    """Eq. 3-7 with Python loops over nodes and an uncapped graph built from the rule; ``edge_dist``: each edge
    attribute is ``(p_j - p_i, |p_j - p_i|)``."""
    d = enc.dim
    out = []
    for b in range(robot.shape[0]):
        r = robot[b]
        nodes = [("r", r[0:2], enc.robot_emb(r))]
        nodes += [("h", humans[b, i, 0:2], enc.human_emb(humans[b, i])) for i in range(humans.shape[1]) if mask[b, i]]
        goal_x = torch.cat((torch.zeros(4), r[4:6]))
        n_ag = len(nodes)
        pos = [p for _, p, _ in nodes] + [r[4:6]]
        h = [x for _, _, x in nodes] + [enc.goal_emb(goal_x)]
        nbrs = {i: [j for j in range(n_ag) if j != i and float(((pos[j] - pos[i]) ** 2).sum()) <= 5.0] for i in range(n_ag)}
        nbrs[0].append(n_ag)  # goal -> robot
        rels = {(i, j): pos[j] - pos[i] for i in nbrs for j in nbrs[i]}
        if edge_dist:
            rels = {ij: torch.cat((r, r.norm().reshape(1))) for ij, r in rels.items()}
        e = {ij: enc.edge_emb(r) for ij, r in rels.items()}
        for layer in enc.layers:
            A, U = layer.tgt.weight.split(d)
            a_b, u_b = layer.tgt.bias.split(d)
            Bw, V = layer.src.weight.split(d)
            b_b, v_b = layer.src.bias.split(d)
            new_e = {
                (i, j): e[i, j] + torch.relu(F.linear(h[i], A, a_b) + F.linear(h[j], Bw, b_b) + layer.C(e[i, j]))
                for (i, j) in e
            }
            new_h = list(h)
            for i in range(n_ag + 1):
                agg = torch.zeros(d)
                if nbrs.get(i):
                    sig = torch.stack([torch.sigmoid(new_e[i, j]) for j in nbrs[i]])
                    eta = sig / (sig.sum(0) + eps)
                    agg = sum(eta[k] * F.linear(h[j], V, v_b) for k, j in enumerate(nbrs[i]))
                new_h[i] = h[i] + torch.relu(F.linear(h[i], U, u_b) + agg)
            h, e = new_h, new_e
        out.append(h[0])
    return torch.stack(out)


def reference_gcn(enc, robot, humans, mask):
    out = []
    for b in range(robot.shape[0]):
        r = robot[b]
        pos = [r[0:2]] + [humans[b, i, 0:2] for i in range(humans.shape[1]) if mask[b, i]]
        h = [enc.robot_emb(r)] + [enc.human_emb(humans[b, i]) for i in range(humans.shape[1]) if mask[b, i]]
        n_ag = len(h)
        h.append(enc.goal_emb(torch.cat((torch.zeros(4), r[4:6]))))
        nbrs = {i: [j for j in range(n_ag) if j != i and float(((pos[j] - pos[i]) ** 2).sum()) <= 5.0] for i in range(n_ag)}
        nbrs[0].append(n_ag)
        for layer in enc.layers:
            new_h = list(h)
            for i in range(n_ag + 1):
                agg = torch.stack([layer.src(h[j]) for j in nbrs[i]]).mean(0) if nbrs.get(i) else 0.0
                new_h[i] = h[i] + torch.relu(layer.tgt(h[i]) + agg)
            h = new_h
        out.append(h[0])
    return torch.stack(out)


@pytest.mark.parametrize("edge_dist", [False, True])
@pytest.mark.parametrize("rf", [True, False])
def test_gatedgcn_matches_loop_reference(real_obs, rf, edge_dist):
    torch.manual_seed(1)
    enc = make_encoder("gatedgcn", dim=8, k=64, receptive_field=rf, edge_dist=edge_dist)  # K never binds
    robot, humans, mask = (x[:4, 0] for x in obs_args(real_obs))
    with torch.no_grad():
        _, got = enc(robot, humans, mask)
        want = reference_gated(enc, robot, humans, mask, eps=1e-6, edge_dist=edge_dist)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


def test_edge_distance_is_an_option_of_gatedgcn_only(real_obs):
    """The distance column: its own graph key (prepared graphs never mix), a finite gradient through the
    lookahead critic's observation even on padded slots, and a one-line error for encoders without edges."""
    enc = make_encoder("gatedgcn", dim=8, edge_dist=True)
    assert enc.prep_key.endswith("_dist") and enc.prep_key != make_encoder("gatedgcn", dim=8).prep_key
    robot, humans, mask = (x[:4, 0].clone() for x in obs_args(real_obs))
    g = enc.build_graph(robot, humans, mask)
    attr = g.edge_attr
    torch.testing.assert_close(attr[..., 2], attr[..., :2].norm(dim=-1) * g.nbr_mask, atol=1e-5, rtol=0)
    robot.requires_grad_(True)
    enc(robot, humans, mask)[1].sum().backward()
    assert torch.isfinite(robot.grad).all() and robot.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="encoder.edge_dist"):
        make_encoder("gcn", dim=8, edge_dist=True)


def test_gcn_matches_loop_reference(real_obs):
    torch.manual_seed(2)
    enc = make_encoder("gcn", dim=8, k=64)
    robot, humans, mask = (x[:4, 0] for x in obs_args(real_obs))
    with torch.no_grad():
        _, got = enc(robot, humans, mask)
        want = reference_gcn(enc, robot, humans, mask)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


# --------------------------------------------------------------------------- gates
def test_gates_sum_to_one_and_are_zero_on_padding(real_obs):
    torch.manual_seed(0)
    enc = make_encoder("gatedgcn", dim=16, receptive_field=False)
    g = enc.build_graph(*obs_args(real_obs))
    gates = []
    with torch.no_grad():
        enc.encode(g, gates_out=gates)
    _, mask, _ = g.slots()
    assert len(gates) == 2
    for eta in gates:  # [B*, N-1, K+1, D]
        assert (eta[~mask] == 0).all()
        total = eta.sum(2)  # per receiving node and channel
        has = mask.any(-1)
        torch.testing.assert_close(total[has], torch.ones_like(total[has]), atol=1e-5, rtol=0)
        assert (total[~has] == 0).all()
    lg = enc.last_gates
    assert lg.values.shape == (12, 1, 9) and lg.nbr.shape == (12, 1, 9)
    assert (lg.nbr[..., 0] == real_obs["humans"].shape[-2] + 1).all()  # slot 0 = goal node id
    assert (lg.values[~lg.mask] == 0).all()
    torch.testing.assert_close(lg.values.sum(-1), torch.ones(12, 1), atol=1e-5, rtol=0)


def test_gcn_and_mlp_have_no_gates(real_obs):
    for name in ("gcn", "mlp"):
        enc = make_encoder(name, **SMALL[name])
        enc(*obs_args(real_obs))
        assert enc.last_gates is None


# --------------------------------------------------------------------------- invariances
@pytest.mark.parametrize("name", list(ENCODERS))
def test_permuting_humans_leaves_robot_output_unchanged(real_obs, name):
    torch.manual_seed(0)
    enc = make_encoder(name, **SMALL[name])
    robot, humans, mask = obs_args(real_obs)
    perm = torch.randperm(humans.shape[-2])
    with torch.no_grad():
        _, a = enc(robot, humans, mask)
        _, b = enc(robot, humans[..., perm, :], mask[..., perm])
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", list(ENCODERS))
def test_unobserved_far_human_changes_nothing(real_obs, name):
    torch.manual_seed(0)
    enc = make_encoder(name, **SMALL[name])
    robot, humans, mask = obs_args(real_obs)
    extra = torch.tensor([40.0, -30.0, 1.0, 1.0]).expand(*humans.shape[:-2], 1, 4)
    humans2 = torch.cat((extra, humans), -2)
    mask2 = torch.cat((torch.zeros_like(mask[..., :1]), mask), -1)
    with torch.no_grad():
        _, a = enc(robot, humans, mask)
        _, b = enc(robot, humans2, mask2)
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["gatedgcn", "gcn", "gat"])
@pytest.mark.parametrize("k", [2, 8])
@pytest.mark.parametrize("layers", [1, 2])
def test_receptive_field_equals_full_computation(real_obs, name, k, layers):
    torch.manual_seed(0)
    full = make_encoder(name, dim=16, k=k, layers=layers, receptive_field=False)
    rf = make_encoder(name, dim=16, k=k, layers=layers, receptive_field=True)
    rf.load_state_dict(full.state_dict())
    with torch.no_grad():
        hn_full, a = full(*obs_args(real_obs))
        hn_rf, b = rf(*obs_args(real_obs))
    assert hn_full.shape[-2] == real_obs["humans"].shape[-2] + 2 and hn_rf.shape[-2] == 1
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(hn_full[..., 0, :], a)
    if name in ("gatedgcn", "gat"):
        torch.testing.assert_close(full.last_gates.values, rf.last_gates.values, atol=1e-6, rtol=0)


def test_three_layers_fall_back_to_full_layout(real_obs):
    enc = make_encoder("gatedgcn", dim=8, layers=3)
    assert enc.build_graph(*obs_args(real_obs)).full
    _, h = enc(*obs_args(real_obs))
    assert h.shape == (12, 1, 8)


# --------------------------------------------------------------------------- heads
@pytest.mark.parametrize("name", list(ENCODERS))
def test_gradients_reach_every_parameter(real_obs, name):
    torch.manual_seed(0)
    actor = Actor(make_encoder(name, **SMALL[name]), hidden=[16])
    critic = Critic(make_encoder(name, **SMALL[name]), hidden=[16])
    a = actor(*obs_args(real_obs))
    q = critic(*obs_args(real_obs), a)
    (q.sum() + a.square().sum()).backward()
    for net in (actor, critic):
        for n, p in net.named_parameters():
            assert p.grad is not None and p.grad.abs().sum() > 0, n


@pytest.mark.parametrize("name", list(ENCODERS))
def test_acting_after_a_fused_adam_step_uses_the_new_weights(real_obs, name):
    """The training actor acts (no_grad, train mode) between optimiser steps: its actions must be
    those of a fresh network holding the updated weights. Fused Adam updates parameters in place
    without bumping their versions, so a cache keyed on versions served the first weights forever."""
    torch.manual_seed(0)
    actor = Actor(make_encoder(name, **SMALL[name]), hidden=[16])
    opt = torch.optim.Adam(actor.parameters(), lr=0.05, fused=True)
    with torch.no_grad():
        before = actor(*obs_args(real_obs))
    for _ in range(3):
        opt.zero_grad()
        actor(*obs_args(real_obs)).sum().backward()
        opt.step()
    fresh = Actor(make_encoder(name, **SMALL[name]), hidden=[16])
    fresh.load_state_dict(actor.state_dict())
    with torch.no_grad():
        after, expected = actor(*obs_args(real_obs)), fresh(*obs_args(real_obs))
        assert (after - before).abs().max() > 1e-3  # the steps changed the policy
        torch.testing.assert_close(after, expected, rtol=0, atol=0)
        # eval mode (an evaluated checkpoint) caches layer 1 and gives the same actions
        fresh.eval()
        torch.testing.assert_close(fresh(*obs_args(real_obs)), expected, rtol=0, atol=0)
        torch.testing.assert_close(fresh(*obs_args(real_obs)), expected, rtol=0, atol=0)


@pytest.mark.parametrize("name", list(ENCODERS))
def test_heads_shapes_and_bounds_with_several_agents(real_obs, name):
    o = {k: torch.cat((v, v.flip(0)), 1) for k, v in real_obs.items()}  # A = 2
    actor = Actor(make_encoder(name, **SMALL[name]), v_max=0.7)
    critic = Critic(make_encoder(name, **SMALL[name]))
    a = actor(*obs_args(o))
    assert a.shape == (12, 2, 2) and a.abs().max() <= 0.7
    assert critic(*obs_args(o), a).shape == (12, 2, 1)
    td = TensorDict({"agents": {"observation": o}}, batch_size=[12])
    torch.testing.assert_close(actor(td), a)


def test_unknown_encoder_lists_valid_names():
    with pytest.raises(ValueError) as err:
        make_encoder("transformer")
    for name in ENCODERS:
        assert name in str(err.value)


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.yaml")), ids=lambda p: p.stem)
def test_encoder_configs_build(real_obs, path):
    cfg = yaml.safe_load(path.read_text())
    enc = make_encoder(**cfg)
    _, h = enc(*obs_args(real_obs))
    assert h.shape == (12, 1, enc.out_dim)


def test_expected_presets_exist():
    names = {p.stem for p in CONFIGS.glob("*.yaml")}
    assert set(ENCODERS) == names  # one preset per encoder: the paper's width is experiment=paper
    gated = yaml.safe_load((CONFIGS / "gatedgcn.yaml").read_text())
    assert gated["dim"] == 32 and gated["layers"] == 2


@pytest.mark.parametrize("name", list(ENCODERS))
def test_twin_critic_vmap_equals_sequential(real_obs, name):
    torch.manual_seed(0)
    twin = TwinCritic(Critic(make_encoder(name, **SMALL[name])), vmap=True)
    a = torch.rand(12, 1, 2) * 2 - 1
    q = twin(*obs_args(real_obs), a)
    twin.vmap = False
    q_seq = twin(*obs_args(real_obs), a)
    assert q.shape == (2, 12, 1, 1)
    torch.testing.assert_close(q, q_seq, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(q[0], q[1])  # independent critics
    q.sum().backward()
    assert all(p.grad is not None for p in twin.parameters())


# --------------------------------------------------------------------------- TorchRL
def transition_batch(o):
    b = o["robot"].shape[0]
    nxt = {k: v.roll(1, 0) for k, v in o.items()}
    return TensorDict(
        {
            "agents": {"observation": o, "action": torch.rand(b, 1, 2) * 2 - 1},
            "next": {
                "agents": {
                    "observation": nxt,
                    "reward": torch.randn(b, 1, 1),
                    "done": torch.zeros(b, 1, 1, dtype=torch.bool),
                    "terminated": torch.zeros(b, 1, 1, dtype=torch.bool),
                }
            },
        },
        batch_size=[b],
    )


@pytest.mark.parametrize("name", list(ENCODERS))
def test_critic_is_vmappable_over_parameter_copies(real_obs, name):
    """What TorchRL's losses do: vmap one critic over stacked parameters, expanded inputs."""
    from tensordict.nn import TensorDictModule  # noqa: F401 - TorchRL's module type

    torch.manual_seed(0)
    critic = Critic(make_encoder(name, **SMALL[name]))
    second = Critic(make_encoder(name, **SMALL[name]))
    params = {n: torch.stack((p, dict(second.named_parameters())[n])) for n, p in critic.named_parameters()}
    args = (*obs_args(real_obs), torch.rand(12, 1, 2))
    expanded = [x.expand(2, *x.shape) for x in args]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a batching-rule fallback would warn
        q = torch.vmap(lambda p, *x: torch.func.functional_call(critic, p, x))(params, *expanded)
    torch.testing.assert_close(q[0], critic(*args), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(q[1], second(*args), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("prepared", [False, True])
def test_td3loss_runs_with_the_modules(real_obs, prepared):
    from torchrl.objectives import SoftUpdate, TD3Loss

    torch.manual_seed(0)
    actor = Actor(make_encoder("gatedgcn", dim=16))
    critic = Critic(make_encoder("gatedgcn", dim=16))
    loss = TD3Loss(
        actor_module(actor, prepared=prepared),
        critic_module(critic, prepared=prepared),
        bounds=(-1.0, 1.0),
        num_qvalue_nets=2,
    )
    loss.set_keys(
        action=ACTION,
        state_action_value=("agents", "state_action_value"),
        reward=("agents", "reward"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
    )
    loss.make_value_estimator(gamma=0.99)
    SoftUpdate(loss, tau=0.005)
    batch = transition_batch(real_obs)
    if prepared:
        prepare_batch(batch, actor.encoder, critic.encoder)
        key = OBS + (actor.encoder.prep_key, "nbr")
        assert key in batch.keys(True) and ("next",) + key in batch.keys(True)
    out = loss(batch)
    (out["loss_actor"] + out["loss_qvalue"]).backward()
    assert all(torch.isfinite(out[k]) for k in ("loss_actor", "loss_qvalue"))
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.parameters())


@pytest.mark.parametrize("name", list(ENCODERS))
def test_prepared_modules_equal_raw_modules(real_obs, name):
    torch.manual_seed(0)
    actor = Actor(make_encoder(name, **SMALL[name]))
    critic = Critic(make_encoder(name, **SMALL[name]))
    batch = transition_batch(real_obs)
    raw = critic_module(critic)(actor_module(actor)(batch.clone()))
    prep = prepare_batch(batch.clone(), actor.encoder, critic.encoder)
    prep = critic_module(critic, prepared=True)(actor_module(actor, prepared=True)(prep))
    torch.testing.assert_close(prep.get(ACTION), raw.get(ACTION))
    key = ("agents", "state_action_value")
    torch.testing.assert_close(prep.get(key), raw.get(key))


# --------------------------------------------------------------------------- edge cases
@pytest.mark.parametrize("name", list(ENCODERS))
def test_no_humans_at_all(name):
    robot = torch.tensor([[[0.0, 0.0, 0.1, 0.0, 4.0, 0.0]]])
    humans, mask = torch.zeros(1, 1, 0, 4), torch.zeros(1, 1, 0, dtype=torch.bool)
    actor = Actor(make_encoder(name, **SMALL[name]))
    a = actor(robot, humans, mask)
    assert a.shape == (1, 1, 2) and torch.isfinite(a).all()


def test_folded_weight_cache_follows_parameter_updates(real_obs):
    """Without gradients the folded layer-1 weights are cached; in-place parameter updates
    (optimiser steps, load_state_dict) must invalidate the cache."""
    torch.manual_seed(0)
    enc = make_encoder("gatedgcn", dim=16)
    other = make_encoder("gatedgcn", dim=16)
    with torch.no_grad():
        before = enc(*obs_args(real_obs))[1]
        enc.load_state_dict(other.state_dict())
        after = enc(*obs_args(real_obs))[1]
        torch.testing.assert_close(after, other(*obs_args(real_obs))[1])
        assert not torch.allclose(before, after)
        for p in enc.parameters():
            p.mul_(0.5)
        cached = enc(*obs_args(real_obs))[1]
    torch.testing.assert_close(cached, enc(*obs_args(real_obs))[1])  # grad enabled: no cache


def test_traced_actor_matches_eager(real_obs):
    from crowdbench.models.heads import trace_for_inference

    torch.manual_seed(0)
    actor = Actor(make_encoder("gatedgcn", dim=16))
    one = [x[:1] for x in obs_args(real_obs)]
    traced = trace_for_inference(actor, *one)
    for i in range(1, 4):  # other observations of the same shape
        x = [t[i : i + 1] for t in obs_args(real_obs)]
        with torch.no_grad():
            torch.testing.assert_close(traced(*x), actor(*x))


class _MinimalEncoder(torch.nn.Module):
    """What a leaderboard submitter may write: only ``out_dim`` and ``forward``."""

    out_dim = 8

    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(6 + 4, 8)

    def forward(self, robot, humans, humans_mask):
        m = humans_mask.unsqueeze(-1).float()
        mean = (humans * m).sum(-2) / m.sum(-2).clamp_min(1.0)
        h = torch.relu(self.lin(torch.cat((robot, mean), -1)))
        return h.unsqueeze(-2), h


def test_heads_and_prepared_path_work_with_a_minimal_encoder(real_obs):
    actor, critic = Actor(_MinimalEncoder()), Critic(_MinimalEncoder())
    batch = transition_batch(real_obs)
    raw = critic_module(critic)(actor_module(actor)(batch.clone()))
    prep = prepare_batch(batch.clone(), actor.encoder, critic.encoder)
    prep = critic_module(critic, prepared=True)(actor_module(actor, prepared=True)(prep))
    torch.testing.assert_close(prep.get(ACTION), raw.get(ACTION))
    q = TwinCritic(critic)(*obs_args(real_obs), raw.get(ACTION))
    assert q.shape == (2, 12, 1, 1)


def test_radial_actor_stays_in_speed_disc_and_keeps_gradient():
    from crowdbench.models.heads import Actor

    enc = make_encoder("mlp", dim=8, hidden=[16])
    for squash, bound in (("radial", 1.0), ("box", 2**0.5)):
        actor = Actor(enc, [8], v_max=1.0, squash=squash)
        h = torch.randn(64, 8) * 100  # far into saturation
        h.requires_grad_(True)
        a = actor.act(h)
        assert a.norm(dim=-1).max() <= bound + 1e-5
        if squash == "radial":
            # the direction still responds to the input even when the speed saturates
            a[:, 1].sum().backward()
            assert h.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="unknown actor squash"):
        Actor(enc, squash="disk")


def test_lookahead_critic_geometry_and_gradient():
    """The lookahead critic = the paper's critic applied to the hand-predicted next observation."""
    from crowdbench.models.heads import Critic, lookahead

    robot = torch.tensor([[0.0, 0.0, 0.5, 0.0, 8.0, 0.0]])
    humans = torch.tensor([[[1.0, 0.0, -1.0, 0.0], [0.0, 2.0, 0.0, -2.0], [0.0, 0.0, 0.0, 0.0]]])
    mask = torch.tensor([[True, True, False]])
    action = torch.tensor([[0.96, 0.72]])  # speed 1.2, clipped as the simulator does to (0.8, 0.6)
    r2, h2, m2 = lookahead(robot, humans, mask, action, 0.25, 1.0)
    assert r2[0].tolist() == pytest.approx([0.0, 0.0, 0.8, 0.6, 8.0 - 0.2, -0.15])
    # human 0: x 1 - 0.25 (its motion) - 0.2 (the robot's); human 1: y 2 - 0.5 - 0.15; padding stays zero
    assert h2[0, :, :2].flatten().tolist() == pytest.approx([0.55, -0.15, -0.2, 1.35, 0.0, 0.0])
    assert torch.equal(h2[..., 2:], humans[..., 2:]) and torch.equal(m2, mask)
    torch.manual_seed(0)
    enc = make_encoder(name="gatedgcn", dim=16, layers=2, k=8)
    ahead, plain = Critic(enc, lookahead_dt=0.25), Critic(enc)
    plain.head = ahead.head
    a = torch.tensor([[0.3, -0.4]], requires_grad=True)
    q = ahead(robot, humans, mask, a)
    assert torch.allclose(q, plain(*lookahead(robot, humans, mask, a.detach(), 0.25, 1.0), a.detach()))
    (g,) = torch.autograd.grad(q.sum(), a)
    enc_only = torch.autograd.grad(plain(robot, humans, mask, a).sum(), a)[0]  # through the final MLP only
    assert not torch.allclose(g, enc_only)  # dQ/da also flows through the encoder's view of the scene
    with pytest.raises(ValueError, match="lookahead"):
        ahead.forward_prepared({}, a)
