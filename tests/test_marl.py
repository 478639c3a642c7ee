"""The multi-agent algorithms (crowdbench/algos/mappo.py, ippo.py, matd3.py): the scene view against hand
geometry, the scene critics against loops, MAPPO's GAE per agent with its own episode cuts and MATD3's
target against loops."""

import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from crowdbench.algos.ppo import ADVANTAGE, VALUE, VALUE_TARGET
from crowdbench.algos.registry import component
from crowdbench.cli import compose
from crowdbench.envs.factory import make_env, selfplay_world
from crowdbench.envs.observation import GROUP, OBS
from crowdbench.envs.rules import RUNNING, SUCCESS
from crowdbench.envs.selfplay import SelfPlayConfig
from crowdbench.envs.transforms import SCENE, SCENE_MASK, SceneView
from crowdbench.models.scene_critic import SceneCritic, SceneQ


def three_agents(frame: str = "rotate"):
    """Three agents with hand-placed starts and goals, agent 2 already done (vanished)."""
    world, _ = selfplay_world(SelfPlayConfig(n_agents=3, frame=frame), 1)
    start = torch.tensor([[[0.0, 0.0], [3.0, 4.0], [20.0, 0.0]]])
    goal = torch.tensor([[[0.0, 8.0], [3.0, -4.0], [-20.0, 0.0]]])
    world.reset(torch.ones(1, dtype=torch.bool), {"start": start, "goal": goal})
    world.vel = torch.tensor([[[0.0, 1.0], [0.5, 0.0], [0.0, 0.0]]])
    world.outcome[0, 2] = SUCCESS  # done: vanished
    return world


def test_scene_view_is_every_body_in_the_agents_frame():
    world = three_agents()
    view = world.scene_view()
    scene, mask = view["scene"][0], view["scene_mask"][0]
    # agent 0 heads to +y: its frame's x axis is world +y, its y axis world -x
    # agent 1 at (3, 4) is at (4, -3) there; its velocity (0.5, 0) is (0, -0.5); its goal (3, -4) is (-4, -3)
    torch.testing.assert_close(scene[0, 1], torch.tensor([4.0, -3.0, 0.0, -0.5, -4.0, -3.0, 1.0]))
    # 20 m away and beyond any sensing range, agent 2 would be in the view were it not done
    assert mask[0].tolist() == [False, True, False] and not scene[0, 2].any() and not scene[0, 0].any()
    # agent 1 heads to -y: x axis world -y, y axis world +x; agent 0 at (-3, -4) rel -> (4, -3), its goal (-3, 4) -> (-4, -3)
    torch.testing.assert_close(scene[1, 0], torch.tensor([4.0, -3.0, -1.0, 0.0, -4.0, -3.0, 1.0]))
    world.outcome[0, 2] = RUNNING  # running again: seen by both, 20 m away, no range limit
    assert world.scene_view()["scene_mask"][0, 0].tolist() == [False, True, True]
    assert world.observe()["humans_mask"][0, 0].tolist() == [False, True, False]  # the policy's 5 m range


def test_scene_view_transform_passes_torchrls_spec_check():
    cfg = compose(["env=selfplay", "env.batch=3", "env.n_agents=4", "env.n_humans=2"])
    env = make_env(cfg, extra=(SceneView(),))
    check_env_specs(env)
    td = env.rollout(3)
    assert td[SCENE].shape == (3, 3, 4, 6, 7) and td[SCENE_MASK].shape == (3, 3, 4, 6)
    # the other 3 agents' slots carry is_agent, the 2 humans' do not; every human is seen, with no range
    assert (td[SCENE][..., :4, 6].sum(-1) == 3).all() and not td[SCENE][..., 4:, 6].any()
    assert td[SCENE_MASK][..., 4:].all()


@torch.no_grad()
def loop_critic(net: SceneCritic, robot, scene, mask, action=None) -> float:
    """One agent's value with a Python loop over the bodies (the module docstring's equations); with
    ``action``, SceneQ's action value."""
    tail = () if action is None else (action,)
    hs = []
    for e in range(scene.shape[0]):
        if mask[e]:
            x = torch.cat((robot, scene[e], scene[e, :2].norm().reshape(1)))
            hs.append(torch.relu(net.pair(x)))
    if not hs:
        return float(net.value(torch.cat((robot, torch.zeros(net.dim), *tail))))
    mean = sum(hs) / len(hs)
    scores = torch.stack([net.score(torch.cat((h, mean))).squeeze() for h in hs])
    w = [math.exp(float(s - scores.max())) for s in scores]
    pooled = sum(wi / sum(w) * h for wi, h in zip(w, hs, strict=True))
    return float(net.value(torch.cat((robot, pooled, *tail))))


def test_scene_critic_equals_a_loop_over_the_bodies():
    torch.manual_seed(0)
    net = SceneCritic(dim=8, hidden=[16])
    robot, scene = torch.randn(5, 6), torch.randn(5, 7, 7)
    mask = torch.rand(5, 7) < 0.6
    mask[3] = False  # alone in its scene: pools zero
    got = net(robot, scene, mask).squeeze(-1)
    want = torch.tensor([loop_critic(net, robot[i], scene[i], mask[i]) for i in range(5)])
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    scene2 = scene.clone()
    scene2[~mask] = 99.0  # masked slots are not read
    torch.testing.assert_close(net(robot, scene2, mask).squeeze(-1), got)
    q, action = SceneQ(dim=8, hidden=[16]), torch.randn(5, 2)
    want = torch.tensor([loop_critic(q, robot[i], scene[i], mask[i], action[i]) for i in range(5)])
    torch.testing.assert_close(q(robot, scene, mask, action).squeeze(-1), want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("algo", ["mappo", "ippo"])
def test_gae_per_agent_with_its_own_episode_cuts_equals_a_loop(algo):
    """Advantages and value targets of a collected self-play batch (agents finishing at different steps,
    environments resetting inside it) against a loop over environments, agents and steps backwards."""
    cfg = compose([f"algo={algo}", "env=selfplay", "env.batch=4", "env.n_agents=3", "env.time_limit=12",
                   "env.circle_radius=0.7",
                   "encoder=mlp", "encoder.dim=16", "encoder.hidden=[16]", "algo.gamma=0.9", "algo.lmbda=0.8"])
    Algo = component(algo)
    torch.manual_seed(0)
    env = make_env(cfg, extra=Algo.env_transforms(cfg))
    learner = Algo(cfg, env.n_agents)
    # random actions on a small circle: agents collide, time out or arrive at different steps
    batch = env.rollout(30, break_when_any_done=False)
    with torch.no_grad():
        learner.loss.value_estimator(batch)
        critic = learner.loss.critic_network
        v = critic(batch.clone())[VALUE].squeeze(-1)
        vn = critic(batch["next"].clone())[VALUE].squeeze(-1)
    nxt = batch["next", GROUP]
    r, d, term = nxt["reward"][..., 0], nxt["done"][..., 0].float(), nxt["terminated"][..., 0].float()
    B, T, A = r.shape
    ends = [(d[b, :, a] > d[b, :, a].roll(1)).nonzero().flatten().tolist() for b in range(B) for a in range(A)]
    assert len({tuple(e) for e in ends}) > 1 and max(len(e) for e in ends) >= 2  # own cuts, and resets inside
    adv = torch.zeros(B, T, A)
    for b in range(B):
        for a in range(A):
            gae = 0.0
            for t in reversed(range(T)):
                delta = r[b, t, a] + 0.9 * vn[b, t, a] * (1 - term[b, t, a]) - v[b, t, a]
                gae = delta + 0.9 * 0.8 * (1 - d[b, t, a]) * gae
                adv[b, t, a] = gae
    torch.testing.assert_close(batch[ADVANTAGE].squeeze(-1), adv, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(batch[VALUE_TARGET].squeeze(-1), adv + v, rtol=1e-4, atol=1e-5)


def test_mappo_critic_reads_the_scene_and_ippo_the_observation():
    base = ["env=selfplay", "env.n_agents=3", "encoder=mlp", "encoder.dim=16", "encoder.hidden=[16]"]
    mappo = component("mappo")(compose(["algo=mappo", *base]), 3)
    ippo = component("ippo")(compose(["algo=ippo", *base]), 3)
    assert set(mappo.loss.critic_network.in_keys) == {OBS + ("robot",), SCENE, SCENE_MASK}
    assert all(k[:2] == OBS for k in ippo.loss.critic_network.in_keys)
    assert component("ippo").env_transforms(None) == ()


def test_matd3_target_equals_a_loop_over_the_transitions():
    """MATD3's critic target ``r + gamma (1 - terminated) min_j Q'_j(s', pi'(s'))`` (no smoothing noise) against
    the target networks called one transition at a time; the replay buffer holds both scene views."""
    from crowdbench.algos.multiagent import agent_transitions
    from crowdbench.models.heads import prepare_batch

    cfg = compose(["algo=matd3", "env=selfplay", "env.batch=4", "env.n_agents=3", "env.circle_radius=0.7",
                   "encoder=mlp", "encoder.dim=16", "encoder.hidden=[16]", "algo.policy_noise=0.0",
                   "algo.batch_size=32", "algo.gamma=0.9", "algo.critic_dim=8", "algo.critic_hidden=[16]"])
    Algo = component("matd3")
    torch.manual_seed(0)
    env = make_env(cfg, extra=Algo.env_transforms(cfg))
    learner = Algo(cfg, env.n_agents)
    learner.rb.extend(agent_transitions(env.rollout(20, break_when_any_done=False), list(learner.keep)))
    sample = learner.rb.sample()
    assert ("next", GROUP, "state", "scene") in sample.keys(True)
    prepare_batch(sample, *learner.encoders)
    _, meta = learner.loss.value_loss(sample.clone())
    loss = learner.loss
    actor, q = loss.actor_network, loss.qvalue_network
    want = []
    with torch.no_grad():
        for i in range(len(sample)):
            nxt = sample[i : i + 1]["next"].clone()
            with loss.target_actor_network_params.to_module(actor):
                a = actor(nxt.clone())[GROUP, "action"].clamp(-1.0, 1.0)
            qs = []
            for j in range(2):
                with loss.target_qvalue_network_params[j].to_module(q):
                    td = nxt.clone()
                    td[GROUP, "action"] = a
                    qs.append(float(q(td)[GROUP, "state_action_value"]))
            r, term = float(sample[i]["next", GROUP, "reward"]), float(sample[i]["next", GROUP, "terminated"])
            want.append(r + 0.9 * (1 - term) * min(qs))
    torch.testing.assert_close(meta["target_value"].flatten(), torch.tensor(want), rtol=1e-4, atol=1e-5)
