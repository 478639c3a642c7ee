"""crowdbench/models/compact.py: the opt-in compacted human slots of the set encoders' training path."""

from __future__ import annotations

import pytest
import torch
from worlds import students_obs

from crowdbench.models import make_encoder
from crowdbench.models.compact import COMPACTABLE, compact_humans
from crowdbench.models.heads import Critic, prepare_batch

SMALL = {"sarl": {"dim": 16, "embed": [16, 16], "interact": [16], "attention": [16], "hidden": [16]},
         "rgl": {"dim": 16, "embed": [16]}, "dsrnn": {"dim": 16, "embed": 16, "attn_dim": 8}}


@pytest.fixture(scope="module")
def real_obs():
    torch.manual_seed(0)
    o = students_obs(12, 6)
    return o["robot"], o["humans"], o["humans_mask"]


def test_compact_humans_keeps_the_observed_humans_in_slot_order(real_obs):
    humans, mask = real_obs[1][:, 0], real_obs[2][:, 0].bool()
    got, got_mask = compact_humans(humans, mask)
    assert got.shape[1] == int(mask.sum(-1).max()) < mask.shape[1]
    for b in range(mask.shape[0]):
        n = int(mask[b].sum())
        assert got_mask[b, :n].all() and not got_mask[b, n:].any()
        assert torch.equal(got[b, :n], humans[b, mask[b]])


@pytest.mark.parametrize("name", COMPACTABLE)
def test_compacted_training_path_equals_the_raw_encoder(real_obs, name):
    """Same parameters and state_dict keys; the raw forward is bit for bit the plain encoder's, the
    prepared (compacted) one equal up to rounding, also inside a vmapped lookahead critic."""
    torch.manual_seed(1)
    plain = make_encoder(name, **SMALL[name])
    comp = make_encoder(name, compact=True, **SMALL[name])
    assert list(comp.state_dict()) == list(plain.state_dict())
    comp.load_state_dict(plain.state_dict())
    with torch.no_grad():
        want = plain(*real_obs)[1]
        assert torch.equal(comp(*real_obs)[1], want)
        gates = comp.last_gates
        prep = comp.prepare(*real_obs)
        assert prep["humans"].shape[-2] < real_obs[1].shape[-2]
        torch.testing.assert_close(comp.forward_prepared(prep)[1], want, atol=1e-5, rtol=1e-5)
        assert torch.equal(comp.last_gates.values, gates.values)  # the prepared call records none
        action = 0.3 * torch.ones(*real_obs[0].shape[:-1], 2)
        critics = [Critic(e, lookahead_dt=0.25) for e in (plain, comp)]
        critics[1].head.load_state_dict(critics[0].head.state_dict())
        params = {n: p.expand(2, *p.shape) for n, p in critics[1].named_parameters()}
        args = [x.expand(2, *x.shape) for x in (*real_obs, action)]
        q = torch.vmap(lambda p, *x: torch.func.functional_call(critics[1], p, x))(params, *args)
        torch.testing.assert_close(q[1], critics[0](*real_obs, action), atol=1e-5, rtol=1e-5)


def test_prepare_batch_serves_the_compacted_keys(real_obs):
    from tensordict import TensorDict

    from crowdbench.envs.observation import OBS

    comp = make_encoder("sarl", compact=True, **SMALL["sarl"])
    td = TensorDict({OBS: TensorDict(dict(zip(("robot", "humans", "humans_mask"), real_obs, strict=True)),
                                     batch_size=[12, 1])}, batch_size=[12, 1])
    prepare_batch(td, comp)
    assert td[OBS + ("humans_compact", "humans")].shape[-2] == int(real_obs[2].sum(-1).max())


def test_unsupported_encoder_refuses_compaction():
    with pytest.raises(ValueError, match="compactable"):
        make_encoder("gatedgcn", compact=True)
