"""IPPO (de Witt et al. 2020): PPO with one shared-weight actor and a decentralised critic, each agent's
value read from its own observation. It is crowdbench/algos/ppo.py, named as the multi-agent literature
names it, beside MAPPO's centralised critic (crowdbench/algos/mappo.py)."""

from __future__ import annotations

from dataclasses import dataclass

from crowdbench.algos.ppo import PPO, PPOConfig
from crowdbench.config_fields import bounded


@dataclass
class IPPOConfig(PPOConfig):
    """``algo=ippo``."""

    name: str = bounded("ippo", choices=("ippo",))


class IPPO(PPO):
    name = "ippo"
    config = IPPOConfig


ALGORITHM = IPPO
