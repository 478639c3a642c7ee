"""Training of ``algo=value`` (:mod:`crowdbench.algos.value`), CrowdNav's recipe batched over ``B`` environments.

1. Imitation: ``il_episodes`` episodes of ORCA (radius inflated by ``il_safety_space``, CrowdNav's demonstrator)
   on training cases; each state of an episode that ends in success or collision goes to the memory with its
   discounted return ``sum_t gamma_bar^(t - i) r_t``; V is fitted for ``il_epochs`` epochs (SGD, lr 0.01).
2. Deep V-learning: rounds of ``B`` epsilon-greedy episodes (epsilon by episode number: 0.5 -> 0.1 over 4,000);
   every state of a finished success/collision episode goes to the memory with the target
   ``r_t + gamma_bar V_target(s_{t+1})`` (``r_t`` on its last step), computed with the target network when the
   episode ends; ``train_batches`` gradient steps of ``batch_size`` per episode; the target network is
   refreshed every ``target_update`` episodes. Timeouts are not stored (CrowdNav's explorer).

Rounds run their ``B`` episodes together; a finished environment waits for the round's end. The memory is a
TorchRL ``ReplayBuffer`` on a ``LazyTensorStorage`` (oldest pairs overwritten past ``capacity``).
"""

from __future__ import annotations

import copy
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler

from crowdbench.algos.value import ValueModel, epsilon
from crowdbench.envs.lookahead import lookahead_observation
from crowdbench.envs.rules import COLLISION, RUNNING, SUCCESS, TIMEOUT
from crowdbench.envs.transforms import density_keep


def discounted_returns(reward: torch.Tensor, g: float) -> torch.Tensor:
    """``[T, B]`` returns-to-go ``sum_{t >= i} g^(t - i) r_t`` (rewards after an episode's end are 0)."""
    out = torch.zeros_like(reward)
    acc = torch.zeros_like(reward[0])
    for t in range(reward.shape[0] - 1, -1, -1):
        acc = reward[t] + g * acc
        out[t] = acc
    return out


def td_targets(reward: torch.Tensor, next_value: torch.Tensor, last: torch.Tensor, g: float) -> torch.Tensor:
    """``[T, B]`` CrowdNav's V-targets: ``r_t + g V'(s_{t+1})``, ``r_t`` where ``last`` (the episode's final step)."""
    return reward + g * next_value * ~last


def thin_draw(world, p: float, gen: torch.Generator) -> torch.Tensor | None:
    """``algo.thin``: each episode draws ``u ~ U(0, p)`` and removes each recorded human with probability ``u``
    (``[B, M]`` slots kept; None when ``p`` is 0). Unlike TD3's ``train.human_dropout``, which hides humans from
    the observation only, a removed human is absent from the world too: the returns V is fitted to stay the
    returns of the crowd it sees. The dense training scene thereby also shows sparse crowds."""
    if not p:
        return None
    if not hasattr(world.crowd, "keep"):
        raise ValueError("algo.thin needs recorded humans (env=replay with env.humans=replay)")
    return density_keep(world.B, world.Mh, p, gen)


def run_round(model: ValueModel, world, episodes: dict, act, keep: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """``B`` episodes of ``world`` from ``episodes``; ``act(obs, running [B]) -> action [B, 1, 2]``; ``keep``:
    the recorded humans present (:func:`thin_draw`; None: all). Returns the net inputs ``x [T, B, M, D]``,
    ``mask [T, B, M]``, ``reward [T, B]``, ``active [T, B]`` and ``outcome [B]``."""
    B = world.B
    world.reset(torch.ones(B, dtype=torch.bool), episodes)
    if keep is not None or hasattr(world.crowd, "keep"):
        world.crowd.keep = keep
    xs, masks, rewards, actives = [], [], [], []
    for _ in range(world.cfg.time_limit):
        running = world.outcome[:, 0] == RUNNING
        if not running.any():
            break
        obs = world.observe()
        x, mask = model.state(obs)
        action = act(obs, running)
        info = world.step(action)
        xs.append(x)
        masks.append(mask)
        rewards.append(info.reward[:, 0])
        actives.append(info.active[:, 0])
    return {"x": torch.stack(xs), "mask": torch.stack(masks), "reward": torch.stack(rewards),
            "active": torch.stack(actives), "outcome": world.outcome[:, 0].clone()}


def lookahead_act(model: ValueModel, world, eps: torch.Tensor | None, gen: torch.Generator):
    """The acting function of :func:`run_round`: greedy lookahead on the running environments (one forward
    pass), a uniformly random action with probability ``eps [B]`` (None: greedy)."""
    K = len(model.actions)

    def act(obs, running):
        idx = torch.zeros(world.B, dtype=torch.long)
        rows = running.nonzero().squeeze(-1)
        look = lookahead_observation(world, model.actions, model.lookahead)
        view = {k: v[rows] for k, v in {**obs, **look}.items()}
        with torch.no_grad():
            idx[rows] = model.candidate_values(view).argmax(-1)
        if eps is not None:
            explore = torch.rand(world.B, generator=gen, dtype=torch.float64) < eps
            idx = torch.where(explore, torch.randint(0, K, (world.B,), generator=gen), idx)
        return model.actions[idx].unsqueeze(1)

    return act


def store(memory: ReplayBuffer, r: dict, values: torch.Tensor, timeouts: bool = False) -> int:
    """Push the ``(state, value)`` pairs of the round's success and collision episodes (CrowdNav's explorer);
    ``timeouts``: those of timed-out episodes too, but their last step (truncated, not terminal: its
    bootstrapped target would need the state after it). Returns how many."""
    keep = (r["outcome"] == SUCCESS) | (r["outcome"] == COLLISION)
    sel = r["active"] & keep.unsqueeze(0)  # [T, B]
    if timeouts:
        cut = (r["outcome"] == TIMEOUT).unsqueeze(0)
        sel = sel | r["active"] & cut & ~last_steps(r["active"])
    n = int(sel.sum())
    if n:
        memory.extend(TensorDict({"x": r["x"][sel], "mask": r["mask"][sel], "value": values[sel].unsqueeze(-1)},
                                 batch_size=[n]))
    return n


def last_steps(active: torch.Tensor) -> torch.Tensor:
    """``[T, B]``: the final active step of each episode."""
    nxt = torch.cat((active[1:], torch.zeros_like(active[:1])))
    return active & ~nxt


@torch.no_grad()
def round_targets(r: dict, target_net, g: float) -> torch.Tensor:
    """The V-targets of a round's states with the target network (one forward pass over its states)."""
    T, B = r["reward"].shape
    v = target_net(r["x"].flatten(0, 1), r["mask"].flatten(0, 1)).reshape(T, B)
    nxt = torch.cat((v[1:], torch.zeros_like(v[:1])))
    return td_targets(r["reward"], nxt, last_steps(r["active"]), g)


def make_memory(capacity: int, batch_size: int) -> ReplayBuffer:
    return ReplayBuffer(storage=LazyTensorStorage(capacity), sampler=RandomSampler(), batch_size=batch_size)


def make_optimizer(net, kind: str, lr: float):
    if kind == "adam":
        return torch.optim.Adam(net.parameters(), lr=lr)
    return torch.optim.SGD(net.parameters(), lr=lr, momentum=0.9)


def fit(net, memory: ReplayBuffer, opt, steps: int) -> float:
    """``steps`` gradient steps of MSE on random batches of the memory; the mean loss."""
    total = 0.0
    for _ in range(steps):
        b = memory.sample()
        loss = torch.nn.functional.mse_loss(net(b["x"], b["mask"]), b["value"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        total += loss.item()
    return total / max(steps, 1)


def demonstrator(cfg):
    """CrowdNav's imitation policy: ORCA with the env's settings and the human radius inflated by
    ``il_safety_space`` (the robot is invisible: ORCA's reciprocity would otherwise leave it half the avoiding)."""
    from crowdbench.baselines.orca import ORCA

    o = cfg.orca
    return ORCA(v_max=cfg.env.v_max, dt=cfg.env.dt, robot_radius=cfg.env.robot_radius,
                human_radius=cfg.env.human_radius, safety_margin=float(o.safety_margin) + float(cfg.algo.il_safety_space),
                neighbor_dist=o.neighbor_dist, max_neighbors=o.max_neighbors, time_horizon=o.time_horizon,
                perturb=o.perturb, pref_rule=o.pref_rule, seed=int(cfg.seed))


def imitation(cfg, model: ValueModel, world, sampler, memory: ReplayBuffer, log) -> dict:
    """Phase 1: ORCA demonstrations -> discounted returns -> V regression."""
    from crowdbench.envs.observation import obs_tensordict

    a, t0 = cfg.algo, time.perf_counter()
    orca = demonstrator(cfg)
    act = lambda obs, running: orca.act(obs_tensordict(obs, world.B))
    gen = torch.Generator().manual_seed(int(cfg.seed) + 7919)  # (thinning only)
    done = success = pairs = frames = 0
    while done < a.il_episodes:
        r = run_round(model, world, sampler(world.B), act, thin_draw(world, float(a.thin), gen))
        frames += int(r["active"].sum())
        pairs += store(memory, r, discounted_returns(r["reward"], model.gamma_bar))
        success += int((r["outcome"] == SUCCESS).sum())
        done += world.B
    collect_s = time.perf_counter() - t0
    opt = make_optimizer(model.net, a.il_optimizer, a.il_lr)
    steps = a.il_steps or a.il_epochs * -(-len(memory) // a.batch_size)  # CrowdNav: epochs over the memory
    loss = fit(model.net, memory, opt, steps) if len(memory) else float("nan")
    out = {"il_episodes": done, "il_frames": frames, "il_success": success / max(done, 1), "il_pairs": pairs, "il_loss": loss,
           "il_collect_s": collect_s, "il_fit_s": time.perf_counter() - t0 - collect_s}
    log(out)
    return out


def validate(model: ValueModel, world, episodes: dict) -> dict:
    """Greedy rounds over a fixed list (``world.B`` environments at a time): success, collision, timeout,
    mean navigation time of the successes."""
    E, outcomes, times = len(episodes["start"]), [], []
    gen = torch.Generator().manual_seed(0)  # unused by greedy acting
    for s in range(0, E, world.B):
        part = {k: v[s:s + world.B] for k, v in episodes.items()}
        n = len(part["start"])
        if n < world.B:  # pad the last round with copies of its first episode, then drop them
            part = {k: torch.cat((v, v[:1].expand(world.B - n, *v.shape[1:]))) for k, v in part.items()}
        r = run_round(model, world, part, lookahead_act(model, world, None, gen))
        outcomes.append(r["outcome"][:n])
        times.append(r["active"][:, :n].sum(0) * world.cfg.dt)
    o, t = torch.cat(outcomes), torch.cat(times)
    ok = o == SUCCESS
    return {"success": float(ok.float().mean()), "collision": float((o == COLLISION).float().mean()),
            "timeout": float((~ok & (o != COLLISION)).float().mean()),
            "nav_time": float(t[ok].mean()) if ok.any() else float("nan")}


VALUE_WORLDS = ("crowdnav", "replay")  # one robot: CrowdNav's cases, or a replayed scene (protocols v1 / v2)
RESUME_FILE = "resume.pt"  # deep V-learning's whole state: a stopped run continues from it (resume=true)
SNAPSHOT_S = 60.0  # s between snapshots (the memory is ~25 MB at capacity; Ctrl-C writes one too)


class Learner:
    """Deep V-learning's state carried from round to round; :meth:`state_dict` is all a resume needs."""

    def __init__(self, cfg, model: ValueModel, sampler, memory: ReplayBuffer, best: Best):
        self.cfg, self.model, self.sampler, self.memory, self.best = cfg, model, sampler, memory, best
        self.gen = torch.Generator().manual_seed(int(cfg.seed) + 1)
        self.target = copy.deepcopy(model.net)
        self.opt = make_optimizer(model.net, cfg.algo.optimizer, cfg.algo.lr)
        self.done, self.credit, self.frames, self.spent, self.last = 0, 0.0, 0, 0.0, {}

    def state_dict(self) -> dict:
        return {"net": self.model.net.state_dict(), "target": self.target.state_dict(), "opt": self.opt.state_dict(),
                "gen": self.gen.get_state(), "torch_rng": torch.get_rng_state(), "sampler": self.sampler.state_dict(),
                "memory": self.memory.state_dict(), "best": self.best.state_dict(), "done": self.done,
                "credit": self.credit, "frames": self.frames, "spent": self.spent, "last": self.last}

    def load_state_dict(self, s: dict) -> None:
        self.model.net.load_state_dict(s["net"])
        self.target.load_state_dict(s["target"])
        self.opt.load_state_dict(s["opt"])
        self.gen.set_state(s["gen"])
        torch.set_rng_state(s["torch_rng"])  # the memory's sampler draws from torch's global generator
        self.sampler.load_state_dict(s["sampler"])
        self.memory.load_state_dict(s["memory"])
        self.best.load_state_dict(s["best"])
        self.done, self.credit, self.frames, self.spent, self.last = \
            s["done"], s["credit"], s["frames"], s["spent"], s["last"]


def rl_round(lr: Learner, world, val_episodes, log) -> None:
    """One round of ``B`` epsilon-greedy episodes, their targets into the memory, the owed gradient steps."""
    a, model, B = lr.cfg.algo, lr.model, world.B
    eps = epsilon(lr.done + torch.arange(B), a.epsilon_start, a.epsilon_end, a.epsilon_decay)
    model.net.eval()
    look = lookahead_act(model, world, eps, lr.gen)
    r = run_round(model, world, lr.sampler(B), look, thin_draw(world, float(a.thin), lr.gen))
    stored = store(lr.memory, r, round_targets(r, lr.target, model.gamma_bar), bool(a.store_timeouts))
    lr.frames += int(r["active"].sum())
    lr.credit += a.train_batches * B  # gradient steps owed: train_batches per finished episode
    steps = int(lr.credit)
    lr.credit -= steps
    model.net.train()
    loss = fit(model.net, lr.memory, lr.opt, steps) if len(lr.memory) >= a.batch_size else float("nan")
    before, lr.done = lr.done, lr.done + B
    if lr.done // a.target_update > before // a.target_update:
        lr.target.load_state_dict(model.net.state_dict())
    o = r["outcome"]
    lr.last = {"episodes": lr.done, "frames": lr.frames, "epsilon": float(eps[0]),
               "success": float((o == SUCCESS).float().mean()), "collision": float((o == COLLISION).float().mean()),
               "loss": loss, "stored": stored}
    if val_episodes is not None and a.val_every and lr.done // a.val_every > before // a.val_every:
        model.net.eval()
        val = validate(model, world, val_episodes)
        lr.last.update({f"val_{k}": v for k, v in val.items()})
        lr.best.offer(val, lr.done)


def v_learning(cfg, model: ValueModel, world, sampler, memory: ReplayBuffer, log, val_episodes=None,
               resume: dict | None = None, snapshot=None) -> dict:
    """Phase 2: epsilon-greedy deep V-learning (rounds of ``B`` episodes) until ``episodes`` or ``max_minutes``
    (counted over every resumed part). ``snapshot(state)``: called with :meth:`Learner.state_dict` when the
    phase starts, every :data:`SNAPSHOT_S` s and on Ctrl-C; ``resume``: such a state to continue from."""
    a = cfg.algo
    best = Best(model, world, val_episodes if a.keep_best else None, log, score=resume is None)
    lr = Learner(cfg, model, sampler, memory, best)
    if resume is not None:
        lr.load_state_dict(resume)
    t0 = last_snap = time.perf_counter()
    save = (lambda: snapshot(lr.state_dict())) if snapshot is not None else (lambda: None)
    if resume is None:
        save()  # from here on a stopped run resumes without repeating the imitation
    try:
        while lr.done < a.episodes and not (a.max_minutes and lr.spent + time.perf_counter() - t0 > 60 * a.max_minutes):
            rl_round(lr, world, val_episodes, log)
            lr.last["wall_s"] = lr.spent + time.perf_counter() - t0
            log(lr.last)
            if time.perf_counter() - last_snap > SNAPSHOT_S:
                lr.spent, t0, last_snap = lr.spent + time.perf_counter() - t0, time.perf_counter(), time.perf_counter()
                save()
    except KeyboardInterrupt:
        lr.spent += time.perf_counter() - t0
        save()
        raise
    lr.spent += time.perf_counter() - t0
    save()  # a finished run can be extended too (resume=true with a larger algo.episodes / max_minutes)
    model.net.eval()
    best.restore()
    return {**lr.last, "selected_episode": best.episode}


class Best:
    """``algo.keep_best``: the network of the best validation (success, then the shorter navigation time),
    the imitation network included; restored at the end. Selection is on CrowdNav's 100 validation cases,
    never the test cases. ``episodes=None``: inactive, the final network is kept."""

    def __init__(self, model: ValueModel, world, episodes, log, score: bool = True):
        self.model, self.active = model, episodes is not None
        self.state, self.key, self.episode = None, None, None
        if self.active and score:  # (a resumed run restores what was scored instead)
            val = validate(model, world, episodes)
            log({"episodes": 0, **{f"val_{k}": v for k, v in val.items()}})
            self.offer(val, 0)

    def offer(self, val: dict, episode: int) -> None:
        key = (val["success"], -val["nav_time"] if val["success"] > 0 else 0.0)
        if self.active and (self.key is None or key > self.key):
            self.key, self.episode = key, episode
            self.state = copy.deepcopy(self.model.net.state_dict())

    def state_dict(self) -> dict:
        return {"state": self.state, "key": self.key, "episode": self.episode}

    def load_state_dict(self, s: dict) -> None:
        self.state, self.episode = s["state"], s["episode"]
        self.key = tuple(s["key"]) if s["key"] is not None else None

    def restore(self) -> None:
        if self.state is not None:
            self.model.net.load_state_dict(self.state)


def train_value(cfg, out_dir, log=print, resume: bool = False) -> dict:
    """Imitation then deep V-learning per ``cfg`` (``algo=value``, ``env=crowdnav`` or ``env=replay``); writes
    ``out_dir/checkpoint.pt`` (config + the value network as ``actor``) and ``out_dir/train_log.jsonl``; returns the stats.
    ``resume``: continue deep V-learning from ``out_dir/resume.pt`` (the imitation is never repeated)."""
    import json
    from pathlib import Path

    from omegaconf import OmegaConf

    from crowdbench.algos.checkpoint import save_checkpoint
    from crowdbench.envs.factory import env_name, make_world

    if env_name(cfg.env) not in VALUE_WORLDS:
        raise ValueError(f"algo=value runs on env={' or env='.join(VALUE_WORLDS)} (one robot), got env={env_name(cfg.env)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(int(cfg.get("cpus", 1)))
    torch.manual_seed(int(cfg.seed))
    a = cfg.algo
    world, scenario = make_world(cfg.env, int(a.batch))
    sampler = scenario.sampler(int(cfg.seed))
    model = ValueModel(a, cfg.env, OmegaConf.to_container(cfg.encoder, resolve=True))
    memory = make_memory(int(a.capacity), int(a.batch_size))
    log_path = out_dir / "train_log.jsonl"

    def record(d):
        with open(log_path, "a") as f:  # a line per round: readable while the run goes on
            f.write(json.dumps(d) + "\n")
        log(d)

    def save(name: str, wall: float, frames: int, episodes: int, extra: dict | None = None) -> None:
        # "actor": what acts is the value network (the checkpoint loader's required field holds it)
        save_checkpoint(out_dir / name, {"config": OmegaConf.to_container(cfg, resolve=True),
                                         "actor": model.net.state_dict(), "wall_time_s": wall, "frames": frames,
                                         "episodes": episodes, **(extra or {})})

    def snapshot(state: dict) -> None:
        save(RESUME_FILE, spent + time.perf_counter() - t0, 0, state["done"], {"learner": state, "il": il})

    t0, spent, state = time.perf_counter(), 0.0, None
    if resume:
        state = load_resume(out_dir / RESUME_FILE, cfg)
        il, spent = state["il"], float(state["wall_time_s"])
        record({"resumed": True, "episodes": state["learner"]["done"], "wall_time_s": spent})
    else:
        il = imitation(cfg, model, world, sampler, memory, record) if a.il_episodes else {}
        save("checkpoint_il.pt", time.perf_counter() - t0, il.get("il_frames", 0), 0)  # imitation alone
    rl = v_learning(cfg, model, world, sampler, memory, record, scenario.test_list("val"),
                    resume=state and state["learner"], snapshot=snapshot)
    wall = spent + time.perf_counter() - t0
    stats = {"il": il, "rl": rl, "wall_time_s": wall, "privileged": model.lookahead == "query"}
    save("checkpoint.pt", wall, il.get("il_frames", 0) + rl.get("frames", 0), rl.get("episodes", 0))
    record({"done": True, "wall_time_s": wall})
    return stats


def load_resume(path, cfg) -> dict:
    """The snapshot of a stopped run; ValueError (one line) if there is none or it is another recipe's."""
    from omegaconf import OmegaConf

    from crowdbench.algos.checkpoint import load_checkpoint

    if not path.is_file():
        raise ValueError(f"resume=true: {path} not found (a run stopped before deep V-learning began has nothing "
                         "to resume: start it again without resume=true)")
    state = load_checkpoint(path)
    now = OmegaConf.to_container(cfg, resolve=True)
    budget = ("episodes", "max_minutes")  # a resume may extend the budget, nothing else
    strip = lambda c: {**c, "algo": {k: v for k, v in (c.get("algo") or {}).items() if k not in budget}}
    old, now = strip(state["config"]), strip(now)
    differ = sorted(k for k in ("algo", "env", "encoder", "seed") if old.get(k) != now.get(k))
    if differ:
        raise ValueError(f"resume=true: {path} was written with other {', '.join(differ)} settings than these")
    return state
