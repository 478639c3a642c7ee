"""The literature encoders SARL, LSTM-RL and RGL (crowdbench/models/sarl.py, lstm_rl.py, rgl.py): loop
references, masking, attention weights, LSTM-RL's distance order, training, evaluation and submission."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml
from worlds import students_obs

from crowdbench.cli import main
from crowdbench.leaderboard import run as leaderboard_run
from crowdbench.models import make_encoder
from crowdbench.models.lstm_rl import sorted_sequence
from crowdbench.viz.record import find_encoder

NAMES = ("sarl", "lstm_rl", "rgl")
SMALL = {"sarl": {"dim": 8, "embed": [16, 8], "interact": [8], "attention": [8], "hidden": [8]},
         "lstm_rl": {"dim": 8, "hidden_size": 8, "hidden": [8]}, "rgl": {"dim": 8, "embed": [16]}}


@pytest.fixture(scope="module")
def obs():
    """Real STUDENTS001 observations a few steps into episodes, ``[B=8, 6]`` etc. (agent axis dropped)."""
    torch.manual_seed(0)
    o = students_obs(8, 4)
    robot, humans, mask = o["robot"][:, 0], o["humans"][:, 0], o["humans_mask"][:, 0].clone()
    mask[0] = False  # one robot without observed humans
    assert mask.sum(-1).max() >= 3
    return robot, humans, mask


def observed(humans, mask, b):
    return [humans[b, i] for i in range(humans.shape[1]) if mask[b, i]]


# --------------------------------------------------------------------------- loop references
def ref_sarl(enc, robot, humans, mask):
    out, weights = [], []
    for b in range(robot.shape[0]):
        s = robot[b]
        hs = observed(humans, mask, b)
        e = [enc.phi_e(torch.cat((s, w, (w[:2] - s[:2]).norm().reshape(1)))) for w in hs]
        c = torch.zeros(enc.psi_h[-1].out_features)
        alpha = []
        if e:
            e_m = sum(e) / len(e)
            z = torch.cat([enc.psi_a(torch.cat((ei, e_m))) for ei in e])
            alpha = torch.softmax(z if enc.score_cap is None else enc.score_cap * torch.tanh(z / enc.score_cap), 0)
            c = sum(a * enc.psi_h(ei) for a, ei in zip(alpha, e, strict=True))
        out.append(enc.f_v(torch.cat((s, c))))
        weights.append(alpha)
    return torch.stack(out), weights


def lstm_cell(enc) -> torch.nn.LSTMCell:
    cell = torch.nn.LSTMCell(5, enc.hidden_size)
    for a in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
        setattr(cell, a, getattr(enc.lstm, f"{a}_l0"))
    return cell


def ref_lstm(enc, robot, humans, mask, order=None):
    """``order(s, humans) -> humans`` in feeding order (default: decreasing distance)."""
    cell, out = lstm_cell(enc), []
    for b in range(robot.shape[0]):
        s = robot[b]
        hs = observed(humans, mask, b)
        hs = sorted(hs, key=lambda w, s=s: float((w[:2] - s[:2]).norm()), reverse=True) if order is None else order(hs)
        h = c = torch.zeros(enc.hidden_size)
        for w in hs:
            rel = w[:2] - s[:2]
            h, c = cell(torch.cat((rel, w[2:], rel.norm().reshape(1))), (h, c))
        out.append(enc.fc(torch.cat((s, h))))
    return torch.stack(out)


def ref_rgl(enc, robot, humans, mask):
    out, rows = [], []
    for b in range(robot.shape[0]):
        x = [enc.w_r(robot[b])] + [enc.w_h(w) for w in observed(humans, mask, b)]
        n = len(x)
        q, k = [enc.w_theta(v) for v in x], [enc.w_phi(v) for v in x]
        if enc.similarity == "cosine":
            sim = [[enc.scale * float(q[i] @ k[j] / (q[i].norm() * k[j].norm())) for j in range(n)] for i in range(n)]
        else:
            sim = [[float(q[i] @ k[j]) for j in range(n)] for i in range(n)]
        a = [[math.exp(v - max(r)) / sum(math.exp(u - max(r)) for u in r) for v in r] for r in sim]
        h = x
        for w in enc.gcn:
            h = [torch.relu(w(sum(a[i][j] * h[j] for j in range(n)))) + h[i] for i in range(n)]
        out.append(h[0])
        rows.append(a[0])
    return torch.stack(out), rows


@pytest.mark.parametrize("name", NAMES)
def test_batched_forward_equals_loop_reference(obs, name):
    torch.manual_seed(3)
    enc = make_encoder(name, **SMALL[name])
    ref = {"sarl": lambda *o: ref_sarl(enc, *o)[0], "lstm_rl": lambda *o: ref_lstm(enc, *o),
           "rgl": lambda *o: ref_rgl(enc, *o)[0]}[name]
    with torch.no_grad():
        _, got = enc(*obs)
        want = ref(*obs)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_rgl_embedded_gaussian_equals_loop_reference(obs):
    """The paper's bilinear similarity (the first leaderboard row's) against the same loop."""
    torch.manual_seed(3)
    enc = make_encoder("rgl", **SMALL["rgl"], similarity="embedded_gaussian")
    with torch.no_grad():
        _, got = enc(*obs)
        want = ref_rgl(enc, *obs)[0]
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def weight_spread(w, valid, dim=-1):
    """Largest / smallest weight and the largest weight over the ``valid`` entries along ``dim``."""
    top = w.where(valid, 0.0).amax(dim)
    return top / w.where(valid, math.inf).amin(dim), top


def test_rgl_cosine_logits_stay_bounded_where_the_bilinear_ones_saturate(obs):
    """Grown similarity weights (what TD3's critic did to RGL) make the bilinear softmax one-hot; the
    cosine's weights keep a ratio of at most e^(2 scale) between any two observed nodes."""
    robot, humans, mask = obs
    rows = {}
    for sim in ("cosine", "embedded_gaussian"):
        torch.manual_seed(5)
        enc = make_encoder("rgl", **SMALL["rgl"], similarity=sim, scale=2.0)
        with torch.no_grad():
            for w in (enc.w_theta, enc.w_phi):
                w.weight.mul_(30.0)
            enc(robot, humans, mask)
        rows[sim] = enc.last_adjacency
    valid = torch.cat((torch.ones_like(mask[:, :1]), mask), 1)
    many = valid.sum(-1) >= 3
    ratio, top = weight_spread(rows["cosine"], valid)
    assert (ratio[many] <= math.exp(4.0) * (1 + 1e-5)).all()
    _, top = weight_spread(rows["embedded_gaussian"], valid)
    assert (top[many] > 0.999).any()  # one-hot rows: the saturation the cosine rules out


def test_sarl_capped_scores_equal_loop_reference(obs):
    torch.manual_seed(3)
    enc = make_encoder("sarl", **SMALL["sarl"], score_cap=0.2)
    with torch.no_grad():
        _, got = enc(*obs)
        want = ref_sarl(enc, *obs)[0]
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["sarl", "gat", "dsrnn"])
def test_capped_attention_stays_bounded_where_the_unbounded_saturates(obs, name):
    """Score weights grown 100x (the critics' drift) make the papers' softmax one-hot; with ``score_cap=c``
    any two attended weights differ by at most e^(2c)."""
    robot, humans, mask = obs
    small = {"sarl": SMALL["sarl"], "gat": {"dim": 8, "k": 64}, "dsrnn": {"dim": 8, "embed": 8, "attn_dim": 8}}[name]
    rows = {}
    for cap in (None, 1.5):
        torch.manual_seed(6)
        enc = make_encoder(name, **small, score_cap=cap)
        with torch.no_grad():
            for n, p in enc.named_parameters():
                if any(k in n for k in ("psi_a", "att.", "query", "key")):
                    p.mul_(100.0)
            enc(robot, humans, mask)
        g = enc.last_gates
        rows[cap] = (g.full, g.mask)
    many = rows[1.5][1].sum(-1) >= 3
    ratio, _ = weight_spread(rows[1.5][0], rows[1.5][1].unsqueeze(-1), dim=1)
    assert (ratio[many] <= math.exp(3.0) * (1 + 1e-5)).all()
    _, top = weight_spread(rows[None][0], rows[None][1].unsqueeze(-1), dim=1)
    assert (top[many] > 0.999).any()


def test_rgl_refuses_an_unknown_similarity():
    with pytest.raises(ValueError, match="encoder.similarity: 'dot' is not one of cosine, embedded_gaussian"):
        make_encoder("rgl", similarity="dot")


def test_lstm_rl_vmap_path_equals_nn_lstm(obs):
    """Under torch.func the LSTM runs as a cell loop on the module's weights: same output as nn.LSTM."""
    torch.manual_seed(4)
    enc = make_encoder("lstm_rl", **SMALL["lstm_rl"])
    other = make_encoder("lstm_rl", **SMALL["lstm_rl"])
    params = {k: torch.stack((v, dict(other.named_parameters())[k])) for k, v in enc.named_parameters()}
    with torch.no_grad():
        _, looped = torch.vmap(lambda p: torch.func.functional_call(enc, p, obs))(params)
        torch.testing.assert_close(looped[0], enc(*obs)[1], atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(looped[1], other(*obs)[1], atol=1e-6, rtol=1e-6)


# --------------------------------------------------------------------------- invariances, masking
@pytest.mark.parametrize("name", NAMES)
def test_permuting_human_slots_changes_nothing(obs, name):
    torch.manual_seed(5)
    enc = make_encoder(name, **SMALL[name])
    robot, humans, mask = obs
    perm = torch.randperm(humans.shape[1])
    with torch.no_grad():
        hn, a = enc(robot, humans, mask)
        hn2, b = enc(robot, humans[:, perm], mask[:, perm])
    torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    if name == "rgl":  # node states are permuted with the slots (node 0 = robot)
        torch.testing.assert_close(hn2[:, 1:], hn[:, 1:][:, perm], atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_masked_far_human_changes_nothing(obs, name):
    torch.manual_seed(6)
    enc = make_encoder(name, **SMALL[name])
    robot, humans, mask = obs
    far = torch.tensor([40.0, -30.0, 1.0, 1.0]).expand(humans.shape[0], 1, 4)
    with torch.no_grad():
        _, a = enc(robot, humans, mask)
        _, b = enc(robot, torch.cat((humans[:, :2], far, humans[:, 2:]), 1),
                   torch.cat((mask[:, :2], torch.zeros_like(mask[:, :1]), mask[:, 2:]), 1))
    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_sarl_attention_sums_to_one_over_observed_and_is_zero_elsewhere(obs):
    torch.manual_seed(7)
    enc = make_encoder("sarl", **SMALL["sarl"])
    robot, humans, mask = obs
    assert enc.last_gates is None
    with torch.no_grad():
        enc(robot, humans, mask)
        _, ref_w = ref_sarl(enc, robot, humans, mask)
    g = enc.last_gates
    m = mask.shape[1]
    assert g.values.shape == g.nbr.shape == g.mask.shape == (8, m + 1) and g.full.shape == (8, m + 1, 1)
    assert torch.equal(g.mask[:, 1:], mask) and not g.mask[:, 0].any()
    assert (g.nbr[:, 0] == m + 1).all() and torch.equal(g.nbr[0, 1:], torch.arange(1, m + 1))
    assert (g.values[~g.mask] == 0).all()  # exactly zero on padding, unobserved slots and the goal slot
    has = mask.any(-1)
    torch.testing.assert_close(g.values.sum(-1)[has], torch.ones(int(has.sum())), atol=1e-6, rtol=0)
    assert (g.values[~has] == 0).all()  # no observed human: no attention at all
    for b in range(8):
        torch.testing.assert_close(g.values[b][g.mask[b]], torch.as_tensor(ref_w[b]).reshape(-1), atol=1e-6, rtol=0)


def test_rgl_adjacency_row_sums_to_one_over_observed_nodes_and_is_zero_elsewhere(obs):
    torch.manual_seed(8)
    enc = make_encoder("rgl", **SMALL["rgl"])
    robot, humans, mask = obs
    with torch.no_grad():
        enc(robot, humans, mask)
        _, rows = ref_rgl(enc, robot, humans, mask)
    row = enc.last_adjacency  # [B, M + 1], robot first
    valid = torch.cat((torch.ones_like(mask[:, :1]), mask), 1)
    assert (row[~valid] == 0).all()
    torch.testing.assert_close(row.sum(-1), torch.ones(8), atol=1e-6, rtol=0)
    for b in range(8):
        torch.testing.assert_close(row[b][valid[b]], torch.tensor(rows[b]), atol=1e-6, rtol=0)
    assert row[0, 0] == 1.0  # alone: the robot attends to itself
    g = enc.last_gates  # the human entries, for the recordings
    torch.testing.assert_close(g.values[:, 1:], row[:, 1:])
    assert torch.equal(g.mask[:, 1:], mask) and not g.mask[:, 0].any()
    # as a source, a masked node gets no weight in any row; as a target its row is zero
    a = enc.adjacency(torch.randn(8, mask.shape[1] + 1, 8), valid)
    assert (a[~valid] == 0).all() and (a.transpose(1, 2)[~valid] == 0).all()


def test_sarl_and_rgl_are_visualisable_like_the_gated_encoders(obs):
    from crowdbench.models.heads import Actor

    for name in ("sarl", "rgl"):
        actor = Actor(make_encoder(name, **SMALL[name]))
        policy = type("P", (), {"actor": actor})()
        assert find_encoder(policy) is actor.encoder
    assert find_encoder(type("P", (), {"actor": Actor(make_encoder("lstm_rl", **SMALL["lstm_rl"]))})()) is None


# --------------------------------------------------------------------------- LSTM-RL's distance order
def two_humans(near_vel=(0.5, 0.0), far_vel=(-0.5, 0.3)):
    robot = torch.tensor([[0.0, 0.0, 0.2, 0.0, 4.0, 0.0]])
    humans = torch.tensor([[[1.0, 0.5, *near_vel], [3.0, -1.0, *far_vel], [0.0, 0.0, 0.0, 0.0]]])
    return robot, humans, torch.tensor([[True, True, False]])


def test_lstm_rl_feeds_the_closest_human_last():
    torch.manual_seed(9)
    enc = make_encoder("lstm_rl", **SMALL["lstm_rl"])
    robot, humans, mask = two_humans()
    seq, n = sorted_sequence(robot, humans, mask)
    assert n.tolist() == [2]
    assert seq[0, 0, :2].tolist() == [3.0, -1.0] and seq[0, 1, :2].tolist() == [1.0, 0.5]  # far, then near
    assert (seq[0, 2] == 0).all()  # padding after the observed humans
    with torch.no_grad():
        _, h = enc(robot, humans, mask)
        far_first = ref_lstm(enc, robot, humans, mask, order=lambda hs: [hs[1], hs[0]])
        near_first = ref_lstm(enc, robot, humans, mask, order=lambda hs: [hs[0], hs[1]])
    torch.testing.assert_close(h, far_first, atol=1e-6, rtol=0)
    assert (h - near_first).abs().max() > 1e-4


def test_lstm_rl_depends_on_distance_order_not_on_slots():
    torch.manual_seed(10)
    enc = make_encoder("lstm_rl", **SMALL["lstm_rl"])
    robot, humans, mask = two_humans()
    swapped_slots = humans[:, [1, 0, 2]]
    moved = humans.clone()  # the two humans swap places (each keeps its velocity): distance order reversed
    moved[0, 0, :2], moved[0, 1, :2] = humans[0, 1, :2], humans[0, 0, :2]
    with torch.no_grad():
        _, a = enc(robot, humans, mask)
        _, b = enc(robot, swapped_slots, mask)
        _, c = enc(robot, moved, mask)
        seq, _ = sorted_sequence(robot, moved, mask)
    assert torch.equal(a, b)
    assert (a - c).abs().max() > 1e-4
    assert seq[0, 1, 2:4].tolist() == [-0.5, 0.30000001192092896]  # the far-velocity human is now the nearest


def test_lstm_rl_without_observed_humans_reads_the_initial_state():
    enc = make_encoder("lstm_rl", **SMALL["lstm_rl"])
    robot, humans, _ = two_humans()
    with torch.no_grad():
        _, a = enc(robot, humans, torch.zeros(1, 3, dtype=torch.bool))
        _, b = enc(robot, humans[:, :0], torch.zeros(1, 0, dtype=torch.bool))
        want = enc.fc(torch.cat((robot, torch.zeros(1, enc.hidden_size)), -1))
    torch.testing.assert_close(a, want, atol=0, rtol=0)
    torch.testing.assert_close(b, want, atol=0, rtol=0)


# --------------------------------------------------------------------------- end to end
RUN = ["train.pretrain=null", "train.total_frames=256", "train.frames_per_batch=128", "algo.warmup=128", "encoder.dim=8",
       "train.probe_every=1000000", "train.checkpoint_every=1000000", "train.utd=0.25", "eval.episodes=2",
       "eval.scenes=[hotel]"]


@pytest.mark.slow
def test_each_trains_evaluates_and_submits(tmp_path):
    root = tmp_path / "lb"
    entries = {}
    for name in NAMES:
        run_dir = tmp_path / name
        assert main(["run", f"method={name}_td3", *RUN, f"out={run_dir}"]) == 0
        assert (run_dir / "checkpoint.pt").is_file()
        assert main(["eval", f"policy={run_dir / 'checkpoint.pt'}", "eval.episodes=2", "eval.scenes=[hotel]",
                     f"out={tmp_path / ('eval_' + name)}"]) == 0
        assert main(["submit", str(run_dir), "--name", f"{name}_tiny", "--root", str(root)]) == 0
        sub = yaml.safe_load((root / "submissions" / f"{name}_tiny" / "submission.yaml").read_text())
        assert sub["encoder"] == name and sub["algo"] == "td3"
        entries[name] = sub["entry"]
    assert entries == {"sarl": "SARL (TD3, sarl)", "lstm_rl": "LSTM-RL (TD3, lstm_rl)", "rgl": "RGL (TD3, rgl)"}
    assert leaderboard_run(root, episodes=2, scenes=["hotel"], tracks=["v1"]) == 0  # learned: in a worker process
    board = (root / "README.md").read_text()
    for entry in entries.values():
        assert f"| {entry} |" in board


def test_sarl_attention_is_drawn_in_the_recording(tmp_path):
    """The rerun recording of a SARL policy holds, per step, one attention line per observed human
    (node = slot + 1) with the attention weight of the policy call that chose the step's action."""
    from crowdbench.algos.actors import build_actor
    from crowdbench.algos.checkpoint import LearnedPolicy
    from crowdbench.cli import compose
    from crowdbench.protocols.replay import evaluate
    from crowdbench.viz.record import make_recorder_factory, read_recording

    torch.manual_seed(0)
    actor = build_actor("td3", {"name": "sarl", **SMALL["sarl"]}, 1.0)
    policy = LearnedPolicy(actor, name="tiny-sarl")
    seen = []
    act = policy.act
    policy.act = lambda td: (seen.append(td.clone()), act(td))[1]
    cfg = compose(["viz.record=true", "viz.episodes=[0]", "eval.episodes=1", "eval.scenes=[students003]"])
    evaluate(policy, ["students003"], 1, out_dir=tmp_path,
             recorder_factory=make_recorder_factory(policy, cfg, tmp_path, ["students003"]))
    att = [r for r in read_recording(tmp_path / "recordings" / "students003_ep000.rrd")["world/attention"]
           if "gate" in r]
    enc = actor.module.encoder
    assert att and sum(len(r["gate"]) >= 2 for r in att) > 0
    for r in att:
        o = seen[r["step"]]["agents", "observation"]
        with torch.no_grad():
            enc(o)
        g = enc.last_gates
        mask = o["humans_mask"][0, 0]
        assert r["node"] == (torch.nonzero(mask).flatten() + 1).tolist()
        assert np.allclose(r["gate"], g.values[0, 0][g.mask[0, 0]].double().numpy(), atol=1e-6)
        assert abs(sum(r["gate"]) - 1.0) < 1e-5
