"""Collecting experience from many egos in one simulation (protocol 1.4): parameter sharing.

Every ego of a multi-ego episode (docs/protocol.md §3.1) drives with the one shared policy, and
every ego's step is a `Transition` for the one replay buffer. `MultiEgoCollector` has the
`Collector` shape of `LocalCollector` (send every server its next command, let the learner
update, receive), over one multi-ego session per server (`MultiEgoLink`):

* one batched forward pass of the shared actor for every running ego of every server, each
  ego with its own exploration noise process (`batch_by_ego`) and its own lane mask
  (`LaneChoice.mask` on its own observation), the same features as one ego's;
* an ego's end is one env's end: its last transition is ``terminated`` for a crash, the end of
  the road or a stop, and bootstraps for the time limit (truncated); an ego that ended stops
  contributing while the others drive on; the simulation is reset when none is left;
* each ego's drive is reported as one finished training episode (`EgoSlot`, a `Slot` with the
  ego's id): one row per ego-episode in the trainer's logs, its progress counting ego-episodes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.drivers.episode import Episode
from agent_client.drivers.policy import ActionScale
from agent_client.envs.link import (
    RewardFn,
    check_scenario,
    open_channel,
    refuse_one_ego_server,
    resolve_reward,
    say_goodbye,
)
from agent_client.envs.remote_env import RemoteEnv
from agent_client.envs.scenario import first_reply
from agent_client.errors import MalformedReply, ServerError, UsageError
from agent_client.rl.features import FeatureMap
from agent_client.rl.lanes import LaneChoice
from agent_client.training.sampling.collect import Chooser, Collected, Slot, Transition
from agent_client.transport.channel import Channel
from agent_client.transport.replies import ReplyChecker, ego_observation
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
from protocol.transport.security import ClientCredentials

"""The first protocol version with many egos in one simulation (§3.1)."""


def check_many_egos(
    welcome: Welcome, address: str, scenario: str, options: Mapping[str, object]
) -> None:
    """Refuse (`UsageError`) a server older than protocol 1.4 and a scenario without the
    ``egos`` option: they drive one ego."""
    refuse_one_ego_server(welcome, address, "training with many egos")
    if "egos" not in options:
        raise UsageError(
            f"scenario {scenario} at {address} has no option egos: its server drives one ego "
            "(train with egos = 1)"
        )


class MultiEgoLink:
    """One server's multi-ego episodes: resets naming ``egos``, ``multi_step``s, each ego's
    reward from its own two consecutive observations, in two halves (send, receive).

    `sharing` runs them in a `RemoteEnv`'s own session, so that its one-ego episodes (the
    trainer's evaluations) and these alternate on one connection: a server serves one client at
    a time. `open` connects on its own.
    """

    def __init__(
        self,
        address: str,
        scenario: str,
        egos: int,
        welcome: Welcome,
        channel: Callable[[], Channel],
        reward_fn: RewardFn,
        options: Mapping[str, OptionValue],
        step_length: float | None,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        owned: Channel | None = None,
    ) -> None:
        if isinstance(egos, bool) or not isinstance(egos, int) or egos < 1:
            raise UsageError(f"egos must be an integer >= 1, got {egos!r}")
        self.address = address
        self.scenario = scenario
        self.egos = egos
        self.welcome = welcome
        self._channel = channel
        """The channel to use now (a `RemoteEnv` that reconnected has a new one)."""
        self.reward_fn = reward_fn
        self.options = dict(options)
        self.step_length = step_length
        self.reset_timeout_s = reset_timeout_s
        self._owned = owned
        self.replies = ReplyChecker(welcome, f"invalid reply from {address}")
        self.episode_seed = 0
        self._seq = 0
        self._last: dict[str, Observation] = {}

    @classmethod
    def sharing(cls, env: RemoteEnv, egos: int) -> MultiEgoLink:
        """Multi-ego episodes in `env`'s session, with its scenario, options and reward (the
        caller keeps the two kinds of episode apart: one request in flight at a time)."""
        check_many_egos(env.welcome, env.address, env.scenario, env.scenario_options)
        return cls(
            env.address, env.scenario, egos, env.welcome,
            lambda: env.connection,  # the env's current channel: reconnect() replaces it
            env.reward_fn, env.options, env.step_length, env.reset_timeout_s,
        )  # fmt: skip

    @classmethod
    def open(
        cls,
        address: str,
        scenario: str,
        *,
        egos: int,
        reward: str | RewardFn = "safe",
        timeout_s: float = STEP_TIMEOUT_S,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        credentials: ClientCredentials | None = None,
        **options: OptionValue,
    ) -> MultiEgoLink:
        """Connect, shake hands and check the scenario and its options (as `RemoteEnv` does)."""
        channel = open_channel(address, timeout_s, credentials, None)
        try:
            checked = check_scenario(channel.hello(timeout_s), address, scenario, dict(options))
            check_many_egos(checked.welcome, address, scenario, checked.all_options)
        except Exception:
            say_goodbye(channel)  # free the server for the next client, then report
            raise
        return cls(
            address, scenario, egos, checked.welcome, lambda: channel, resolve_reward(reward),
            checked.options, checked.info.step_length, reset_timeout_s, owned=channel,
        )  # fmt: skip

    def send_reset(self, seed: int, options: Mapping[str, OptionValue] | None = None) -> None:
        """Start an episode of `egos` egos with scenario options (and `options` for it)."""
        self.episode_seed = seed
        wanted = {**self.options, **(options or {}), "egos": self.egos}
        self._channel().send(Reset(self.scenario, seed, wanted))

    def receive_reset(self) -> list[tuple[str, Observation]]:
        """Every ego's id and first observation, in the server's stable order (an episode whose
        egos could not enter is retried on other seeds, then `InsertionFailed`)."""
        frame, seed = first_reply(
            self._channel(), self.replies, self.reset_timeout_s, MultiObservation
        )
        if seed is not None:
            self.episode_seed = seed
        self._seq = 0
        egos = [(ego.id, ego_observation(frame, ego)) for ego in frame.egos]
        self._last = dict(egos)
        return egos

    def send_step(self, commands: Sequence[Command]) -> None:
        """One decision of every running ego (exactly one command each, §3.1)."""
        self._seq += 1
        self._channel().send(MultiStep(self._seq, tuple(commands)))

    def receive_step(self) -> tuple[MultiObservation, dict[str, tuple[Observation, float]]]:
        """The step's frame (checked against the protocol) and, per ego that drove into it, its
        observation and reward; an error reply is a `ServerError`."""
        channel = self._channel()
        reply = self.replies.check(channel.sent, channel.receive())
        if isinstance(reply, Error):
            self._seq -= 1  # not taken: the same seq may be sent again
            raise ServerError(reply.code, reply.message)
        if not isinstance(reply, MultiObservation):
            raise MalformedReply(f"{self.address}: expected a multi_observation, got {reply.TYPE}")
        steps: dict[str, tuple[Observation, float]] = {}
        for ego in reply.egos:
            obs = ego_observation(reply, ego)
            prev = self._last.get(ego.id)
            elapsed = obs.time - prev.time if prev is not None else 0.0
            steps[ego.id] = (obs, float(self.reward_fn(prev, obs, elapsed)))
            self._last[ego.id] = obs
        return reply, steps

    def close(self) -> None:
        """Say goodbye on a channel of its own; a shared one belongs to its `RemoteEnv`."""
        if self._owned is not None:
            say_goodbye(self._owned)
            self._owned = None


@dataclass
class EgoSlot(Slot):
    """One ego's drive in a multi-ego episode: a `Slot` whose `env_index` is the ego's slot
    (the server's first slot + its place in the server's order) and that knows the ego's id."""

    ego_id: str = ""


def batch_by_ego(slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features and lane masks of the running egos as a batch whose row i is ego slot i, and
    the rows of `slots`. `Agent.act_batch` draws noise process i for row i: so every ego keeps
    its own process for its whole drive, however many of the others have ended (their rows are
    zeros with "keep" only, and their actions are not used)."""
    rows = np.fromiter((slot.env_index for slot in slots), np.int64, len(slots))
    first = slots[0]
    n = int(rows.max()) + 1
    x = np.zeros((n, *first.x.shape), dtype=first.x.dtype)
    masks = np.zeros((n, *first.mask.shape), dtype=bool)
    masks[:, 0] = True
    x[rows] = np.stack([slot.x for slot in slots])
    masks[rows] = np.stack([slot.mask for slot in slots])
    return x, masks, rows


class MultiEgoCollector:
    """Training episodes of many egos each, one multi-ego simulation per link (server).

    `choose` is called once per send with every running ego of every link (each an `EgoSlot`),
    `on_start(ego_slot)` when an ego's drive starts (the trainer resets that ego's noise),
    `next_seed()` once per simulation: the egos of one simulation share its seed.
    """

    def __init__(
        self,
        links: Sequence[MultiEgoLink],
        features: FeatureMap,
        lanes: LaneChoice,
        scale: ActionScale,
        choose: Chooser,
        next_seed: Callable[[], int],
        on_start: Callable[[int], None] | None = None,
        reset_options: Mapping[str, OptionValue] | None = None,
    ) -> None:
        self.links = list(links)
        self.features = features
        self.lanes = lanes
        self.scale = scale
        self.choose = choose
        self.next_seed = next_seed
        self.on_start = on_start
        self.reset_options = dict(reset_options or {})
        self.offsets = [sum(link.egos for link in self.links[:i]) for i in range(len(self.links))]
        """Per link: the ego slot of its first ego."""
        self.n_egos = sum(link.egos for link in self.links)
        """Ego slots in all: the number of exploration noise processes needed."""
        self.running: list[dict[str, EgoSlot]] = [{} for _ in self.links]
        """Per link: the egos still driving, by id, in the server's order."""
        self._sent: list[dict[str, tuple[float, int]] | int | None] = [None] * len(self.links)
        """Per link: each ego's (u, lane) of a step in flight, the seed of a reset, or None."""

    def send(self) -> None:
        for index, link in enumerate(self.links):
            if not self.running[index]:
                seed = self.next_seed()
                link.send_reset(seed, self.reset_options)
                self._sent[index] = seed
        slots = [slot for running in self.running for slot in running.values()]
        if not slots:
            return
        us, lane_choices = self.choose(slots)
        first = 0
        for index, running in enumerate(self.running):
            if not running:
                continue
            commands, sent = [], {}
            last = first + len(running)
            for slot, u, lane in zip(
                running.values(), us[first:last], lane_choices[first:last], strict=True
            ):
                acceleration = self.scale.to_env(float(u), slot.obs)
                command = self.lanes.command(int(lane), slot.obs)
                commands.append(Command(slot.ego_id, acceleration, command))
                sent[slot.ego_id] = (float(u), int(lane))
            self.links[index].send_step(commands)
            self._sent[index] = sent
            first = last

    def receive(self) -> Collected:
        collected = Collected()
        for index in range(len(self.links)):
            sent, self._sent[index] = self._sent[index], None
            if isinstance(sent, int):
                self._start(index)
            elif sent is not None:
                self._step(index, sent, collected)
        return collected

    def _start(self, index: int) -> None:
        link = self.links[index]
        running: dict[str, EgoSlot] = {}
        for k, (ego_id, obs) in enumerate(link.receive_reset()):
            episode = Episode(seed=link.episode_seed, step_length=link.step_length)
            episode.add(obs)
            slot = EgoSlot(
                self.offsets[index] + k, obs, self.features(obs), self.lanes.mask(obs), episode,
                ego_id=ego_id,
            )  # fmt: skip
            running[ego_id] = slot
            if self.on_start is not None:
                self.on_start(slot.env_index)
        self.running[index] = running

    def _step(self, index: int, sent: dict[str, tuple[float, int]], collected: Collected) -> None:
        frame, steps = self.links[index].receive_step()
        running = self.running[index]
        for ego_id, (next_obs, reward) in steps.items():
            slot = running[ego_id]  # the reply checks made sure: exactly the running egos
            u, lane = sent[ego_id]
            next_x, next_mask = self.features(next_obs), self.lanes.mask(next_obs)
            collected.transitions.append(
                Transition(
                    slot.x, u, lane, reward, next_x, next_obs.terminated, slot.mask, next_mask
                )
            )
            slot.states.append(slot.x)
            slot.accelerations.append(u)
            slot.lanes.append(lane)
            slot.episode.add(next_obs, reward)
            slot.obs, slot.x, slot.mask = next_obs, next_x, next_mask
            if next_obs.terminated or next_obs.truncated:
                collected.finished.append(running.pop(ego_id))
        if frame.terminated or frame.truncated:  # none is left by §3.1; never step it again
            collected.finished += running.values()
            running.clear()

    def drop_episodes(self) -> None:
        self.running = [{} for _ in self.links]
        self._sent = [None] * len(self.links)

    def drop_episode(self, index: int) -> None:
        """Forget the simulation on server `index` (something else used that session)."""
        self.running[index] = {}
        self._sent[index] = None

    def close(self) -> None:
        """Close the links' own connections (shared ones belong to the trainer's envs)."""
        for link in self.links:
            link.close()
