"""A sampling worker: training episodes on one server with a copy of the learner's policy.

The worker is the trainer's own `LocalCollector` on one `RemoteEnv`, with a chooser of its own
(`Exploration`: a numpy copy of the policy, its own exploration noise, the warm-up driver) in
place of the trainer's agent. `ChunkCollector` (`agent_client.training.sampling.chunks`) runs
one per sim-server, in a process of its own or as a Ray actor, and asks it for chunks of steps
while the learner updates; the class itself needs neither, so tests can run it in-process. It
never imports torch.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent_client.defaults import RESET_TIMEOUT_S
from agent_client.drivers.mobil import DECISION_INTERVAL
from agent_client.drivers.policy import ActionScale, lane_choice
from agent_client.drivers.safety import SafetyLayer
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import BridgeError, ServerError, ServerUnavailable
from agent_client.rl.features import FeatureMap
from agent_client.rl.greedy import NumpyActor, NumpyCritic
from agent_client.rl.lanes import choose_lanes
from agent_client.rl.noise import ActionNoise, make_noise
from agent_client.rl.rewards import RewardFn
from agent_client.training.sampling.collect import (
    EPISODE_FAILURES,
    MAX_FAILURES_IN_A_ROW,
    Collected,
    LocalCollector,
    Slot,
)
from agent_client.training.sampling.exploration import WarmupDriver
from agent_client.training.simulators import OwnSimulator
from protocol.messages import OptionValue


@dataclass(frozen=True)
class WorkerSpec:
    """Everything a worker needs to build its env, features and exploration (picklable)."""

    address: str
    scenario: str | list[str]
    reward: RewardFn
    """The reward (a dataclass of `agent_client.rl.rewards`, picklable for Ray)."""
    options: dict[str, Any]
    """`RemoteEnv` scenario options (decision_interval included)."""
    reset_options: dict[str, OptionValue]
    features: str
    lane_phase_every: int
    n_lanes: int
    lane_every: int
    lane_gap_rule: bool
    lane_route_masks: bool
    noise: str
    noise_sigma: float
    noise_theta: float
    noise_dt: float
    warmup_policy: str
    seed: int
    timeout_s: float
    retry_for_s: float = 0.0
    residual: str = ""
    """The trainer's `ActionScale.residual`: what the actor's output corrects."""
    residual_reach: float = 2.0
    residual_shield: bool = True
    residual_lanes: str = "follow"
    """The trainer's `ActionScale.reach`, `.shield` and whether its lanes are the reference's."""
    reset_timeout_s: float = RESET_TIMEOUT_S
    simulator_args: str | None = None
    """Start a simulator of its own with this sim-server command line (`OwnSimulator`) and
    drive it, not `address`."""
    safety_layer: bool = False
    """Drive through the safety layer, as the policy does when it drives
    (`TrainConfig.safety_layer_training`)."""
    override_penalty: float = 0.0
    """Taken off the reward of a decision the safety layer overrode."""
    learn_own_decision: bool = False
    """Store the policy's own decision where the layer overrode it
    (`TrainConfig.learn_own_decision`)."""


@dataclass(frozen=True)
class Settings:
    """The learner's exploration schedule at the time of a request."""

    learning: bool
    """False: warm-up actions (IDM + noise, or random), True: the policy copy + noise."""
    noise_scale: float = 1.0
    lane_epsilon: float = 0.0


class SamplingFailed(BridgeError):
    """A sampling worker raised (its server is gone and no retry was set), exited or hung."""


@dataclass
class Chunk(Collected):
    """What one request brought back from a worker."""

    seconds: float = 0.0
    """Time the worker spent sampling it."""


class Exploration:
    """The worker's chooser: what `Trainer._choose` does with the agent, on a policy copy."""

    def __init__(self, spec: WorkerSpec, scale: ActionScale, seed: int) -> None:
        self.spec = spec
        self.scale = scale
        choices, noise = np.random.SeedSequence(seed).generate_state(2)
        self.rng = np.random.default_rng(int(choices))
        self.noise: ActionNoise = make_noise(
            spec.noise, spec.noise_sigma, int(noise), spec.noise_theta, spec.noise_dt
        )
        self.settings = Settings(learning=False)
        self.warmup = WarmupDriver(spec.warmup_policy, scale, spec.noise_sigma, self.rng)
        self._actor: NumpyActor | None = None
        self._critic: NumpyCritic | None = None

    def load(self, policy_state: dict[str, Any]) -> None:
        """Take a new policy copy (`Agent.policy_state_dict()`: the actor, critic 1 for lanes)."""
        self._actor = NumpyActor([_float32(p) for p in policy_state["actor"]])
        critic = policy_state.get("critic")
        self._critic = NumpyCritic([_float32(p) for p in critic]) if critic else None

    def configure(self, settings: Settings) -> None:
        """Follow the learner's schedule: warm-up or policy, noise scale, lane epsilon."""
        self.settings = settings
        self.noise.scale = settings.noise_scale

    def __call__(self, slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray]:
        actions = [self._act(slot) for slot in slots]
        return np.array([u for u, _ in actions]), np.array([lane for _, lane in actions])

    def _act(self, slot: Slot) -> tuple[float, int]:
        if not self.settings.learning or self._actor is None:
            return self.warmup(slot)
        x = slot.x[None].astype(np.float32)
        u = float(self._actor(x)[0]) + self.noise.sample()
        u = float(np.clip(u, -1.0, 1.0))  # NaN stays NaN: a diverged actor fails the step
        if self._critic is None or self.spec.n_lanes == 1:
            return u, 0
        q = self._critic(x, np.array([u], np.float32))
        lanes = choose_lanes(q, slot.mask[None], self.settings.lane_epsilon, self.rng)
        return u, int(lanes[0])


class SamplingWorker:
    """Training episodes on one server, a chunk of steps per `sample` call.

    Episode seeds are ``first_seed + index + stride * k`` for its k-th episode, so that the
    workers of one run never share one. A failed simulator episode is started again; a lost
    server is waited for up to `WorkerSpec.retry_for_s` (0: the error goes to the caller).
    """

    def __init__(self, spec: WorkerSpec, index: int, stride: int, first_seed: int) -> None:
        self.spec = spec
        self.index = index
        own = spec.simulator_args is not None
        self.simulator = OwnSimulator(spec.simulator_args or "") if own else None
        self.env = self._connect()
        features = FeatureMap(spec.features, lane_phase_every=spec.lane_phase_every)
        lanes = lane_choice(
            spec.n_lanes, spec.lane_every, spec.lane_gap_rule, spec.residual,
            spec.lane_route_masks, spec.residual_lanes,
        )  # fmt: skip
        interval = float(spec.options.get("decision_interval", DECISION_INTERVAL))
        scale = ActionScale.from_schema(
            self.env.welcome.action, spec.residual, interval, spec.residual_reach,
            spec.residual_shield,
        )  # fmt: skip
        self.exploration = Exploration(spec, scale, spec.seed + 7919 * (index + 1))
        self._seeds = (first_seed + index + stride * k for k in range(2**31))
        safety = SafetyLayer(interval, scale.low) if spec.safety_layer else None
        self.local = LocalCollector(
            [self.env], features, lanes, scale, self.exploration, self._next_seed,
            self._episode_started, spec.reset_options, safety, spec.override_penalty,
            spec.learn_own_decision,
        )  # fmt: skip
        self._failures_in_a_row = 0

    def sample(
        self,
        n_steps: int,
        settings: Settings,
        policy_state: dict[str, Any] | None = None,
        interrupted: Callable[[], bool] | None = None,
    ) -> Chunk:
        """Take at least `n_steps` steps (episodes carry on across calls) and return them;
        fewer where `interrupted` (asked after every step) says the learner wants something
        else first (to stop, or new episodes)."""
        started = time.perf_counter()
        if policy_state is not None:
            self.exploration.load(policy_state)
        self.exploration.configure(settings)
        chunk = Chunk()
        while len(chunk.transitions) < n_steps:
            try:
                self.local.send()
                collected = self.local.receive()
            except ServerError as exc:
                self._failures_in_a_row += 1
                if exc.code not in EPISODE_FAILURES or (
                    self._failures_in_a_row >= MAX_FAILURES_IN_A_ROW
                ):
                    raise
                chunk.failed_episodes += 1
                self.local.drop_episodes()
                continue
            except ServerUnavailable:
                if self.simulator is not None:  # its own, exited or hung: nobody else restarts it
                    self._failures_in_a_row += 1
                    if self._failures_in_a_row >= MAX_FAILURES_IN_A_ROW:
                        raise
                    self.local.drop_episodes()
                    self._restart_simulator()
                    chunk.reconnects += 1
                    continue
                if self.spec.retry_for_s <= 0:
                    raise
                self.local.drop_episodes()
                self.env.reconnect(self.spec.retry_for_s)
                chunk.reconnects += 1
                continue
            self._failures_in_a_row = 0
            chunk.extend(collected)
            if interrupted is not None and interrupted():
                break
        for slot in chunk.finished:
            slot.env_index = self.index
            slot.summarise()  # its figures travel to the learner, not its observations
        chunk.seconds = time.perf_counter() - started
        return chunk

    def drop_episodes(self) -> None:
        """Forget the running episode: the next `sample` starts a new one."""
        self.local.drop_episodes()

    def _connect(self) -> RemoteEnv:
        """The env on the worker's server (its own simulator, if it starts one)."""
        spec = self.spec
        address = self.simulator.address if self.simulator is not None else spec.address
        try:
            return RemoteEnv(
                address, spec.scenario, reward=spec.reward, timeout_s=spec.timeout_s,
                reset_timeout_s=spec.reset_timeout_s, **spec.options,
            )  # fmt: skip
        except BaseException:
            if self.simulator is not None:
                self.simulator.close()
            raise

    def _restart_simulator(self) -> None:
        """A simulator of its own that exited (a SUMO crash): start another and drive it."""
        assert self.simulator is not None
        self.env.close()
        self.simulator.close()
        self.simulator = OwnSimulator(self.spec.simulator_args or "")
        self.env = self.local.envs[0] = self._connect()

    def close(self) -> None:
        """Say goodbye to the server; stop the simulator it started, if any."""
        try:
            self.env.close()
        finally:
            if self.simulator is not None:
                self.simulator.close()

    def _next_seed(self) -> int:
        return next(self._seeds)

    def _episode_started(self, index: int) -> None:
        self.exploration.noise.reset()


def policy_arrays(policy_state: dict[str, Any]) -> dict[str, list[np.ndarray]]:
    """What `Exploration.load` reads of `Agent.policy_state_dict()`, as float32 numpy arrays
    (a process that unpickles them needs no torch)."""
    return {
        key: [_float32(p) for p in policy_state[key]]
        for key in ("actor", "critic")
        if policy_state.get(key)
    }


def _float32(tensor: Any) -> np.ndarray:
    """A float32 copy of a policy tensor (numpy's own array of it, not a view)."""
    data = tensor.detach().numpy() if hasattr(tensor, "detach") else tensor
    return np.array(data, dtype=np.float32)
