"""Collected ``[B, T]`` batches with an agent group ``[B, T, A]`` -> per-agent replay transitions and episode stats.

Self-play stores one transition per *agent* and step: the agent dimension is flattened into
the batch and kept as a singleton agent dimension (``[N * A, 1, ...]``). Why: (1) the buffer
then holds exactly the single-robot layout, so the TorchRL losses, priorities (one per
transition) and ``n_agents=1`` action specs are the replay ones, unchanged; (2) a done agent
waits, frozen and with zero reward, for the rest of its environment: those steps are not
transitions of the MDP and are dropped here (its sticky ``done`` was already set before the
step), which a ``[B, A]`` layout could only express with masks inside every loss; (3) every
agent's experience counts as a sample of the one shared-weight policy, which is what
parameter sharing means. With one agent (replay env) nothing is dropped and this is
``batch.reshape(-1)``.
"""

from __future__ import annotations

from tensordict import TensorDict, TensorDictBase

from crowdbench.envs.observation import GROUP


def agent_transitions(batch: TensorDictBase, keep: list) -> TensorDict:
    """``[N * A_valid]`` transitions with a singleton agent dim: ``keep`` keys of agents running at step start."""
    td = batch.select(*keep, (GROUP, "done")).reshape(-1)
    n, a = td[GROUP].batch_size
    flat = TensorDict({GROUP: td[GROUP].reshape(n * a).unsqueeze(1),
                       "next": {GROUP: td["next", GROUP].reshape(n * a).unsqueeze(1)}}, batch_size=[n * a])
    running = ~flat[GROUP, "done"].reshape(n * a)
    return flat[running].exclude((GROUP, "done"))


def finished_episodes(batch: TensorDictBase, return_key) -> tuple[list[int], list[float]]:
    """Outcome code and undiscounted return of every agent episode that ended in ``batch``."""
    ended = (batch["next", GROUP, "done"] & ~batch[GROUP, "done"]).squeeze(-1)  # [B, T, A]
    outcome = batch["next", GROUP, "info", "outcome"][ended]
    ret = batch["next", return_key].squeeze(-1)[ended]
    return outcome.tolist(), ret.tolist()
