"""crowdbench.envs.crowdnav_cases reproduces CrowdNav's test cases exactly."""

import numpy as np
import pytest

from crowdbench.envs.crowdnav_cases import CROWDNAV, case_list, crowdnav_case, reference_case

# Reference values: obtained once by running CrowdNav's own code (github.com/vita-epfl/CrowdNav at commit
# 20d678085c06831e658a65b9e20c8bb6f6ecdc10: CrowdSim.configure/reset of crowd_sim/envs/crowd_sim.py with
# Human/Robot of crowd_sim/envs/utils/ and crowd_nav/configs/env.config, gym and rvo2 stubbed, numpy 2.4)
# in a scratch directory outside this repository: env.reset('test', test_case=case) with
# test_sim = circle_crossing or square_crossing and [sim] human_num = 5 or 20, printing repr() of the
# first two humans' (px, py) and (gx, gy). Keys: (scenario, n_humans, case) -> (start0, goal0, start1, goal1).
REFERENCE = {
    ("circle", 5, 0): (
        (-2.6625559084662678, -2.837985290326649), (2.6625559084662678, 2.837985290326649),
        (-3.6025107218593906, 0.15897818498977118), (3.6025107218593906, -0.15897818498977118),
    ),
    ("circle", 5, 1): (
        (-1.6189844599022485, 3.4489804011123173), (1.6189844599022485, -3.4489804011123173),
        (-4.101755541185293, 1.3870311744563686), (4.101755541185293, -1.3870311744563686),
    ),
    ("circle", 5, 7): (
        (-3.520366552238565, -1.6880531654372484), (3.520366552238565, 1.6880531654372484),
        (-0.8226408804702925, -4.142700726059962), (0.8226408804702925, 4.142700726059962),
    ),
    ("circle", 5, 499): (
        (1.1864128465707466, -3.4844207477053897), (-1.1864128465707466, 3.4844207477053897),
        (2.8992680728456968, -3.164794308595407), (-2.8992680728456968, 3.164794308595407),
    ),
    ("square", 5, 0): (
        (-0.5750347156220287, 4.502828643490245), (2.410957007139991, 3.7247453518203533),
        (0.20354812384544563, -1.028055386542942), (-1.1656609867418999, 3.417407242530616),
    ),
    ("square", 5, 3): (
        (-2.179668944299694, -4.8313000610840175), (2.9834372919610153, 3.9497810105534703),
        (-0.029776518866930224, 4.021795069659744), (3.7725980893353004, -3.2789622619584566),
    ),
    ("circle", 20, 0): (
        (-2.6625559084662678, -2.837985290326649), (2.6625559084662678, 2.837985290326649),
        (-3.6025107218593906, 0.15897818498977118), (3.6025107218593906, -0.15897818498977118),
    ),
}

MIN_SEP = CROWDNAV.human_radius + CROWDNAV.robot_radius + CROWDNAV.discomfort_dist  # 0.8 m, as CrowdNav sums it


@pytest.fixture(scope="module")
def circle():
    return case_list("circle", 5)


@pytest.fixture(scope="module")
def square():
    return case_list("square", 5)


@pytest.mark.parametrize("key", sorted(REFERENCE))
def test_reference_values_exact(key):
    scenario, n_humans, case = key
    c = crowdnav_case(case, scenario, n_humans)
    s0, g0, s1, g1 = REFERENCE[key]
    assert c["human_start"].shape == (n_humans, 2) and c["human_start"].dtype == np.float64
    assert tuple(c["human_start"][0]) == s0 and tuple(c["human_goal"][0]) == g0
    assert tuple(c["human_start"][1]) == s1 and tuple(c["human_goal"][1]) == g1
    assert tuple(c["robot_start"]) == (0.0, -4.0) and tuple(c["robot_goal"]) == (0.0, 4.0)
    assert c["seed"] == 1000 + case


def test_case_list_matches_single_cases(circle, square):
    assert circle["human_start"].shape == (500, 5, 2) and circle["robot_goal"].shape == (500, 2)
    assert np.array_equal(circle["episode"], np.arange(500)) and np.array_equal(circle["seed"], 1000 + np.arange(500))
    for k in (0, 7, 499):
        for lst, scen in ((circle, "circle"), (square, "square")):
            c = crowdnav_case(k, scen)
            assert np.array_equal(lst["human_start"][k], c["human_start"])
            assert np.array_equal(lst["human_goal"][k], c["human_goal"])
    # the counter wraps at test_size: episode 500 of a run is case 0 again
    assert list(case_list("circle", 5, n=502)["episode"][-2:]) == [0, 1]


def test_circle_geometry(circle):
    s, g = circle["human_start"], circle["human_goal"]
    assert np.array_equal(g, -s)  # goal is exactly the opposite point, noise included
    ang, noise = circle["human_angle"], circle["human_noise"]
    on_circle = CROWDNAV.circle_radius * np.stack([np.cos(ang), np.sin(ang)], -1)
    assert np.array_equal(on_circle + noise, s)
    half = CROWDNAV.human_v_pref / 2  # noise = (u - 0.5) * v_pref per axis, u in [0, 1)
    assert (noise >= -half).all() and (noise < half).all()
    r = np.linalg.norm(s, axis=-1)
    assert (np.abs(r - CROWDNAV.circle_radius) <= half * np.sqrt(2) + 1e-12).all()
    # every start/goal point (humans' and the robot's) is >= 0.8 m from every other agent's start and goal
    rs, rg = circle["robot_start"][:, None], circle["robot_goal"][:, None]
    pts = np.concatenate([s, g], 1)  # [n, 10, 2]
    assert (np.linalg.norm(pts - rs, axis=-1) >= MIN_SEP).all()
    assert (np.linalg.norm(pts - rg, axis=-1) >= MIN_SEP).all()
    d = np.linalg.norm(pts[:, :, None] - pts[:, None], axis=-1)
    own = np.eye(5, dtype=bool)
    same_agent = np.block([[own, own], [own, own]])
    assert (d[:, ~same_agent] >= MIN_SEP).all()


def test_square_geometry(square):
    s, g, sign = square["human_start"], square["human_goal"], square["human_sign"]
    half = CROWDNAV.square_width / 2
    assert (np.abs(s) <= half).all() and (np.abs(g) <= half).all()
    assert set(np.unique(sign)) == {-1.0, 1.0}
    assert (s[..., 0] * sign >= 0).all() and (g[..., 0] * sign <= 0).all()  # opposite sides of the y axis
    # robot placed as in circle crossing
    assert (square["robot_start"] == (0.0, -4.0)).all() and (square["robot_goal"] == (0.0, 4.0)).all()
    # starts are separated from starts, goals from goals (robot included) ...
    off = ~np.eye(5, dtype=bool)
    for p, robot in ((s, square["robot_start"]), (g, square["robot_goal"])):
        assert (np.linalg.norm(p - robot[:, None], axis=-1) >= MIN_SEP).all()
        assert (np.linalg.norm(p[:, :, None] - p[:, None], axis=-1)[:, off] >= MIN_SEP).all()
    # ... but a start is not checked against goals: in case 0 human 0 starts 0.76 m from the robot's goal
    assert np.linalg.norm(s[0, 0] - square["robot_goal"][0]) < MIN_SEP


def test_more_humans_extend_fewer():
    # humans are rejection-sampled one by one against earlier ones only, from a seed without human_num
    c5, c20 = crowdnav_case(3, "circle", 5), crowdnav_case(3, "circle", 20)
    assert np.array_equal(c20["human_start"][:5], c5["human_start"])
    d = np.linalg.norm(c20["human_start"][:, None] - c20["human_start"][None], axis=-1)
    assert (d[~np.eye(20, dtype=bool)] >= MIN_SEP).all()


def test_phases_and_special_cases():
    assert crowdnav_case(4, phase="val")["seed"] == 4 and crowdnav_case(4, phase="train")["seed"] == 2004
    # no bound check in CrowdNav: test case 1000 is training episode 0
    assert np.array_equal(crowdnav_case(1000)["human_start"], crowdnav_case(0, phase="train")["human_start"])
    dbg = crowdnav_case(-1)
    assert dbg["human_start"].tolist() == [[0, -6], [-5, -5], [5, -5]] and dbg["seed"] is None
    with pytest.raises(ValueError):
        crowdnav_case(-2)
    with pytest.raises(ValueError):
        crowdnav_case(0, "mixed")
    r = crowdnav_case(0, randomize_attributes=True)
    assert ((r["human_radius"] >= 0.3) & (r["human_radius"] < 0.5)).all()
    assert ((r["human_v_pref"] >= 0.5) & (r["human_v_pref"] < 1.5)).all()


@pytest.mark.parametrize("scenario,n,phase", [pytest.param("circle", 20, "test", marks=pytest.mark.slow),  # ~10 s
                                             ("circle", 12, "train"), ("square", 20, "val"),
                                             ("circle", 5, "test"), ("square", 5, "test"), ("circle", 0, "test")])
def test_batched_rejection_equals_crowdnavs_loop(scenario, n, phase):
    """The block-wise rejection test (crowdnav_case) makes the same draws, decisions and values as the
    one-candidate-at-a-time transcription of CrowdNav's loop (reference_case)."""
    for case in range(0, 500, 17):
        fast, ref = crowdnav_case(case, scenario, n, phase), reference_case(case, scenario, n, phase)
        assert fast.keys() == ref.keys()
        for k, v in ref.items():
            if isinstance(v, np.ndarray):
                assert v.dtype == fast[k].dtype and np.array_equal(v, fast[k]), (case, k)
            else:
                assert fast[k] == v, (case, k)


def test_published_case_lists_keep_their_digests():
    from crowdbench.envs.crowdnav import CrowdNavConfig
    from crowdbench.protocols.crowdnav import crowdnav_digests
    from crowdbench.protocols.lists import CROWDNAV as DIGESTS

    assert crowdnav_digests(CrowdNavConfig(), list(DIGESTS)) == DIGESTS


def _equal_to_reference(case, scenario, n, phase="test"):
    fast, ref = crowdnav_case(case, scenario, n, phase), reference_case(case, scenario, n, phase)
    assert fast.keys() == ref.keys()
    for k, v in ref.items():
        same = v.dtype == fast[k].dtype and np.array_equal(v, fast[k]) if isinstance(v, np.ndarray) else fast[k] == v
        assert same, (scenario, n, case, k)


@pytest.mark.parametrize("scenario,n", [("circle", 20), ("square", 20), ("circle", 5)])
def test_compiled_sampler_with_tiny_buffers_and_a_wide_margin(monkeypatch, scenario, n):
    """The compiled sampler's two slow paths, forced to run all the time: the draw buffer runs out every 6
    draws (resume mid-loop), and every candidate within 5 cm of a threshold is handed back and decided by
    CrowdNav's own scalar test; the cases are still CrowdNav's."""
    import crowdbench.envs.crowdnav_cases as cc

    undecided = []
    decide = cc._Run._decide

    def counting(self, *args):
        undecided.append(args)
        return decide(self, *args)

    monkeypatch.setattr(cc, "DRAWS", 6)
    monkeypatch.setattr(cc._Run, "__init__", _with_margin(cc._Run.__init__, 0.05))
    monkeypatch.setattr(cc._Run, "_decide", counting)
    for case in (0, 3, 211) if scenario == "circle" and n == 20 else range(0, 500, 41):
        _equal_to_reference(case, scenario, n)
    assert undecided


def _with_margin(init, margin):
    def wrapped(self, *args, **kwargs):
        kwargs["margin"] = margin
        init(self, *args, **kwargs)
    return wrapped


@pytest.mark.slow  # ~25 s: reference_case draws the 1.8 million uniforms one by one
def test_the_long_rejection_runs_of_circle_20():
    # case 66 of circle_n20 draws 1,840,689 uniforms (its 20th human is refused ~600,000 times), case 3 few
    for case in (66, 3):
        _equal_to_reference(case, "circle", 20)
    assert crowdnav_case(66, "circle", 20)["n_draws"] == 1840689


UNPLACEABLE = 766005165  # a training case of circle crossing with 20 humans: human 19 never fits (CrowdNav loops)


def test_a_case_crowdnav_cannot_place_is_refused_and_the_training_stream_replaces_it(monkeypatch):
    """A training run at 20 humans hung in case generation: CrowdNav's rejection loop (transcribed and
    compiled) never ends for this case. It is refused after MAX_DRAWS draws, and the training sampler takes
    the stream's next draw instead; a stream that never meets such a case is unchanged."""
    import torch

    from crowdbench.envs import crowdnav, crowdnav_cases
    from crowdbench.envs.crowdnav import CrowdNavConfig, CrowdNavScenario

    monkeypatch.setattr(crowdnav_cases, "MAX_DRAWS", 2 * 10 ** 6)  # above the published lists' 1.8M
    with pytest.raises(crowdnav_cases.UnplaceableCase, match="human 19 not placed within 2,000,000 draws"):
        crowdnav_case(UNPLACEABLE, "circle", 20, "train")
    scenario = CrowdNavScenario(CrowdNavConfig(n_humans=20))
    plain = scenario.sampler(3)(4)
    first = torch.randint(0, CROWDNAV.train_size, (4,), generator=torch.Generator().manual_seed(3)).tolist()
    assert plain["case"].tolist() == first  # no unplaceable case: the stream as before

    real = crowdnav.torch.randint
    calls = []

    def with_unplaceable_first(*args, **kwargs):  # the stream's first draw is the unplaceable case
        out = real(*args, **kwargs)
        calls.append(out.clone())
        if len(calls) == 1:
            out[0] = UNPLACEABLE
        return out

    monkeypatch.setattr(crowdnav.torch, "randint", with_unplaceable_first)
    got = scenario.sampler(3)(4)
    replacement = int(calls[1])
    assert got["case"].tolist() == [replacement, *first[1:]]
