"""Protocol v2 (docs/reactive_replay.md): protocol v1's episodes with reactive humans, who yield to the
robot through ORCA or social force with the parameters the v2 lists fix (``env.humans=reactive_replay``)."""

from __future__ import annotations

from crowdbench.envs.factory import env_name, replay_humans
from crowdbench.envs.protocol import V2, V2_DIR
from crowdbench.protocols.base import Track
from crowdbench.protocols.replay import ReplayProtocol


class ReactiveReplayProtocol(ReplayProtocol):
    """The humans' future depends on the robot here: no privileged plan exists, so no oracle."""

    name, label = "reactive_replay", V2
    version = "v2"
    list_dir = V2_DIR
    privileged_ok = False
    tracks = (
        Track("v2-orca", "Reactive replay (protocol v2): the recorded pedestrians yield through ORCA",
              "reactive_replay", "orca"),
        Track("v2-sfm", "Reactive replay (protocol v2): the recorded pedestrians yield through social force",
              "reactive_replay", "sfm"),
    )

    def selects(self, env_cfg) -> bool:
        return env_name(env_cfg) == self.world and replay_humans(env_cfg) is not None

    def check(self, cfg, policy_name: str) -> None:
        from crowdbench.policies import PRIVILEGED

        super().check(cfg, policy_name)
        if policy_name in PRIVILEGED:
            raise ValueError(f"the {policy_name} knows the humans' future, which in protocol v2 depends on the robot: "
                             "not available with env.humans=reactive_replay")

    def trained_track(self, env: dict) -> str | None:
        return f"v2-{(env.get('reactive') or {}).get('model', 'orca')}"
