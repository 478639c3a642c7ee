"""The explicit interfaces of crowdbench/models/encoder.py and crowdbench/kinematics.py: which encoders
split their preprocessing (declared by class, never probed), and the shared kinematics giving the same bits
as the expressions they replaced."""

from __future__ import annotations

import ast
import re
from dataclasses import fields
from pathlib import Path

import pytest
import torch
from worlds import SMALL_ENCODERS

from crowdbench import kinematics
from crowdbench.envs import rules
from crowdbench.models import ENCODERS, make_encoder
from crowdbench.models.encoder import RAW_FIELDS, SplitEncoder, forward_prepared, prep_fields, prepare, splits
from crowdbench.models.heads import lookahead, prepared_keys

REPO = Path(__file__).resolve().parents[1]

PACKAGE = REPO / "crowdbench"
SPLIT = {"gatedgcn", "gcn", "gat", "mlp", "lstm_rl"}  # the encoders with a split-out preprocessing
INTERFACE = {"prepare", "forward_prepared", "prep_key", "prep_fields", "out_dim", "last_gates"}


def observation(b=5, m=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    robot = torch.randn(b, 1, 6, generator=g)
    humans = torch.randn(b, 1, m, 4, generator=g) * 2
    mask = torch.rand(b, 1, m, generator=g) < 0.7
    return robot, humans * mask.unsqueeze(-1), mask


@pytest.mark.parametrize("name", sorted(ENCODERS))
def test_which_encoders_split_is_declared_by_class(name):
    enc = make_encoder(name, **SMALL_ENCODERS[name])
    assert splits(enc) == (name in SPLIT) == isinstance(enc, SplitEncoder)
    if splits(enc):  # a split encoder overrides both halves; forward is the two composed, bit for bit
        assert type(enc).prepare is not SplitEncoder.prepare
        assert type(enc).forward_prepared is not SplitEncoder.forward_prepared
        obs = observation()
        torch.manual_seed(0)
        h_raw = enc(*obs)[1]
        assert set(prep_fields(enc)) == set(prepare(enc, *obs))
        assert torch.equal(forward_prepared(enc, prepare(enc, *obs))[1], h_raw)
    else:
        assert prep_fields(enc) == RAW_FIELDS


@pytest.mark.parametrize("name", ["sarl", "rgl", "dsrnn"])
def test_compacted_set_encoders_split(name):
    enc = make_encoder(name, compact=True, **SMALL_ENCODERS[name])
    assert splits(enc) and enc.prep_key == "humans_compact"
    assert [k[-1] for k in prepared_keys(enc)] == list(RAW_FIELDS)


def test_a_duck_typed_prepare_is_not_taken_for_the_interface():
    class Loose(torch.nn.Module):  # has the methods, does not declare the interface: read raw
        out_dim = 4

        def prepare(self, *a):
            raise AssertionError("never called")

    assert not splits(Loose())
    assert prepare(Loose(), 1, 2, 3) == dict(zip(RAW_FIELDS, (1, 2, 3), strict=True))


def test_no_module_probes_the_encoder_interface_with_hasattr():
    found = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("hasattr", "getattr")
                    and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                    and node.args[1].value in INTERFACE):
                found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert found == [], "declare it in crowdbench/models/encoder.py instead: " + ", ".join(found)


def test_kinematics_are_one_module():
    for name in ("clip_speed", "to_local", "to_world", "heading_to"):
        assert getattr(rules, name) is getattr(kinematics, name)  # re-exported, not redefined
    assert lookahead is kinematics.predict_observation


def test_prediction_is_the_expression_it_replaced_bit_for_bit():
    robot, humans, mask = observation(64, 9, seed=3)
    action = torch.randn(64, 1, 2) * 1.5
    dt, v_max = 0.25, 1.0
    # the critic's former inline prediction (crowdbench/models/heads.py before the kinematics module)
    a = action.clamp(-v_max, v_max)
    a = a * (v_max / a.norm(dim=-1, keepdim=True).clamp_min(v_max))
    shift = a * dt
    r_old = torch.cat((robot[..., :2], a, robot[..., 4:6] - shift), -1)
    moved = humans[..., :2] + humans[..., 2:4] * dt - shift.unsqueeze(-2)
    h_old = torch.cat((moved * mask.unsqueeze(-1).to(humans.dtype), humans[..., 2:4]), -1)
    r, h, m = kinematics.predict_observation(robot, humans, mask, action, dt, v_max)
    assert torch.equal(r, r_old) and torch.equal(h, h_old) and m is mask
    pos, vel = humans[..., :2], humans[..., 2:4]
    assert torch.equal(kinematics.advance(pos, vel, dt), pos + vel * dt)
    heading = torch.nn.functional.normalize(torch.randn(64, 1, 2), dim=-1)
    back = kinematics.to_world(kinematics.to_local(pos, heading), heading)
    torch.testing.assert_close(back, pos)


def _section(title: str) -> set[str]:
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text.split(f"## {title}", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"`((?:crowdbench|tests|docs)/[\w/.<>]+\.(?:py|md|yaml))`", section))


@pytest.mark.parametrize("title, must", [
    ("How to add an encoder", {"crowdbench/models/__init__.py", "crowdbench/config_schema.py", "tests/worlds.py"}),
    ("How to add an algorithm", {"crowdbench/algos/registry.py"}),
    ("How to add a crowd model", {"crowdbench/envs/humans/reactive.py"}),
])
def test_the_how_to_lists_name_files_that_exist(title, must):
    named = _section(title)
    assert must <= named, sorted(must - named)
    fixed = [f for f in named if "<" not in f]
    assert all((REPO / f).is_file() for f in fixed), sorted(f for f in fixed if not (REPO / f).is_file())


def test_every_component_has_the_entries_the_how_to_lists():
    from crowdbench.algos.registry import BUILTIN
    from crowdbench.config_schema import ENCODER_SCHEMAS, CrowdNavEnvConfig, SelfPlayEnvConfig
    from crowdbench.envs.humans.reactive import CROWDS

    conf = PACKAGE / "conf"
    for name in ENCODERS:  # models/__init__.py, conf/encoder, config_schema.py, tests/worlds.py
        assert (conf / "encoder" / f"{name}.yaml").is_file() and name in ENCODER_SCHEMAS and name in SMALL_ENCODERS
    for name, e in BUILTIN.items():  # its module and its YAML
        assert (PACKAGE / Path(*e.module.split(".")[1:])).with_suffix(".py").is_file()
        assert (conf / "algo" / f"{name}.yaml").is_file()
    for schema in (CrowdNavEnvConfig, SelfPlayEnvConfig):  # every crowd model is a choice of both worlds
        choices = {f.name: f for f in fields(schema)}["humans"].metadata["choices"]
        assert set(CROWDS) <= set(choices), (schema.__name__, choices)
