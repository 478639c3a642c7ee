"""The evaluation protocols, one module each, over one engine (crowdbench/protocols/engine.py), and their
registry: replay v1 (``replay``), reactive replay v2 (``reactive_replay``), ``crowdnav`` and ``selfplay``.

``of_config(env)`` is the protocol of a composed ``env`` config (``+env.protocol=NAME`` names one);
``get(name)``, ``names()``, ``register(protocol)``; ``tracks()`` the leaderboard tracks they define.
docs/architecture.md, "How to add a protocol".
"""

from crowdbench.protocols.base import (
    Protocol,
    ProtocolError,
    Track,
    get,
    homes,
    names,
    of_config,
    register,
    registered,
    tracks,
    unregister,
)
from crowdbench.protocols.crowdnav import CrowdNavProtocol
from crowdbench.protocols.reactive_replay import ReactiveReplayProtocol
from crowdbench.protocols.replay import ReplayProtocol
from crowdbench.protocols.selfplay import SelfPlayProtocol

__all__ = ["Protocol", "ProtocolError", "Track", "get", "homes", "names", "of_config", "register", "registered", "tracks",
           "unregister"]

# the order of the leaderboard's tracks (v1, v2-orca, v2-sfm, crowdnav-*) and of of_config's questions
for _protocol in (ReplayProtocol(), ReactiveReplayProtocol(), CrowdNavProtocol(), SelfPlayProtocol()):
    register(_protocol)
