"""crowdbench/models/vmap_once.py: parameter-free preprocessing run once under TorchRL's vmapped
critics, and the LSTM-RL cell loop that TorchRL's critics run (crowdbench/models/lstm_rl.py)."""

from __future__ import annotations

import pytest
import torch
from torch._C import _functorch as _ft
from worlds import SMALL_ENCODERS, students_obs

from crowdbench.models import ENCODERS, make_encoder
from crowdbench.models.heads import Critic
from crowdbench.models.lstm_rl import sorted_sequence
from crowdbench.models.vmap_once import batch_max, once

SMALL = SMALL_ENCODERS


@pytest.fixture(scope="module")
def real_obs():
    """Real STUDENTS001 observations ``[B=12, A=1, ...]`` and actions."""
    torch.manual_seed(0)
    o = students_obs(12, 6)
    return o["robot"], o["humans"], o["humans_mask"], 0.8 * torch.rand(12, 1, 2) - 0.4


def twin(name, lookahead_dt):
    torch.manual_seed(1)
    critic = Critic(make_encoder(name, **SMALL[name]), lookahead_dt=lookahead_dt)
    second = Critic(make_encoder(name, **SMALL[name]), lookahead_dt=lookahead_dt)
    params = {n: torch.stack((p, dict(second.named_parameters())[n])).detach().requires_grad_()
              for n, p in critic.named_parameters()}
    return critic, second, params


def vmapped(critic, params, args, shared: bool):
    """``Q [2, *]`` as TorchRL's losses compute it: one critic vmapped over ``params`` on inputs
    expanded to ``[2, *]``; ``shared=False`` materialises the copies (the ordinary vmapped path)."""
    expanded = [x.expand(2, *x.shape) if shared else x.expand(2, *x.shape).clone() for x in args]
    return torch.vmap(lambda p, *x: torch.func.functional_call(critic, p, x))(params, *expanded)


def test_once_runs_plain_on_shared_copies_and_falls_back_otherwise():
    seen = []

    def fn(x, y):
        seen.append(_ft.is_functorch_wrapped_tensor(x))
        return {"s": x * y + 1.0, "n": (x > 0).sum(-1)}

    x, y = torch.randn(5, 3), torch.randn(5, 3)
    want = fn(x, y)
    for shared in (True, False):
        seen.clear()
        xs = x.expand(2, 5, 3) if shared else x.expand(2, 5, 3).clone()
        got = torch.vmap(lambda a, b: once(fn, a, b), in_dims=(0, None))(xs, y)
        assert seen == [not shared]
        for k in want:
            assert torch.equal(got[k][0], want[k]) and torch.equal(got[k][1], want[k])
    assert once(fn, x, y)["s"].equal(want["s"])  # no transform: a plain call


@pytest.mark.parametrize("name", sorted(ENCODERS))
def test_lookahead_critic_under_vmap_equals_plain_critics(real_obs, name):
    """The shared preprocessing gives each copy what its own critic computes on its own."""
    critic, second, params = twin(name, 0.25)
    with torch.no_grad():
        q = vmapped(critic, params, real_obs, shared=True)
        torch.testing.assert_close(q[0], critic(*real_obs), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(q[1], second(*real_obs), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["gatedgcn", "lstm_rl", "sarl", "gat"])
@pytest.mark.parametrize("term", ["td3_actor", "sac_actor", "critic"])
def test_shared_preprocessing_is_bitwise_the_vmapped_path(real_obs, name, term):
    """Values and gradients (parameters, action) equal the ordinary vmapped path's bit for bit for
    the losses' terms: TD3's actor term reads copy 0, SAC's min over the copies, the critic term
    regresses both on a target (the action carries no gradient there)."""
    critic, _, params = twin(name, 0.25)
    robot, humans, mask, action = real_obs
    results = []
    for shared in (True, False):
        a = action.clone().requires_grad_(term != "critic")
        q = vmapped(critic, params, (robot, humans, mask, a), shared)
        loss = {"td3_actor": -q[0].mean(), "sac_actor": -q.min(0).values.mean(),
                "critic": (q - 0.3).pow(2).sum(0).mean()}[term]
        grads = torch.autograd.grad(loss, [*params.values(), *([a] if a.requires_grad else [])])
        results.append((q.detach(), grads))
    (q1, g1), (q2, g2) = results
    assert torch.equal(q1, q2)
    assert all(torch.equal(u, v) for u, v in zip(g1, g2, strict=True))


def test_lstm_cell_loop_equals_nn_lstm_with_gradients(real_obs):
    """The loop stops at the batch's last observed step; output and gradients as nn.LSTM's."""
    torch.manual_seed(2)
    enc = make_encoder("lstm_rl", **SMALL["lstm_rl"])
    robot, humans, mask = (t[:, 0] for t in real_obs[:3])
    mask = mask.clone()
    mask[0] = False  # a row without observed humans
    seq, n = sorted_sequence(robot, humans, mask.bool())
    assert 0 < batch_max(n) < seq.shape[1]  # the loop is cut short
    params = {"enc." + k: v.detach().unsqueeze(0).requires_grad_() for k, v in enc.named_parameters()}
    looped = torch.vmap(lambda p: torch.func.functional_call(_Encode(enc), p, (robot, seq, n)))(params)[0]
    plain = enc.encode(robot, seq, n)
    torch.testing.assert_close(looped, plain, atol=1e-6, rtol=1e-6)
    g_loop = torch.autograd.grad(looped.square().sum(), list(params.values()))
    g_plain = torch.autograd.grad(plain.square().sum(), list(enc.parameters()))
    for u, v in zip(g_loop, g_plain, strict=True):
        torch.testing.assert_close(u[0], v, atol=1e-5, rtol=1e-5)


class _Encode(torch.nn.Module):
    """``encoder.encode`` as a module's forward, for ``functional_call``."""

    def __init__(self, enc):
        super().__init__()
        self.enc = enc

    def forward(self, *args):
        return self.enc.encode(*args)


def test_batch_max_reads_every_vmapped_copy():
    n = torch.tensor([[1, 4, 2], [7, 0, 3]])
    assert batch_max(n) == 7
    assert torch.vmap(lambda x: torch.tensor(batch_max(x)))(n).tolist() == [7, 7]
    assert batch_max(torch.zeros(0, dtype=torch.long)) == 0


@pytest.mark.parametrize("name", ["gatedgcn", "lstm_rl"])
def test_lookahead_critic_term_needs_no_root_graphs(real_obs, name):
    """``prepare_batch(include_root=False)``: a TD3 critic-only step with a lookahead critic reads the
    actor's preprocessing of the next observation only; its loss and priorities are bit for bit those
    of a fully prepared batch (what OffPolicyAlgorithm.update relies on)."""
    from tensordict import TensorDict

    from crowdbench.algos.td3 import TD3
    from crowdbench.cli import compose
    from crowdbench.envs.observation import OBS
    from crowdbench.models.heads import prepare_batch

    torch.manual_seed(3)
    small = [f"encoder.{k}={v}".replace(" ", "") for k, v in SMALL[name].items()]
    td3 = TD3(compose([f"encoder={name}", *small, "algo.critic_lookahead=0.25"]), 1)
    actor, loss = td3.actor, td3.loss
    robot, humans, mask, action = real_obs
    obs = {"robot": robot, "humans": humans, "humans_mask": mask}
    nxt = {k: v.roll(1, 0) for k, v in obs.items()}
    zeros = torch.zeros(12, 1, 1, dtype=torch.bool)
    batch = TensorDict({"agents": {"observation": obs, "action": action},
                        "next": {"agents": {"observation": nxt, "reward": torch.randn(12, 1, 1), "done": zeros,
                                            "terminated": zeros}}}, batch_size=[12])
    enc = actor.module.encoder
    results = []
    for include_root in (True, False):
        td = prepare_batch(batch.clone(), enc, include_root=include_root)
        assert ((OBS + (enc.prep_key,)) in td.keys(True)) == include_root
        assert ("next",) + OBS + (enc.prep_key,) in td.keys(True)
        torch.manual_seed(4)  # the target policy noise
        q_loss, meta = loss.value_loss(td)
        results.append((q_loss.detach(), meta["td_error"]))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
