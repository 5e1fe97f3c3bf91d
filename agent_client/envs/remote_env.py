"""`RemoteEnv`: a Gymnasium environment whose simulator runs in another process.

Observations are the flat float32 vector announced by the server's schema, with finite bounds
(the named `protocol.Observation` is in ``info["observation"]``); actions encode a longitudinal
acceleration (m/s^2, within the server's bounds) and a lane change (-1 right, 0 keep, +1 left) in
the space chosen with ``action_space`` (`agent_client.envs.spaces`: a flat normalised Box by
default, which Stable-Baselines3 and RLlib take as it is; the Dict on request). The reward is
computed here, on the learner's side, from the observations alone.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from agent_client.defaults import DEFAULT_SCENARIO, RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.envs.link import (
    CheckedScenario,
    ObservationVector,
    RewardFn,
    check_scenario,
    open_channel,
    resolve_reward,
    say_goodbye,
)
from agent_client.envs.scenario import first_observation
from agent_client.envs.spaces import (
    ACTION_SPACES,
    DEFAULT_ACCELERATION_LEVELS,
    ActionEncoding,
    decode_named,
    make_action_encoding,
)
from agent_client.errors import (
    MalformedReply,
    ServerError,
    ServerTimeout,
    ServerUnavailable,
    UsageError,
)
from agent_client.transport.channel import Channel
from agent_client.transport.recording import WireRecorder
from agent_client.transport.replies import ReplyChecker, check_welcome
from protocol.messages import Error, Observation, OptionValue, Reset, Step, Welcome
from protocol.schema import Flattener
from protocol.transport.endpoint import DEFAULT_ADDRESS
from protocol.transport.security import ClientCredentials

ActionDict = Mapping[str, Any]


class RemoteEnv(gym.Env[np.ndarray, Any]):
    """One ego vehicle in a remote simulator, behind the bridge protocol.

    ``action_space="auto"`` (the default) is a ``Box(-1, 1, (1,))`` acceleration on a one-lane
    road and the hybrid ``Box(-1, 1, (2,))`` (acceleration, lane choice) on a road with several;
    ``"box"``, ``"hybrid"``, ``"discrete"``, ``"multi_discrete"`` and ``"dict"`` choose one
    (`agent_client.envs.spaces`). For ``"auto"`` and the discrete ones the lane count comes from
    the first observation: asked for before any reset, ``action_space`` resets once to find
    out. `step` also takes the named form ``{"acceleration": [a], "lane_change": k}`` in m/s²
    whatever the space.

    `scenario` may also be several scenarios of the server: each episode then drives the one its
    seed picks (`scenario_for`), so that one policy learns them all and the same seed always
    gives the same episode; an option goes to the scenarios that offer it.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        address: str = DEFAULT_ADDRESS,
        scenario: str | Sequence[str] = DEFAULT_SCENARIO,
        *,
        reward: str | RewardFn = "safe",
        timeout_s: float = STEP_TIMEOUT_S,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        credentials: ClientCredentials | None = None,
        action_space: str = "auto",
        acceleration_levels: int = DEFAULT_ACCELERATION_LEVELS,
        recorder: WireRecorder | None = None,
        **options: OptionValue,
    ) -> None:
        """Connect and shake hands; `options` are scenario options sent with every reset.

        `credentials` (CURVE keys) default to $AV_BRIDGE_SERVER_KEY / $AV_BRIDGE_SECRET_KEY.
        `action_space` is one of `agent_client.envs.spaces.ACTION_SPACES`;
        `acceleration_levels` the number of accelerations of the discrete encodings.
        `recorder` records the whole wire stream, the hello included (docs/recording.md).
        """
        if action_space not in ACTION_SPACES:
            raise UsageError(
                f"action_space {action_space!r} is not one of: {', '.join(ACTION_SPACES)}"
            )
        if acceleration_levels < 2:
            raise UsageError(f"acceleration_levels must be at least 2, got {acceleration_levels}")
        self.address = address
        self.scenarios: tuple[str, ...] = (
            (scenario,) if isinstance(scenario, str) else tuple(scenario)
        )
        """The scenarios episodes are drawn from (by seed), in order."""
        if not self.scenarios or len(set(self.scenarios)) != len(self.scenarios):
            raise UsageError(f"scenarios must be distinct and at least one, got {scenario!r}")
        self.scenario = self.scenarios[0]
        """The scenario of the running episode (or of the next, once `send_reset` picked it)."""
        self.requested_options = dict(options)
        """The options asked for, before each scenario takes those it offers (`options`)."""
        self.reset_timeout_s = reset_timeout_s
        self.reward_fn = resolve_reward(reward)
        self.timeout_s = timeout_s
        self._credentials = credentials
        self._recorder = recorder
        self._connection: Channel = self._connect()
        try:
            self.welcome: Welcome = self._connection.hello(timeout_s)
            self._checked = self._check_scenarios()
            self.flatten = self._check_schema()
        except Exception:
            self.close()  # free the server for the next client, then report
            raise
        self._action_space_name = action_space
        self._acceleration_levels = acceleration_levels
        self._encoding: ActionEncoding | None = None
        if action_space in ("box", "hybrid", "dict"):  # the others depend on the lane count
            self._encoding = make_action_encoding(
                action_space, self.welcome.action, True, acceleration_levels
            )
        self._vectors = ObservationVector(self.welcome)
        self.observation_space = self._vectors.space
        self._seq = 0
        self._last: Observation | None = None
        self._done = True
        self._episode_seed = 0

    # ----------------------------------------------------------------------- gymnasium API

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        self.send_reset(seed=seed, options=options)
        return self.receive_reset()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.send_step(action)
        return self.receive_step()

    @property
    def episode_seed(self) -> int:
        """The seed the current episode runs with: the one asked for, or the one an insertion
        retry moved to (`agent_client.envs.scenario`)."""
        return self._episode_seed

    # The two halves of reset and step, so that a vector env can keep several servers busy.

    def send_reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        super().reset(seed=seed)
        self._episode_seed = int(seed) if seed is not None else int(self.np_random.integers(2**31))
        self.scenario = self.scenario_for(self._episode_seed)
        extra = options or {}
        if len(self.scenarios) > 1:  # what this scenario offers of the caller's options
            extra = {k: v for k, v in extra.items() if k in self.scenario_options}
        request = Reset(self.scenario, self._episode_seed, {**self.options, **extra})
        self._connection.send(request)

    def scenario_for(self, seed: int) -> str:
        """The scenario an episode of `seed` drives: the only one, or of several the one at
        `seed` modulo their number (an insertion retry keeps its episode's)."""
        return self.scenarios[seed % len(self.scenarios)]

    @property
    def options(self) -> dict[str, OptionValue]:
        """The options sent with every reset of the current scenario: those asked for that it
        offers."""
        return self._checked[self.scenario].options

    @property
    def scenario_options(self) -> dict[str, OptionValue]:
        """Every option of the current scenario, its defaults overridden by `options`."""
        return self._checked[self.scenario].all_options

    @property
    def step_length(self) -> float | None:
        """The current scenario's simulation step (s)."""
        return self._checked[self.scenario].info.step_length

    def receive_reset(self) -> tuple[np.ndarray, dict[str, Any]]:
        obs = self.receive_reset_observation()
        return self._vector(obs), {"observation": obs, "seed": self._episode_seed}

    def send_step(self, action: Any) -> None:
        if isinstance(action, Mapping):  # the named form, whatever the space
            self.send_command(*decode_named(action))
        else:
            self.send_command(*self.action_encoding.decode(action))

    def receive_step(self) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward = self.receive_observation()
        return self._vector(obs), reward, obs.terminated, obs.truncated, {"observation": obs}

    # The named path, for drivers and the trainer: no flat vector, no action parsing.

    def receive_reset_observation(self) -> Observation:
        """The first observation of the episode `send_reset` started, checked against the
        protocol; an ego that could not enter is retried on other seeds, then `InsertionFailed`
        (`agent_client.envs.scenario.first_observation`)."""
        obs, seed = first_observation(self._connection, self._replies, self.reset_timeout_s)
        if seed is not None:
            self._episode_seed = seed
        self._seq, self._last, self._done = 0, obs, False
        return obs

    def send_command(self, acceleration: float, lane_change: int) -> None:
        """Send one decision: an acceleration (m/s^2) and a lane change (-1, 0, +1)."""
        if self._done:
            raise gym.error.ResetNeeded("the episode has ended (or never started): call reset()")
        if not math.isfinite(acceleration):
            raise ValueError(f"acceleration must be finite, got {acceleration}")
        if lane_change not in (-1, 0, 1):
            raise ValueError(f"lane_change must be -1, 0 or 1, got {lane_change}")
        self._seq += 1
        self._connection.send(Step(self._seq, float(acceleration), int(lane_change)))

    def receive_observation(self) -> tuple[Observation, float]:
        """The observation after the decision `send_command` sent (checked against the protocol:
        `InvalidReply`), and its reward."""
        reply = self._connection.receive()
        obs = self._observation(self._replies.check(self._connection.sent, reply))
        prev, self._last = self._last, obs
        elapsed = obs.time - prev.time if prev is not None else 0.0
        reward = float(self.reward_fn(prev, obs, elapsed))
        self._done = obs.terminated or obs.truncated
        return obs, reward

    def reconnect(self, timeout_s: float) -> None:
        """After `ServerUnavailable`: connect afresh and shake hands, waiting up to `timeout_s`.

        For a server that restarts (or a network that comes back). The running episode is lost:
        call `reset` next. Raises `ServerUnavailable` if no server answered in time, and
        `MalformedReply` if the server came back with another observation schema.
        """
        deadline = time.monotonic() + timeout_s
        if self._connection is not None:
            self._connection.close()
        self._done, self._last = True, None
        self._connection = self._connect()
        while True:
            remaining = deadline - time.monotonic()
            try:
                welcome = self._connection.hello(timeout_s=max(0.1, remaining))
                break
            except ServerError as exc:
                if exc.code != "busy" or remaining <= 0:
                    raise
                time.sleep(min(1.0, remaining))  # back off: another client still holds it
            except ServerUnavailable:
                if time.monotonic() >= deadline:
                    raise ServerTimeout(
                        f"no server at {self.address} came back within {timeout_s:g} s"
                    ) from None
        source = f"invalid reply from {self.address}"
        welcome, _ = check_welcome(welcome, source, self.scenario)
        if Flattener(welcome.observation_fields).names != self.flatten.names:
            raise MalformedReply(f"{self.address} came back with another observation schema")
        self.welcome, self._replies = welcome, ReplyChecker(welcome, source)

    @property
    def connection(self) -> Channel:
        """The channel to the server now (`reconnect` replaces it): for a collector that runs
        another kind of episode, such as a multi-ego one, in this env's session."""
        return self._connection

    def close(self) -> None:
        """Say goodbye (best effort, short timeout) and release the socket."""
        if getattr(self, "_connection", None) is None:
            return
        say_goodbye(self._connection)
        self._connection = None  # type: ignore[assignment]

    # ----------------------------------------------------------------------- helpers

    def _connect(self) -> Channel:
        """A fresh channel to the server, recorded from its first frame if asked."""
        return open_channel(self.address, self.timeout_s, self._credentials, self._recorder)

    def _check_scenarios(self) -> dict[str, CheckedScenario]:
        """Each scenario as checked against the welcome. Refuses early: an unknown scenario or
        option (`UsageError`: of several scenarios, an option none of them offers), a welcome
        that breaks the protocol (`InvalidReply`); a 1.0/1.1 server without a step length gets
        one assumed, with a warning (`replies.check_welcome`)."""
        asked, checked = self.requested_options, {}
        for name in self.scenarios:
            wanted = asked
            if len(self.scenarios) > 1:
                offered = next((s.options for s in self.welcome.scenarios if s.name == name), {})
                wanted = {k: v for k, v in asked.items() if k in offered}
            checked[name] = check_scenario(self.welcome, self.address, name, wanted)
        offered_by_some = set().union(*(c.info.options for c in checked.values()))
        unknown = sorted(set(asked) - offered_by_some - {"decision_interval"})
        if unknown:
            raise UsageError(
                f"no scenario of {', '.join(self.scenarios)} has option {unknown[0]!r}; "
                f"known: {', '.join(sorted(offered_by_some))}"
            )
        first = checked[self.scenarios[0]]
        for note in first.notes:
            warnings.warn(note, stacklevel=3)
        self.welcome, self._replies = first.welcome, first.replies
        return checked

    def _check_schema(self) -> Flattener:
        """The flat vector of the server's schema (`_check_scenario` checked the welcome)."""
        return Flattener(self.welcome.observation_fields)

    # ----------------------------------------------------------------------- action spaces

    @property  # type: ignore[override]
    def action_space(self) -> spaces.Space[Any]:
        """The space of the chosen action encoding (`agent_client.envs.spaces`)."""
        return self.action_encoding.space

    @action_space.setter
    def action_space(self, space: spaces.Space[Any]) -> None:
        raise AttributeError("choose the action space with RemoteEnv(action_space=NAME)")

    @property
    def action_encoding(self) -> ActionEncoding:
        """The encoding that `step` decodes; for ``"auto"``, fixed by the first lane count seen."""
        if self._encoding is None:
            several = self._lane_count() > 1
            self._encoding = make_action_encoding(
                self._action_space_name, self.welcome.action, several, self._acceleration_levels
            )
        return self._encoding

    def _lane_count(self) -> int:
        """Lanes of the ego's road: from the last observation, else from one reset (seed 0) whose
        episode is then dropped (the next `reset` starts the caller's own)."""
        if self._last is not None:
            return self._last.ego.lane_count
        self._connection.send(Reset(self.scenario, 0, dict(self.options)))
        lane_count = self.receive_reset_observation().ego.lane_count
        self._seq, self._last, self._done = 0, None, True
        return lane_count

    @property
    def last_observation(self) -> Observation | None:
        """The named observation of the last reset or step."""
        return self._last

    def _vector(self, obs: Observation) -> np.ndarray:
        return self._vectors(obs)

    @staticmethod
    def _observation(reply: object) -> Observation:
        if isinstance(reply, Error):
            raise ServerError(reply.code, reply.message)
        if not isinstance(reply, Observation):
            raise MalformedReply(f"expected an observation, got {type(reply).__name__}")
        return reply
