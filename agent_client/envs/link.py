"""What the envs over the wire share: the channel, the checked scenario, the flat vector, the
reward and the goodbye.

`RemoteEnv` (one ego) and `RemoteParallelEnv` (many egos, protocol 1.4) open and leave a server
the same way, judge its welcome and every reply with the same `ReplyChecker`, send the same
scenario options and turn a named observation into the same clipped vector, so that an ego is
seen alike whichever env drives it.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import zmq
from gymnasium import spaces

from agent_client.defaults import CLOSE_TIMEOUT_S
from agent_client.envs.scenario import scenario_options
from agent_client.envs.spaces import observation_space
from agent_client.errors import (
    BridgeError,
    UsageError,
)
from agent_client.transport import connect
from agent_client.transport.channel import Channel
from agent_client.transport.recording import WireRecorder
from agent_client.transport.replies import ReplyChecker, check_welcome
from protocol.messages import (
    Close,
    Observation,
    OptionValue,
    ScenarioInfo,
    Welcome,
)
from protocol.schema import Flattener
from protocol.transport.security import ClientCredentials
from protocol.version import MANY_EGOS_VERSION, format_version

log = logging.getLogger("agent_client")

RewardFn = Callable[[Observation | None, Observation, float], float]
"""reward(prev, obs, dt) -> float (`agent_client.rl.rewards`)."""


def resolve_reward(reward: str | RewardFn) -> RewardFn:
    """A reward function, or the one of `agent_client.rl.rewards` named `reward`."""
    if callable(reward):
        return reward
    from agent_client.rl.rewards import make_reward

    return make_reward(reward)


def open_channel(
    address: str,
    timeout_s: float,
    credentials: ClientCredentials | None,
    recorder: WireRecorder | None,
) -> Channel:
    """A fresh channel to the server, recorded from its first frame if asked."""
    channel = connect(address, timeout_s, credentials)
    if recorder is not None:
        recorder.tap(channel)
    return channel


def say_goodbye(channel: Channel) -> None:
    """Close the session (best effort, short timeout) and release the socket."""
    # The server may be gone or broken: closing our side is all that is left then.
    with contextlib.suppress(BridgeError, zmq.ZMQError, OSError):
        channel.exchange(Close(), timeout_s=CLOSE_TIMEOUT_S)
    channel.close()


@dataclass(frozen=True)
class CheckedScenario:
    """The welcome as the client takes it, and the scenario an env drives on it."""

    welcome: Welcome
    """With every step length known (assumed for a 1.0/1.1 server, see `notes`)."""
    replies: ReplyChecker
    info: ScenarioInfo
    options: dict[str, OptionValue]
    """The options to send with every reset (`agent_client.envs.scenario.scenario_options`)."""
    notes: list[str]
    """What was assumed about the welcome, for a warning."""

    @property
    def all_options(self) -> dict[str, OptionValue]:
        """Every option of the scenario, its defaults overridden by `options`."""
        return {**self.info.options, **self.options}


def check_scenario(
    welcome: Welcome, address: str, scenario: str, options: dict[str, OptionValue]
) -> CheckedScenario:
    """Refuses early: an unknown scenario or option (`UsageError`), a welcome that breaks the
    protocol (`InvalidReply`); a 1.0/1.1 server without a step length gets one assumed, with a
    note (`replies.check_welcome`). ``egos`` and ``ego_share`` are no options here: they make every
    reply a multi-ego frame, which `RemoteParallelEnv` (its own arguments of those names) reads."""
    for name in ("egos", "ego_share"):
        if name in options:
            raise UsageError(
                f"option {name} starts a multi-ego episode: drive many egos with "
                f"agent_client.RemoteParallelEnv(address, scenario, {name}=...)"
            )
    offered = {s.name: s for s in welcome.scenarios}
    if scenario not in offered:
        raise UsageError(
            f"server at {address} offers no scenario {scenario!r}; offered: {', '.join(offered)}"
        )
    source = f"invalid reply from {address}"
    welcome, notes = check_welcome(welcome, source, scenario)
    info = next(s for s in welcome.scenarios if s.name == scenario)
    wanted = scenario_options(info, options, address)
    return CheckedScenario(welcome, ReplyChecker(welcome, source), info, wanted, notes)


class ObservationVector:
    """The flat float32 vector of the server's schema (`protocol.schema`), clipped into the
    finite bounds of its Box (`agent_client.envs.spaces.observation_space`)."""

    def __init__(self, welcome: Welcome) -> None:
        self.flatten = Flattener(welcome.observation_fields)
        self.space: spaces.Box = observation_space(
            welcome.observation_fields, welcome.sensor_range, welcome.action
        )

    def __call__(self, obs: Observation) -> np.ndarray:
        vector = np.asarray(self.flatten(obs), dtype=np.float32)
        return np.clip(vector, self.space.low, self.space.high)


def refuse_one_ego_server(welcome: Welcome, address: str, who: str) -> None:
    """Refuse (`UsageError`) a 1.x server before `MANY_EGOS_VERSION`: it drives one ego (another
    major version is refused by the welcome's own checks). `who` names what needs many."""
    refuse_old_server(welcome, address, MANY_EGOS_VERSION, who, "many egos in one simulation")


def refuse_old_server(
    welcome: Welcome, address: str, version: tuple[int, int], who: str, what: str
) -> None:
    """Refuse (`UsageError`) a 1.x server older than `version`, which brought `what`."""
    major, minor = welcome.protocol
    if major == version[0] and (major, minor) < version:
        raise UsageError(
            f"server at {address} speaks protocol {format_version(welcome.protocol)}: {who} "
            f"needs {format_version(version)} or newer ({what}, docs/protocol.md §3.1)"
        )
