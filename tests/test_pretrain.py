"""The imitation warm start (train.pretrain=orca): returns-to-go, behaviour cloning, critic regression, the CLI."""

import math

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from crowdbench.algos.checkpoint import load_checkpoint, policy_from_checkpoint
from crowdbench.algos.pretrain import COMPLETE, EPISODE, RETURN, collect_demonstrations, returns_to_go
from crowdbench.algos.registry import component
from crowdbench.cli import compose, main
from crowdbench.envs.factory import make_env
from crowdbench.envs.observation import ACTION, GROUP, OBS
from crowdbench.models.heads import STATE_ACTION_VALUE, prepare_batch

TINY = ["env.batch=8", "train.frames_per_batch=64", "algo.warmup=128", "algo.batch_size=16", "train.utd=0.125",
        "train.checkpoint_every=128"]
MLP = ["encoder=mlp", "encoder.dim=16", "encoder.hidden=[32]"]
# plain actors: what the imitation fits (TD3's default actor, a residual on ORCA, starts at ORCA's actions)
SMALL = {"td3": ["algo=td3", "algo.actor_base=none", *MLP], "ddpg": ["algo=ddpg", "algo.n_steps=3", *MLP],
         "sac": ["algo=sac", "encoder=gatedgcn", "encoder.dim=16"]}


def loop_returns(reward, done, gamma):
    """The return-to-go and "episode ended in the data" flag of one sequence, the textbook way."""
    g, ended, ret, complete = 0.0, False, [], []
    for r, d in zip(reversed(reward), reversed(done), strict=True):
        g = r if d else r + gamma * g
        ended = ended or d
        ret.append(g)
        complete.append(ended)
    return ret[::-1], complete[::-1]


def test_returns_to_go_match_a_python_loop():
    gen = torch.Generator().manual_seed(3)
    B, T, A, gamma = 3, 9, 2, 0.9
    reward = torch.randn(B, T, A, 1, generator=gen)
    done = torch.rand(B, T, A, 1, generator=gen) < 0.3
    done[0, :, 0] = False  # one sequence with no episode end: its return has no tail
    ret, complete = returns_to_go(reward, done, gamma)
    for b in range(B):
        for a in range(A):
            want, ended = loop_returns(reward[b, :, a, 0].tolist(), done[b, :, a, 0].tolist(), gamma)
            assert ret[b, :, a, 0].tolist() == pytest.approx(want, abs=1e-5)
            assert complete[b, :, a, 0].tolist() == ended
    assert not complete[0, :, 0].any()


def make(algo: str, *extra):
    cfg = compose([*SMALL[algo], "train.pretrain=orca", "env.batch=8", *extra])
    torch.manual_seed(0)
    env = make_env(cfg, progress_reward=cfg.train.progress_reward)
    return cfg, env, component(algo)(cfg, env.n_agents)


def test_demonstrations_are_orca_with_per_episode_returns():
    """Every complete agent episode's stored return-to-go is its discounted reward sum (from its own rows)."""
    cfg, env, _ = make("td3")
    demos = collect_demonstrations(cfg, env, 400)
    assert len(demos) == 400  # one robot: no frozen agent dropped
    from crowdbench.algos.pretrain import expert_policy

    assert torch.allclose(expert_policy(cfg).act(demos.select(OBS)), demos[ACTION])
    ids, gamma = demos[EPISODE].reshape(-1), cfg.algo.gamma
    assert demos[COMPLETE].any() and not demos[COMPLETE].all()  # 50 steps per env: some tails are cut
    for i in ids.unique():
        ep = demos[ids == i]
        reward = ep["next", GROUP, "reward"].reshape(-1).tolist()
        done = ep["next", GROUP, "done"].reshape(-1).tolist()
        assert sum(done) <= 1 and (not done[-1] or done.index(True) == len(done) - 1)
        want, ended = loop_returns(reward, done, gamma)
        assert ep[RETURN].reshape(-1).tolist() == pytest.approx(want, abs=1e-4)
        assert ep[COMPLETE].reshape(-1).tolist() == ended


@torch.no_grad()
def acting_mse(actor, demos) -> float:
    """The error of the action an evaluation takes (deterministic exploration) to ORCA's."""
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        action = actor(demos.select(OBS).copy())[ACTION]
    return ((action - demos[ACTION]) ** 2).mean().item()


@torch.no_grad()
def critic_mse(algo, demos) -> float:
    """Mean over the critics of the squared error of Q(s, a_demo) to the returns (complete episodes)."""
    td = demos[demos[COMPLETE].reshape(-1)]
    if algo.prepared:
        td = prepare_batch(td.copy(), *algo.encoders, include_next=False)
    params, net = algo.critic_params(), algo.critic_network()
    errs = []
    for p in params.unbind(0) if params.batch_dims else [params]:  # twin critics stacked; DDPG's one
        with p.to_module(net):
            errs.append(((net(td.copy())[STATE_ACTION_VALUE] - td[RETURN]) ** 2).mean().item())
    return sum(errs) / len(errs)


@pytest.mark.parametrize("algo, frames, epochs", [("td3", 1600, 8), ("ddpg", 1200, 6), ("sac", 1200, 4)])
@pytest.mark.slow
def test_warm_start_imitates_orca_on_unseen_episodes(algo, frames, epochs):
    cfg, env, learner = make(algo, f"train.pretrain_epochs={epochs}", "train.pretrain_batch=128",
                             "train.pretrain_lr=3e-3")
    demos = collect_demonstrations(cfg, env, frames)
    # episodes of another seed: none of them is among the demonstrations
    other_cfg = compose([*SMALL[algo], "train.pretrain=orca", "env.batch=8", "seed=1"])
    unseen = collect_demonstrations(other_cfg, make_env(other_cfg, progress_reward=0.1), 800)
    before, q_before = acting_mse(learner.actor, unseen), critic_mse(learner, unseen)
    logs = learner.warm_start(demos)
    after, q_after = acting_mse(learner.actor, unseen), critic_mse(learner, unseen)
    assert after < 0.5 * before, (before, after)
    assert q_after < 0.7 * q_before, (q_before, q_after)
    assert logs["pretrain_heldout_action_mse"] < 0.5 * logs["pretrain_heldout_action_mse_before"]
    assert logs["pretrain_heldout_critic_mse"] < logs["pretrain_heldout_critic_mse_before"]
    loss = learner.loss  # the targets start from the warm-started networks
    for name in ("actor_network_params", "qvalue_network_params"):
        target = getattr(loss, f"target_{name}", None)
        if target is not None:
            assert (target.data == getattr(loss, name).data).all(), name
    assert len(learner.rb) == len(demos)
    sample = learner.rb.sample()  # the demonstrations are replay transitions (n-step ones for DDPG here)
    if algo == "ddpg":
        assert 1 <= sample[GROUP, "steps_to_next_obs"].min() and sample[GROUP, "steps_to_next_obs"].max() <= 3
    assert math.isfinite(learner.update(sample, 0)["loss_critic"])
    assert learner.random_frames(False, False, 0) == 0


def read_log(run, name):
    path = run / "logs" / "scalars" / f"{name}.csv"
    return [(int(float(a)), float(b)) for a, b in (line.split(",") for line in path.read_text().splitlines())]


def test_cli_run_with_warm_start_then_resume(tmp_path):
    args = ["run", *SMALL["td3"], *TINY, "train.pretrain=orca", "train.pretrain_frames=256", "train.pretrain_epochs=1",
            "eval.episodes=2", "eval.scenes=[hotel]", f"out={tmp_path}"]
    assert main([*args, "train.total_frames=128"]) == 0
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    # no random warm-up: the 256 demonstrations already fill algo.warmup, updates start with the first batch
    assert state["frames"] == 128 and state["updates"] == 2 * 8
    assert policy_from_checkpoint(tmp_path / "checkpoint.pt") is not None
    [(step, mse)] = read_log(tmp_path, "pretrain_heldout_action_mse")
    assert step == 0 and mse < read_log(tmp_path, "pretrain_heldout_action_mse_before")[0][1]
    assert main([*args, "train.total_frames=256", "resume=true"]) == 0
    assert load_checkpoint(tmp_path / "checkpoint.pt")["frames"] == 256
    assert len(read_log(tmp_path, "pretrain_heldout_action_mse")) == 1  # a resumed run never pretrains again


def test_a_budget_that_counts_the_warm_start_starts_the_clock_at_its_end(tmp_path):
    """train.budget_warm_start: max_minutes counts the demonstrations and their fit (experiment=selfplay_residual's
    30 minutes per seed), so the loop's first wall time already holds them; a budget they used up stops the run
    after its first batch, with a checkpoint."""
    from crowdbench.algos.train import train

    base = [*SMALL["td3"], *TINY, "train.pretrain=orca", "train.pretrain_frames=128", "train.pretrain_epochs=1",
            "train.total_frames=1024"]
    assert compose(base).train.budget_warm_start is False
    train(compose([*base, "train.budget_warm_start=true", "train.max_minutes=1e-6"]), tmp_path, progress=False)
    warm = read_log(tmp_path, "pretrain_collect_s")[0][1] + read_log(tmp_path, "pretrain_fit_s")[0][1]
    [(step, wall)] = read_log(tmp_path, "wall_time_s")
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert step == state["frames"] == 64 and wall >= warm > 0 and state["wall_time_s"] >= warm


def test_bad_pretrain_is_a_one_line_error(tmp_path, capsys):
    assert main(["run", "train.pretrain=foo", f"out={tmp_path / 'run'}"]) == 2
    err = capsys.readouterr().err
    assert "train.pretrain: must be one of orca, checkpoint (got 'foo')" in err and err.count("\n") == 1
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_ppo_warm_start_clones_the_actor_and_fits_v(tmp_path):
    """PPO: the deterministic action imitates ORCA on another seed's episodes and V(s) moves to the returns."""
    from crowdbench.algos.ppo import VALUE

    cfg = compose(["algo=ppo", *MLP, "train.pretrain=orca", "env.batch=8", "train.pretrain_epochs=8",
                   "train.pretrain_batch=128", "train.pretrain_lr=3e-3"])
    env = make_env(cfg, progress_reward=0.1)
    torch.manual_seed(0)
    ppo = component("ppo")(cfg, env.n_agents)
    demos = collect_demonstrations(cfg, env, 1600)
    other = compose(["algo=ppo", *MLP, "train.pretrain=orca", "env.batch=8", "seed=1"])
    unseen = collect_demonstrations(other, make_env(other, progress_reward=0.1), 800)
    complete = unseen[unseen[COMPLETE].reshape(-1)]

    @torch.no_grad()
    def v_mse():
        return ((ppo.loss.critic_network(complete.copy())[VALUE] - complete[RETURN]) ** 2).mean().item()

    before, v_before = acting_mse(ppo.actor, unseen), v_mse()
    logs = ppo.warm_start(demos)
    assert acting_mse(ppo.actor, unseen) < 0.5 * before and v_mse() < 0.7 * v_before
    assert logs["pretrain_heldout_critic_mse"] < logs["pretrain_heldout_critic_mse_before"]
    args = ["run", "algo=ppo", *MLP, "env.batch=8", "train.frames_per_batch=64", "algo.minibatch_size=64",
            "algo.epochs=1", "train.pretrain=orca", "train.pretrain_frames=256", "train.pretrain_epochs=1",
            "train.total_frames=128", "eval.episodes=2", "eval.scenes=[hotel]", f"out={tmp_path}"]
    assert main(args) == 0 and load_checkpoint(tmp_path / "checkpoint.pt")["updates"] == 2


@pytest.mark.slow
def test_cloning_term_holds_the_actor_near_orca_and_resumes(tmp_path):
    """train.pretrain_bc_weight: the actor's error to ORCA after RL updates stays below the run without the
    term; the term decays as configured, and a resumed run keeps it (demos.pt) and ends where the whole run does."""
    from crowdbench.algos.pretrain import DemoCloning

    base = [*SMALL["td3"], *TINY, "train.pretrain=orca", "train.pretrain_frames=1024", "train.pretrain_epochs=6",
            "train.pretrain_lr=3e-3", "algo.warmup=64"]
    other = compose([*SMALL["td3"], "train.pretrain=orca", "env.batch=8", "seed=1"])
    unseen = collect_demonstrations(other, make_env(other, progress_reward=0.1), 600)
    from crowdbench.algos.train import train

    errs = {}
    for w in (0.0, 20.0):
        out = tmp_path / f"w{w}"
        train(compose([*base, f"train.pretrain_bc_weight={w}", "train.total_frames=256"]), out, progress=False)
        errs[w] = acting_mse(policy_from_checkpoint(out / "checkpoint.pt").actor, unseen)
    # Adam steps are scale-free, so a larger weight moves the actor about as far: the term's effect is bounded
    assert errs[20.0] < 0.9 * errs[0.0], errs
    assert (tmp_path / "w20.0" / "demos.pt").exists() and not (tmp_path / "w0.0" / "demos.pt").exists()
    cl = DemoCloning(compose([*base, "train.pretrain_bc_weight=2", "train.pretrain_bc_updates=100"]))
    assert [cl.weight_at(n) for n in (0, 50, 100, 200)] == [2.0, 1.0, 0.0, 0.0]
    # resume: two halves end with the whole run's actor
    cfg = [*base, "train.pretrain_bc_weight=20"]
    train(compose([*cfg, "train.total_frames=128"]), tmp_path / "split", progress=False)
    train(compose([*cfg, "train.total_frames=256"]), tmp_path / "split", resume=True, progress=False)
    whole = load_checkpoint(tmp_path / "w20.0" / "checkpoint.pt")
    split = load_checkpoint(tmp_path / "split" / "checkpoint.pt")
    assert whole["updates"] == split["updates"]
    # the term continues after the resume: the same rows, identical up to the checkpoint (episodes in flight at
    # a checkpoint restart on resume, so later values differ in low-order digits: docs/training.md, Resuming)
    w_rows, s_rows = read_log(tmp_path / "w20.0", "loss_bc"), read_log(tmp_path / "split", "loss_bc")
    assert [f for f, _ in w_rows] == [f for f, _ in s_rows] == [64, 128, 192, 256]
    assert w_rows[:2] == s_rows[:2] and all(abs(a - b) < 1e-2 * a for (_, a), (_, b) in zip(w_rows, s_rows, strict=True))
    # without demonstrations the term has nothing to clone: off, whatever its weight
    train(compose([*SMALL["td3"], *TINY, "train.pretrain=null", "train.pretrain_bc_weight=1", "train.total_frames=128"]),
          tmp_path / "x", progress=False)
    assert not (tmp_path / "x" / "demos.pt").exists() and not (tmp_path / "x" / "logs" / "scalars" / "loss_bc.csv").exists()


def teacher_setup(tmp_path, lookahead: str = "cv", *extra):
    from tests.test_value_leaderboard import value_checkpoint

    path = tmp_path / "teacher.pt"
    value_checkpoint(path, lookahead)
    cfg = compose(["env=crowdnav", *SMALL["td3"], "train.pretrain=checkpoint", f"train.pretrain_checkpoint={path}",
                   "env.batch=4", *extra])
    torch.manual_seed(0)
    return cfg, make_env(cfg, progress_reward=cfg.train.progress_reward), path


def test_a_value_checkpoint_teaches_from_the_candidates_of_the_state_it_observes(tmp_path):
    """train.pretrain=checkpoint with a value entry (lookahead cv): each demonstrated action is the greedy
    action of the candidates computed from the world at the observed step, as the evaluation hands them."""
    from crowdbench.envs.lookahead import lookahead_observation

    cfg, env, path = teacher_setup(tmp_path)
    T = 30
    demos = collect_demonstrations(cfg, env, 4 * T)
    torch.manual_seed(0)
    again = make_env(cfg, progress_reward=cfg.train.progress_reward)  # the same episodes, stepped by hand
    teacher = policy_from_checkpoint(path)
    model, actions = teacher.lookahead
    td, want = again.reset(), []
    for _ in range(T):
        obs = td.select(OBS).clone()
        for key, value in lookahead_observation(again.world, actions, model).items():
            obs.set(OBS + (key,), value)
        td.set(ACTION, teacher.act(obs))
        want.append(td[ACTION])
        td = again.step_and_maybe_reset(td)[1]
    want = torch.stack(want, 1)  # [B, T, 1, 2]
    assert torch.equal(demos[ACTION].reshape(want.shape), want)
    assert len(set(map(tuple, demos[ACTION].reshape(-1, 2).tolist()))) > 1  # it steers, not one fixed action


def test_a_privileged_or_mismatched_teacher_is_refused(tmp_path):
    from crowdbench.algos.pretrain import expert_policy

    cfg, env, _ = teacher_setup(tmp_path, "query")
    with pytest.raises(ValueError, match="privileged lookahead 'query'"):
        expert_policy(cfg, env)
    cfg, env, _ = teacher_setup(tmp_path, "cv", "env.frame=translate")
    with pytest.raises(ValueError, match="env.frame=rotate"):
        expert_policy(cfg, env)
    cfg.train.pretrain_checkpoint = None
    with pytest.raises(ValueError, match="needs train.pretrain_checkpoint"):
        expert_policy(cfg, env)


def test_dagger_labels_the_states_the_student_visits_with_the_experts_action():
    """collect_corrections: the env is driven by the student's evaluated action, and each visited state is
    labelled with ORCA's action there, stepped by hand on the same episodes; success counts the ended ones."""
    from crowdbench.algos.pretrain import collect_corrections, expert_policy, policy_action

    cfg, env, learner = make("td3")
    expert = expert_policy(cfg)
    T = 40
    data, success = collect_corrections(env, learner.actor, "deterministic", expert, 8 * T)
    torch.manual_seed(0)
    again = make_env(cfg, progress_reward=cfg.train.progress_reward)
    td, labels, ended, arrived = again.reset(), [], 0, 0
    for _ in range(T):
        labels.append(expert.act(td.select(OBS)))
        with torch.no_grad():
            td.set(ACTION, policy_action(learner.actor, td, "deterministic"))
        stepped, td = again.step_and_maybe_reset(td)
        done = stepped["next", GROUP, "done"].reshape(-1)
        ended += int(done.sum())
        arrived += int((stepped["next", GROUP, "info", "outcome"].reshape(-1)[done] == 1).sum())
    want = torch.stack(labels, 1)  # [B, T, 1, 2]: running agents only in data; one robot never frozen
    assert torch.equal(data[ACTION].reshape(want.shape), want)
    assert ended > 0 and success == pytest.approx(arrived / ended)
    assert not torch.equal(data[ACTION], policy_action(learner.actor, data, "deterministic").detach())


def test_dagger_rounds_aggregate_and_reclone(tmp_path):
    """dagger(): each round adds the student's labelled states (distinct episode ids) and re-clones the actor
    on everything; the CLI logs each round's student success; a tiny run trains end to end with it."""
    from crowdbench.algos.pretrain import collect_demonstrations, dagger, expert_policy

    cfg, env, learner = make("td3", "train.pretrain_dagger_rounds=2", "train.pretrain_dagger_frames=160",
                             "train.pretrain_epochs=2")
    demos = collect_demonstrations(cfg, env, 320)
    learner.warm_start(demos)
    before = [p.detach().clone() for p in learner.actor.parameters()]
    data, logs = dagger(cfg, env, learner.actor, "deterministic", expert_policy(cfg), demos)
    assert len(data) == len(demos) + 2 * 160 and logs["dagger_transitions"] == len(data)
    assert len(data[EPISODE].unique()) > len(demos[EPISODE].unique())
    assert not torch.isin(data[EPISODE][len(demos):], demos[EPISODE]).any()
    assert any(not torch.equal(a, b) for a, b in zip(before, learner.actor.parameters(), strict=True))
    assert {"dagger_0_student_success", "dagger_1_action_mse"} <= set(logs)
    args = ["run", *SMALL["td3"], *TINY, "train.pretrain=orca", "train.pretrain_frames=128", "train.pretrain_epochs=1",
            "train.pretrain_dagger_rounds=1", "train.pretrain_dagger_frames=64", "train.pretrain_bc_weight=1",
            "train.total_frames=256", "eval.episodes=1", "eval.scenes=[hotel]", f"out={tmp_path}"]
    assert main(args) == 0
    assert read_log(tmp_path, "dagger_0_student_success") and read_log(tmp_path, "dagger_transitions")[0][1] == 192
