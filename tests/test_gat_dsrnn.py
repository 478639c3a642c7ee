"""The encoders from the literature: GAT (crowdbench/models/gat.py) and DS-RNN-style spatial
attention (crowdbench/models/dsrnn.py) against Python-loop references, their attention weights,
and each one trained, evaluated, submitted and run by the leaderboard harness, and recorded by the
visualisation with its attention.

The generic encoder tests (permutation, far masked human, receptive field, gradients, vmapped
critics, heads, prepared modules) run on every registered encoder in tests/test_models.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml
from worlds import students_obs

from crowdbench.models import make_encoder


@pytest.fixture(scope="module")
def real_obs():
    """STUDENTS001 observations a few steps into episodes: [B=8, A=1, ...] (many humans, some isolated)."""
    return students_obs(8, 4)


def obs_args(o):
    return o["robot"], o["humans"], o["humans_mask"]


def gates_by_node(g, b):
    """{node id: weight} of the real slots of graph ``b`` in ``last_gates``."""
    return {int(n): float(v) for n, v, m in zip(g.nbr[b, 0], g.values[b, 0], g.mask[b, 0], strict=True) if m}


# --------------------------------------------------------------------------- GAT reference
def reference_gat(enc, robot, humans, mask):
    """The GAT update with loops over graphs, nodes, heads and edges, on an uncapped graph built
    from the rule (radius, goal -> robot). Returns the robot states and the robot's last-layer
    attention {node id: mean over heads} (ids: 0 robot, slot + 1 humans, M + 1 goal)."""
    m = humans.shape[1]
    out, att = [], []
    for b in range(robot.shape[0]):
        r = robot[b]
        ids = [0] + [i + 1 for i in range(m) if mask[b, i]] + [m + 1]
        pos = [r[0:2]] + [humans[b, i - 1, 0:2] for i in ids[1:-1]] + [r[4:6]]
        h = [enc.robot_emb(r)] + [enc.human_emb(humans[b, i - 1]) for i in ids[1:-1]]
        h.append(enc.goal_emb(torch.cat((torch.zeros(4), r[4:6]))))
        n_ag = len(ids) - 1  # robot and observed humans
        nbrs = {i: [j for j in range(n_ag) if j != i and float(((pos[j] - pos[i]) ** 2).sum()) <= 5.0]
                for i in range(n_ag)}
        nbrs[0].append(n_ag)  # goal -> robot
        nbrs[n_ag] = []  # the goal receives nothing
        for layer in enc.layers:
            n_h, c = layer.heads, layer.out
            new_h, robot_alpha = [], {}
            for i in range(n_ag + 1):
                heads = []
                for k in range(n_h):
                    w = layer.W.weight[k * c : (k + 1) * c]
                    if not nbrs[i]:
                        heads.append(torch.zeros(c))
                        continue
                    scores = []
                    for j in nbrs[i]:
                        s = layer.att["dst"][k] @ (w @ h[i]) + layer.att["src"][k] @ (w @ h[j])
                        if "edge" in layer.att:
                            s = s + layer.att["edge"][k] @ (pos[j] - pos[i])
                        s = F.leaky_relu(s, layer.slope)
                        scores.append(s if layer.score_cap is None else layer.score_cap * torch.tanh(s / layer.score_cap))
                    alpha = torch.softmax(torch.stack(scores), 0)
                    heads.append(sum(a * (w @ h[j]) for a, j in zip(alpha, nbrs[i], strict=True)))
                    if i == 0:
                        for a, j in zip(alpha, nbrs[i], strict=True):
                            robot_alpha[ids[j]] = robot_alpha.get(ids[j], 0.0) + float(a) / n_h
                agg = torch.cat(heads) if layer.concat else torch.stack(heads).mean(0)
                new_h.append(h[i] + F.elu(layer.U(h[i]) + agg))
            h = new_h
        out.append(h[0])
        att.append(robot_alpha)
    return torch.stack(out), att


@pytest.mark.parametrize("rf", [True, False])
@pytest.mark.parametrize("cfg", [{}, {"heads": 2, "out_heads": 3}, {"edge_features": False, "layers": 1},
                                 {"score_cap": 0.5}], ids=["preset", "heads", "no-edges-1-layer", "capped"])
def test_gat_matches_loop_reference(real_obs, rf, cfg):
    torch.manual_seed(1)
    enc = make_encoder("gat", dim=8, k=64, receptive_field=rf, **cfg)  # K never binds
    robot, humans, mask = (x[:, 0] for x in obs_args(real_obs))
    with torch.no_grad():
        _, got = enc(robot, humans, mask)
        want, att = reference_gat(enc, robot, humans, mask)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    g = enc.last_gates
    for b in range(robot.shape[0]):
        real = {int(n): float(v) for n, v, m in zip(g.nbr[b], g.values[b], g.mask[b], strict=True) if m}
        assert real.keys() == att[b].keys()
        for n, v in att[b].items():
            assert real[n] == pytest.approx(v, abs=1e-5)


def test_gat_attention_sums_to_one_over_real_edges_and_is_zero_on_padding(real_obs):
    torch.manual_seed(0)
    enc = make_encoder("gat", dim=16, receptive_field=False)
    g = enc.build_graph(*obs_args(real_obs))
    alphas = []
    with torch.no_grad():
        enc.encode(g, gates_out=alphas)
    _, mask, _ = g.slots()
    has = mask.any(-1)
    assert len(alphas) == 2 and (~has).any()  # some nodes have no incoming edge
    for alpha, heads in zip(alphas, (4, 1), strict=True):  # [B*, N-1, K+1, heads]
        assert alpha.shape[-1] == heads
        assert (alpha[~mask] == 0).all()
        total = alpha.sum(2)
        torch.testing.assert_close(total[has], torch.ones_like(total[has]), atol=1e-6, rtol=0)
        assert (total[~has] == 0).all()
    lg = enc.last_gates
    assert lg.values.shape == (8, 1, 9) and lg.full.shape == (8, 1, 9, 1)
    assert (lg.nbr[..., 0] == real_obs["humans"].shape[-2] + 1).all() and lg.mask[..., 0].all()  # goal slot
    assert (lg.values[~lg.mask] == 0).all()
    torch.testing.assert_close(lg.values.sum(-1), torch.ones(8, 1), atol=1e-6, rtol=0)


# --------------------------------------------------------------------------- DS-RNN reference
def reference_dsrnn(enc, robot, humans, mask):
    """The DS-RNN-style forward with loops over graphs and humans; returns robot states and the
    attention {node id: weight}."""
    out, att = [], []
    for b in range(robot.shape[0]):
        r = robot[b]
        t = enc.temporal(r[2:4])
        seen = [i for i in range(humans.shape[1]) if mask[b, i]]
        s, logits = [], []
        for i in seen:
            x = humans[b, i, 0:2] - r[0:2]
            if enc.spatial_velocity:
                x = torch.cat((x, humans[b, i, 2:4] - r[2:4]))
            s.append(enc.spatial(x))
            z = enc.query(t) @ enc.key(s[-1]) / math.sqrt(enc.attn_dim)
            logits.append(z if enc.score_cap is None else enc.score_cap * torch.tanh(z / enc.score_cap))
        if seen:
            alpha = torch.softmax(torch.stack(logits), 0)
            a = sum(w * sj for w, sj in zip(alpha, s, strict=True))
            att.append({i + 1: float(w) for i, w in zip(seen, alpha, strict=True)})
        else:
            a = torch.zeros_like(t)
            att.append({})
        edges = torch.relu(enc.edge_emb(torch.cat((t, a))))
        out.append(torch.relu(enc.node_out(torch.cat((torch.relu(enc.node_emb(r)), edges)))))
    return torch.stack(out), att


@pytest.mark.parametrize("velocity,cap", [(True, None), (False, None), (True, 0.3)])
def test_dsrnn_matches_loop_reference(real_obs, velocity, cap):
    torch.manual_seed(2)
    enc = make_encoder("dsrnn", dim=8, embed=12, attn_dim=6, spatial_velocity=velocity, score_cap=cap)
    robot, humans, mask = (x[:, 0] for x in obs_args(real_obs))
    mask = mask.clone()
    mask[0] = False  # a robot that observes nobody
    with torch.no_grad():
        _, got = enc(robot, humans, mask)
        want, att = reference_dsrnn(enc, robot, humans, mask)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    g = enc.last_gates
    assert g.values.shape == g.nbr.shape == g.mask.shape == mask.shape and (g.values[0] == 0).all()
    for b in range(robot.shape[0]):
        real = {int(n): float(v) for n, v, m in zip(g.nbr[b], g.values[b], g.mask[b], strict=True) if m}
        assert real.keys() == att[b].keys()
        for n, v in att[b].items():
            assert real[n] == pytest.approx(v, abs=1e-6)


def test_dsrnn_attention_sums_to_one_over_observed_humans_and_is_zero_on_padding(real_obs):
    torch.manual_seed(0)
    enc = make_encoder("dsrnn", dim=16)
    robot, humans, mask = obs_args(real_obs)
    humans = humans.clone()
    humans[~mask] = 1e3  # garbage in unobserved slots must not matter
    with torch.no_grad():
        enc(robot, humans, mask)
    g = enc.last_gates
    assert g.values.shape == mask.shape and mask.any(-1).all()
    assert (g.values[~mask] == 0).all() and (g.values[mask] > 0).all()
    torch.testing.assert_close(g.values.sum(-1), torch.ones(8, 1), atol=1e-6, rtol=0)
    assert torch.equal(g.nbr[0, 0], torch.arange(1, mask.shape[-1] + 1))


@pytest.mark.parametrize("name", ["gat", "dsrnn"])
def test_attention_follows_permuted_humans(real_obs, name):
    """Permuting the human slots leaves the robot output unchanged and permutes the attention with them."""
    torch.manual_seed(0)
    enc = make_encoder(name, dim=16)
    robot, humans, mask = obs_args(real_obs)
    m = humans.shape[-2]
    perm = torch.randperm(m)
    with torch.no_grad():
        _, a = enc(robot, humans, mask)
        g1 = enc.last_gates
        _, b = enc(robot, humans[..., perm, :], mask[..., perm])
        g2 = enc.last_gates
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    to_old = {int(new) + 1: int(old) + 1 for new, old in enumerate(perm)} | {m + 1: m + 1}  # goal id kept
    for i in range(robot.shape[0]):
        w1, w2 = gates_by_node(g1, i), gates_by_node(g2, i)
        assert {to_old[n] for n in w2} == set(w1)
        for n, v in w2.items():
            assert v == pytest.approx(w1[to_old[n]], abs=1e-6)


# --------------------------------------------------------------------------- end to end
RUN = ["train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8",
       "train.probe_every=1000000", "train.checkpoint_every=1000000", "train.utd=0.25", "env.batch=8",
       "algo.batch_size=16"]
EVAL = ["eval.episodes=2", "eval.scenes=[hotel]"]


@pytest.mark.parametrize("name, label", [("gat", "GAT (TD3, gat)"), ("dsrnn", "DS-RNN attention (TD3, dsrnn)")])
@pytest.mark.slow
def test_trains_evaluates_submits_and_the_harness_runs_it(tmp_path, name, label, monkeypatch):
    from crowdbench.algos.checkpoint import load_checkpoint
    from crowdbench.cli import main
    from crowdbench.leaderboard import run

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "run"
    assert main(["run", f"method={name}_td3", *RUN, *EVAL, f"out={out}"]) == 0
    state = load_checkpoint(out / "checkpoint.pt")
    assert state["frames"] == 256 and state["config"]["encoder"]["name"] == name
    assert main(["eval", f"policy={out}/checkpoint.pt", *EVAL, f"out={tmp_path / 'eval'}"]) == 0
    lb = tmp_path / "lb"
    assert main(["submit", str(out), "--name", f"{name}_tiny", "--root", str(lb)]) == 0
    sub = yaml.safe_load((lb / "submissions" / f"{name}_tiny" / "submission.yaml").read_text())
    assert sub["encoder"] == name and sub["entry"] == label and sub["kind"] == "learned"
    log: list[str] = []
    assert run(lb, episodes=2, scenes=["hotel"], tracks=["v1"], log=log.append) == 0, log
    assert f"| {label} |" in (lb / "README.md").read_text()


@pytest.mark.parametrize("name", ["gat", "dsrnn"])
def test_recorded_attention_equals_the_encoders_weights(tmp_path, name):
    """The rerun recording (crowdbench/viz/record.py) draws these encoders' attention as it draws gates."""
    from crowdbench.algos.actors import build_actor
    from crowdbench.algos.checkpoint import LearnedPolicy
    from crowdbench.cli import compose
    from crowdbench.protocols.replay import evaluate
    from crowdbench.viz.record import make_recorder_factory, read_recording

    torch.manual_seed(0)
    actor = build_actor("td3", {"name": name, "dim": 16}, 1.0)
    policy, seen = LearnedPolicy(actor, name=f"tiny-{name}"), []
    act = policy.act
    policy.act = lambda td: (seen.append(td.clone()), act(td))[1]
    cfg = compose(["viz.record=true", "viz.episodes=[0]", "eval.episodes=1", "eval.scenes=[students003]"])
    factory = make_recorder_factory(policy, cfg, tmp_path, ["students003"])
    evaluate(policy, ["students003"], 1, out_dir=tmp_path, recorder_factory=factory)
    att = [r for r in read_recording(tmp_path / "recordings" / "students003_ep000.rrd")["world/attention"]
           if "gate" in r]
    enc = actor.module.encoder
    assert len(att) > 10
    for r in att:
        with torch.no_grad():
            enc(seen[r["step"]])
        g = enc.last_gates
        real = g.mask[0, 0]
        assert r["node"] == g.nbr[0, 0][real].tolist()
        assert np.allclose(r["gate"], g.values[0, 0][real].double().numpy(), atol=1e-6)
        assert not r["gate"] or abs(sum(r["gate"]) - 1.0) < 1e-5
