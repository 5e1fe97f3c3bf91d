"""`RemoteParallelEnv`: the egos of one remote simulation as the agents of a PettingZoo
`ParallelEnv`.

Since protocol 1.4 a server may drive several egos in one simulation (docs/protocol.md §3.1): a
reset naming ``egos`` N is answered with every ego's observation, and every step carries one
command per ego still driving. Here each ego is an agent named by its id on the wire (``ego.0``,
``ego.1``, ... on our servers; ``ego`` for a one-ego server's single ego). Per agent everything
is `RemoteEnv`'s: the flat observation vector with its finite bounds, the action encoding
(``action_space``, `agent_client.envs.spaces`; the named form too), the reward function of two
consecutive observations, the reply checks and every deadline (`agent_client.envs.link`). An
ego whose drive ends (a collision, the end of the road, a stop, the time limit) gets its last
observation with its termination or truncation and then leaves `agents`; the episode is over
once `agents` is empty. With ``ego_share`` (protocol 1.5) the egos are a share of the traffic
and the vehicles that enter during the episode join it: they appear in `agents` (and in
`possible_agents`, which then grows) with their first observation.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding

from agent_client.defaults import DEFAULT_SCENARIO, RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.envs.link import (
    ObservationVector,
    RewardFn,
    check_scenario,
    open_channel,
    refuse_old_server,
    refuse_one_ego_server,
    resolve_reward,
    say_goodbye,
)
from agent_client.envs.scenario import SEEDS, first_reply, scenario_options
from agent_client.envs.spaces import (
    ACTION_SPACES,
    DEFAULT_ACCELERATION_LEVELS,
    ActionEncoding,
    decode_named,
    make_action_encoding,
)
from agent_client.errors import MalformedReply, ServerError, UsageError
from agent_client.transport.recording import WireRecorder
from agent_client.transport.replies import ego_observation
from protocol.errors import ErrorCode
from protocol.messages import (
    Command,
    Error,
    MultiObservation,
    MultiStep,
    Observation,
    OptionValue,
    Reset,
    Welcome,
)
from protocol.transport.endpoint import DEFAULT_ADDRESS
from protocol.transport.security import ClientCredentials
from protocol.version import EGO_SHARE_VERSION

try:
    from pettingzoo import ParallelEnv
except ModuleNotFoundError as exc:  # the extra is not installed
    raise ModuleNotFoundError(
        "RemoteParallelEnv needs PettingZoo: pip install 'av-bridge[pettingzoo]'", name=exc.name
    ) from exc

"""The first protocol version with many egos in one simulation (§3.1)."""
_EPISODE_ENDERS = frozenset({ErrorCode.INSERTION_FAILED.value, ErrorCode.SIMULATOR_ERROR.value})


class RemoteParallelEnv(ParallelEnv[str, np.ndarray, Any]):
    """The egos of one remote simulation, stepped together (PettingZoo's parallel API).

    `possible_agents` are the ego ids of the first reset (asked for before any reset, they
    reset once, seed 0, to find out; with `ego_share`, every ego seen so far), `agents` those
    still driving. Every agent has
    `RemoteEnv`'s observation and action spaces (one object per agent, always the same);
    ``action_space="auto"`` takes the lane count of the first observation, as `RemoteEnv`
    does. `step` takes one action per agent in `agents`, in any of the encoding's forms or the
    named ``{"acceleration": [a], "lane_change": k}`` in m/s², and returns one observation,
    reward, termination, truncation and info (``info["observation"]``: the named
    `protocol.Observation`) per agent that drove into the step, the ended ones for the last
    time. The reward function is shared by all egos: it is called for each with that ego's two
    consecutive observations. An ego that joins (`ego_share`) comes with reward 0 and
    ``info["joined"]`` True.
    """

    metadata: dict[str, Any] = {
        "name": "av_bridge_remote_parallel_v0",
        "render_modes": [],
        "is_parallelizable": True,
    }

    def __init__(
        self,
        address: str = DEFAULT_ADDRESS,
        scenario: str = DEFAULT_SCENARIO,
        *,
        egos: int | None = None,
        ego_share: float | None = None,
        reward: str | RewardFn = "safe",
        timeout_s: float = STEP_TIMEOUT_S,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        credentials: ClientCredentials | None = None,
        action_space: str = "auto",
        acceleration_levels: int = DEFAULT_ACCELERATION_LEVELS,
        recorder: WireRecorder | None = None,
        **options: OptionValue,
    ) -> None:
        """Connect and shake hands; `egos` is the number of egos of every episode, or
        `ego_share` their share of the traffic (one of the two); `options` are scenario options
        sent with every reset; the rest as `RemoteEnv`'s.

        Refused before any reset (`UsageError`): a server older than protocol 1.4 (1.5 for
        `ego_share`), a scenario without the ``egos`` (``ego_share``) option, an option or
        argument the scenario or env does not know.
        """
        many = _many_option(egos, ego_share)
        if action_space not in ACTION_SPACES:
            raise UsageError(
                f"action_space {action_space!r} is not one of: {', '.join(ACTION_SPACES)}"
            )
        if acceleration_levels < 2:
            raise UsageError(f"acceleration_levels must be at least 2, got {acceleration_levels}")
        self.address = address
        self.scenario = scenario
        self.egos = egos
        self.ego_share = ego_share
        self._many = many
        """The reset option that makes the episodes multi-ego: {"egos": N} or {"ego_share": x}."""
        self.timeout_s = timeout_s
        self.reset_timeout_s = reset_timeout_s
        self.reward_fn = resolve_reward(reward)
        self._connection = open_channel(address, timeout_s, credentials, recorder)
        try:
            welcome = self._connection.hello(timeout_s)
            _refuse_old(welcome, address, ego_share is not None)
            checked = check_scenario(welcome, address, scenario, dict(options))
            (name,) = many
            if name not in checked.info.options:
                drives = (
                    "its server drives one ego (use RemoteEnv)"
                    if name == "egos"
                    else "its server places a number of egos (use egos=N)"
                )
                raise UsageError(
                    f"scenario {scenario} at {address} has no option {name}: {drives}; "
                    "options: " + ", ".join(checked.info.options)
                )
        except Exception:
            self.close()  # free the server for the next client, then report
            raise
        for note in checked.notes:
            warnings.warn(note, stacklevel=2)
        self.welcome: Welcome = checked.welcome
        self._replies = checked.replies
        self._info = checked.info
        self.options = checked.options
        self.scenario_options = checked.all_options
        self.step_length = checked.info.step_length
        self._vectors = ObservationVector(self.welcome)
        self.flatten = self._vectors.flatten
        self._action_space_name = action_space
        self._acceleration_levels = acceleration_levels
        self._encoding: ActionEncoding | None = None
        if action_space in ("box", "hybrid", "dict"):  # the others depend on the lane count
            self._encoding = make_action_encoding(
                action_space, self.welcome.action, True, acceleration_levels
            )
        self._observation_spaces: dict[str, spaces.Space[Any]] = {}
        self._action_spaces: dict[str, spaces.Space[Any]] = {}
        self._possible: list[str] | None = None
        self._seen: set[str] = set()
        """The ids in `_possible` (with ego_share it grows, and a later episode's egos often
        have an earlier one's ids: SUMO numbers each flow's vehicles from 0 at every load)."""
        self._lane_count: int | None = None
        self.agents: list[str] = []
        self._last: dict[str, Observation] = {}
        self._frame: MultiObservation | None = None
        self._seq = 0
        self._rng: np.random.Generator | None = None
        self._episode_seed = 0

    # ----------------------------------------------------------------------- PettingZoo API

    @property
    def possible_agents(self) -> list[str]:
        """The ego ids of the first reset, in the server's stable order (with `ego_share`, every
        ego seen so far, in the order first seen)."""
        if self._possible is None:
            self._probe()
        assert self._possible is not None
        return list(self._possible)

    @possible_agents.setter
    def possible_agents(self, agents: list[str]) -> None:
        raise AttributeError("possible_agents are the server's ego ids of the first reset")

    def observation_space(self, agent: str) -> spaces.Space[Any]:
        """The flat vector's Box (`RemoteEnv.observation_space`), the same object every call."""
        space = self._observation_spaces.get(agent)
        if space is None:
            self._known(agent)
            space = self._observation_spaces[agent] = copy.deepcopy(self._vectors.space)
        return space

    def action_space(self, agent: str) -> spaces.Space[Any]:
        """The chosen encoding's space (`RemoteEnv.action_space`), the same object every call."""
        space = self._action_spaces.get(agent)
        if space is None:
            self._known(agent)
            space = self._action_spaces[agent] = copy.deepcopy(self.action_encoding.space)
        return space

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start an episode of `egos` egos; `options` override scenario options for it (a name
        the scenario does not offer is ignored, with a warning). Without a seed, one is drawn
        from the generator the last seed started."""
        if seed is not None or self._rng is None:
            self._rng, _ = seeding.np_random(seed)
        self._episode_seed = int(seed) if seed is not None else int(self._rng.integers(SEEDS))
        wanted = {**self.options, **self._episode_options(options or {}), **self._many}
        self._connection.send(Reset(self.scenario, self._episode_seed, wanted))
        frame, retried = first_reply(
            self._connection, self._replies, self.reset_timeout_s, MultiObservation
        )
        if retried is not None:
            self._episode_seed = retried
        self._start(frame)
        observations = {ego.id: self._vectors(self._last[ego.id]) for ego in frame.egos}
        infos = {
            ego.id: {"observation": self._last[ego.id], "seed": self._episode_seed}
            for ego in frame.egos
        }
        return observations, infos

    def step(
        self, actions: Mapping[str, Any]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """One decision of every agent still driving; see the class for what comes back."""
        if not self.agents:
            raise gym.error.ResetNeeded("no ego is driving (the episode has ended): call reset()")
        commands = self._commands(actions)
        self._seq += 1
        self._connection.send(MultiStep(self._seq, commands))
        frame = self._frame_of(self._connection.receive())
        observations, rewards, infos = {}, {}, {}
        for ego in frame.egos:
            obs = ego_observation(frame, ego)
            prev = self._last.get(ego.id)
            observations[ego.id] = self._vectors(obs)
            if prev is None:  # it joins (the reply checks let only an ego_share episode's in)
                self._see([ego.id])
                rewards[ego.id], infos[ego.id] = 0.0, {"observation": obs, "joined": True}
            else:
                rewards[ego.id] = float(self.reward_fn(prev, obs, obs.time - prev.time))
                infos[ego.id] = {"observation": obs}
            self._last[ego.id] = obs
        self._frame = frame
        over = frame.terminated or frame.truncated
        self.agents = (
            [] if over else [e.id for e in frame.egos if not (e.terminated or e.truncated)]
        )
        terminations = {ego.id: ego.terminated for ego in frame.egos}
        truncations = {ego.id: ego.truncated for ego in frame.egos}
        return observations, rewards, terminations, truncations, infos

    def close(self) -> None:
        """Say goodbye (best effort, short timeout) and release the socket."""
        if getattr(self, "_connection", None) is None:
            return
        say_goodbye(self._connection)
        self._connection = None  # type: ignore[assignment]
        self.agents = []

    # ----------------------------------------------------------------------- more

    @property
    def action_encoding(self) -> ActionEncoding:
        """The encoding `step` decodes; for ``"auto"``, fixed by the first lane count seen."""
        if self._encoding is None:
            if self._lane_count is None:
                self._probe()
            assert self._lane_count is not None
            self._encoding = make_action_encoding(
                self._action_space_name,
                self.welcome.action,
                self._lane_count > 1,
                self._acceleration_levels,
            )
        return self._encoding

    @property
    def last_frame(self) -> MultiObservation | None:
        """The last reply of the episode, every ego in it (`protocol.MultiObservation`)."""
        return self._frame

    @property
    def last_observations(self) -> dict[str, Observation]:
        """Each agent's latest named observation in this episode (the ended ones' last)."""
        return dict(self._last)

    @property
    def episode_seed(self) -> int:
        """The seed the current episode runs with (an insertion retry may have moved it)."""
        return self._episode_seed

    # ----------------------------------------------------------------------- helpers

    def _episode_options(self, options: Mapping[str, Any]) -> dict[str, OptionValue]:
        """The scenario options among a reset's `options`: those the scenario does not offer
        are ignored with a warning (PettingZoo's own API test resets with an unknown one)."""
        for name in ("egos", "ego_share"):
            if name in options:
                raise UsageError(
                    f"{name} is fixed for the env: choose it with RemoteParallelEnv({name}=...)"
                )
        offered = self._info.options
        ignored = [name for name in options if name not in offered and name != "decision_interval"]
        if ignored:
            warnings.warn(
                f"RemoteParallelEnv.reset ignores option(s) {', '.join(map(repr, ignored))}: "
                f"scenario {self.scenario} has no such option; options: {', '.join(offered)}",
                stacklevel=3,
            )
        kept = {name: value for name, value in options.items() if name not in ignored}
        return scenario_options(self._info, kept, self.address)

    def _start(self, frame: MultiObservation) -> None:
        """Take a reset's frame as the episode's start."""
        ids = [ego.id for ego in frame.egos]
        if self._possible is None or self.ego_share is not None:
            self._see(ids)
        elif not set(ids) <= self._seen:
            raise MalformedReply(
                f"{self.address}: the egos of this reset, {ids}, are not those of the first, "
                f"{self._possible}: possible_agents cannot change"
            )
        if self._lane_count is None:
            self._lane_count = frame.egos[0].ego.lane_count
        self._frame, self._seq, self.agents = frame, 0, ids
        self._last = {ego.id: ego_observation(frame, ego) for ego in frame.egos}

    def _probe(self) -> None:
        """The ego ids and the lane count, asked for before any reset: from one reset (seed 0)
        whose episode is then dropped (the next `reset` starts the caller's own)."""
        self._connection.send(Reset(self.scenario, 0, {**self.options, **self._many}))
        frame, _ = first_reply(
            self._connection, self._replies, self.reset_timeout_s, MultiObservation
        )
        self._start(frame)
        self._frame, self._seq, self.agents, self._last = None, 0, [], {}

    def _see(self, ids: list[str]) -> None:
        """Add the ids not seen yet to `possible_agents`, in their order."""
        if self._possible is None:
            self._possible = []
        for agent in ids:
            if agent not in self._seen:
                self._seen.add(agent)
                self._possible.append(agent)

    def _known(self, agent: str) -> None:
        if self._possible is None:
            self._probe()
        if agent not in self._seen:
            raise ValueError(
                f"no agent {agent!r}; possible agents: {', '.join(self._possible or [])}"
            )

    def _commands(self, actions: Mapping[str, Any]) -> tuple[Command, ...]:
        """One command per agent still driving, in their order; anything else is a ValueError
        naming the agents (the server would refuse it with invalid_message)."""
        unknown = [agent for agent in actions if agent not in self.agents]
        missing = [agent for agent in self.agents if agent not in actions]
        if unknown or missing:
            words = [f"no running agent {', '.join(map(repr, unknown))}"] if unknown else []
            words += [f"no action for {', '.join(map(repr, missing))}"] if missing else []
            raise ValueError(f"{'; '.join(words)} (agents: {', '.join(self.agents)})")
        commands = []
        for agent in self.agents:
            action = actions[agent]
            if isinstance(action, Mapping):
                acceleration, lane_change = decode_named(action)
            else:
                acceleration, lane_change = self.action_encoding.decode(action)
            if not math.isfinite(acceleration):
                raise ValueError(f"{agent}: acceleration must be finite, got {acceleration}")
            if lane_change not in (-1, 0, 1):
                raise ValueError(f"{agent}: lane_change must be -1, 0 or 1, got {lane_change}")
            commands.append(Command(agent, float(acceleration), int(lane_change)))
        return tuple(commands)

    def _frame_of(self, reply: object) -> MultiObservation:
        """The step's frame, checked against the protocol (`InvalidReply`); an error reply is a
        `ServerError` (the step was not taken: the next `step` sends the same seq again)."""
        checked = self._replies.check(self._connection.sent, reply)  # type: ignore[arg-type]
        if isinstance(checked, Error):
            self._seq -= 1
            if checked.code in _EPISODE_ENDERS:
                self.agents = []
            raise ServerError(checked.code, checked.message)
        if not isinstance(checked, MultiObservation):
            raise MalformedReply(f"expected a multi_observation, got {checked.TYPE}")
        return checked


def _many_option(egos: int | None, ego_share: float | None) -> dict[str, OptionValue]:
    """The reset option of a multi-ego episode: ``egos`` (an integer >= 1) or ``ego_share``
    (within (0, 1]), exactly one of them."""
    if (egos is None) == (ego_share is None):
        raise UsageError("give egos (a number of egos) or ego_share (a share of the traffic)")
    if ego_share is not None:
        if isinstance(ego_share, bool) or not isinstance(ego_share, int | float):
            raise UsageError(f"ego_share must be a number within (0, 1], got {ego_share!r}")
        if not 0.0 < ego_share <= 1.0:
            raise UsageError(f"ego_share must be within (0, 1], got {ego_share!r}")
        return {"ego_share": float(ego_share)}
    if isinstance(egos, bool) or not isinstance(egos, int) or egos < 1:
        raise UsageError(f"egos must be an integer >= 1, got {egos!r}")
    return {"egos": egos}


def _refuse_old(welcome: Welcome, address: str, share: bool) -> None:
    """A server of protocol 1.x before 1.4 drives one ego only, one before 1.5 no share of
    the traffic (another major version is refused by the welcome's own checks)."""
    refuse_one_ego_server(welcome, address, "RemoteParallelEnv")
    if share:
        refuse_old_server(welcome, address, EGO_SHARE_VERSION, "ego_share", "egos as a share")
