"""`RemoteEnv`: a Gymnasium environment whose simulator runs in another process.

Observations are the flat float32 vector announced by the server's schema (the named
`protocol.Observation` is in ``info["observation"]``); actions are a dict of a longitudinal
acceleration (m/s^2, within the server's bounds) and a lane change (-1 right, 0 keep, +1 left).
The reward is computed here, on the learner's side, from the observations alone.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import zmq
from gymnasium import spaces

from agent_client.defaults import CLOSE_TIMEOUT_S, DEFAULT_SCENARIO, RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.errors import (
    BridgeError,
    MalformedReply,
    ServerError,
    ServerTimeout,
    ServerUnavailable,
    UsageError,
)
from agent_client.transport import connect
from agent_client.transport.channel import Channel
from protocol.messages import Close, Observation, OptionValue, Reset, Step, Welcome
from protocol.schema import Flattener
from protocol.transport.endpoint import DEFAULT_ADDRESS
from protocol.transport.security import ClientCredentials

RewardFn = Callable[[Observation | None, Observation, float], float]

ActionDict = Mapping[str, Any]


class RemoteEnv(gym.Env[np.ndarray, ActionDict]):
    """One ego vehicle in a remote simulator, behind the bridge protocol."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        address: str = DEFAULT_ADDRESS,
        scenario: str = DEFAULT_SCENARIO,
        *,
        reward: str | RewardFn = "safe",
        timeout_s: float = STEP_TIMEOUT_S,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        credentials: ClientCredentials | None = None,
        **options: OptionValue,
    ) -> None:
        """Connect and shake hands; `options` are scenario options sent with every reset.

        `credentials` (CURVE keys) default to $AV_BRIDGE_SERVER_KEY / $AV_BRIDGE_SECRET_KEY.
        """
        self.address = address
        self.scenario = scenario
        self.options = dict(options)
        self.reset_timeout_s = reset_timeout_s
        self.reward_fn = _resolve_reward(reward)
        self.timeout_s = timeout_s
        self._credentials = credentials
        self._connection: Channel = connect(address, timeout_s, credentials)
        try:
            self.welcome: Welcome = self._connection.hello(timeout_s)
            self.scenario_options = self._check_scenario()
            self.flatten = self._check_schema()
        except Exception:
            self.close()  # free the server for the next client, then report
            raise
        self.step_length = next(s.step_length for s in self.welcome.scenarios if s.name == scenario)
        schema = self.welcome.action
        self.action_space = spaces.Dict(
            {
                "acceleration": spaces.Box(
                    schema.acceleration_min, schema.acceleration_max, (1,), np.float32
                ),
                "lane_change": spaces.Discrete(3, start=-1),
            }
        )
        self.observation_space = spaces.Box(-np.inf, np.inf, (len(self.flatten.names),), np.float32)
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

    def step(self, action: ActionDict) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.send_step(action)
        return self.receive_step()

    # The two halves of reset and step, so that a vector env can keep several servers busy.

    def send_reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        super().reset(seed=seed)
        self._episode_seed = int(seed) if seed is not None else int(self.np_random.integers(2**31))
        request = Reset(self.scenario, self._episode_seed, {**self.options, **(options or {})})
        self._connection.send(request)

    def receive_reset(self) -> tuple[np.ndarray, dict[str, Any]]:
        obs = self._observation(self._connection.receive_checked(self.reset_timeout_s))
        self._seq, self._last, self._done = 0, obs, False
        return self._vector(obs), {"observation": obs, "seed": self._episode_seed}

    def send_step(self, action: ActionDict) -> None:
        if self._done:
            raise gym.error.ResetNeeded("the episode has ended (or never started): call reset()")
        acceleration, lane_change = _parse_action(action)
        self._seq += 1
        self._connection.send(Step(self._seq, acceleration, lane_change))

    def receive_step(self) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs = self._observation(self._connection.receive_checked())
        prev, self._last = self._last, obs
        elapsed = obs.time - prev.time if prev is not None else 0.0
        reward = float(self.reward_fn(prev, obs, elapsed))
        self._done = obs.terminated or obs.truncated
        return self._vector(obs), reward, obs.terminated, obs.truncated, {"observation": obs}

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
        self._connection = connect(self.address, self.timeout_s, self._credentials)
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
        if Flattener(welcome.observation_fields).names != self.flatten.names:
            raise MalformedReply(f"{self.address} came back with another observation schema")
        self.welcome = welcome

    def close(self) -> None:
        """Say goodbye (best effort, short timeout) and release the socket."""
        if getattr(self, "_connection", None) is None:
            return
        # The server may be gone or broken: closing our side is all that is left then.
        with contextlib.suppress(BridgeError, zmq.ZMQError, OSError):
            self._connection.exchange(Close(), timeout_s=CLOSE_TIMEOUT_S)
        self._connection.close()
        self._connection = None  # type: ignore[assignment]

    # ----------------------------------------------------------------------- helpers

    def _check_scenario(self) -> dict[str, OptionValue]:
        """The scenario's full options; refuses unknown scenarios and options early."""
        offered = {s.name: s for s in self.welcome.scenarios}
        if self.scenario not in offered:
            raise UsageError(
                f"server at {self.address} offers no scenario {self.scenario!r}; "
                f"offered: {', '.join(offered)}"
            )
        known = offered[self.scenario].options
        unknown = set(self.options) - set(known)
        if unknown:
            raise UsageError(
                f"scenario {self.scenario} has no option {sorted(unknown)[0]!r}; "
                f"known: {', '.join(known)}"
            )
        return {**known, **self.options}

    def _check_schema(self) -> Flattener:
        """The server's schemas must be usable: known fields, sensible action bounds."""
        schema = self.welcome.action
        if not schema.acceleration_min < schema.acceleration_max:
            raise MalformedReply(
                f"welcome from {self.address}: acceleration bounds "
                f"[{schema.acceleration_min}, {schema.acceleration_max}] are empty"
            )
        try:
            return Flattener(self.welcome.observation_fields)
        except ValueError as exc:
            raise MalformedReply(f"welcome from {self.address}: {exc}") from exc

    @property
    def last_observation(self) -> Observation | None:
        """The named observation of the last reset or step."""
        return self._last

    def _vector(self, obs: Observation) -> np.ndarray:
        return np.asarray(self.flatten(obs), dtype=np.float32)

    @staticmethod
    def _observation(reply: object) -> Observation:
        if not isinstance(reply, Observation):
            raise MalformedReply(f"expected an observation, got {type(reply).__name__}")
        return reply


def _parse_action(action: ActionDict | float) -> tuple[float, int]:
    """Accept ``{"acceleration": [a], "lane_change": k}`` (or a bare acceleration)."""
    if isinstance(action, Mapping):
        acceleration = float(np.asarray(action["acceleration"], dtype=np.float64).reshape(-1)[0])
        lane_change = int(action.get("lane_change", 0))
    else:
        acceleration, lane_change = float(np.asarray(action).reshape(-1)[0]), 0
    if not np.isfinite(acceleration):
        raise ValueError(f"acceleration must be finite, got {acceleration}")
    if lane_change not in (-1, 0, 1):
        raise ValueError(f"lane_change must be -1, 0 or 1, got {lane_change}")
    return acceleration, lane_change


def _resolve_reward(reward: str | RewardFn) -> RewardFn:
    if callable(reward):
        return reward
    from agent_client.rl.rewards import make_reward

    return make_reward(reward)
