"""Sampling apart from the learner: workers that each drive one server with a copy of the
policy, asked for chunks of steps while the learner updates.

`ChunkCollector` has the `Collector` shape of `LocalCollector`: `send` asks every worker for
chunks until it has ``in_flight`` requests of it outstanding (with a fresh policy copy when one
is due) and returns at once; the learner updates meanwhile; `receive` waits for the first chunk
to come back and takes every chunk that is ready. With one in flight (the default) a worker
waits for the learner's next ask after each chunk; with two it starts its next chunk as soon as
it sends one. A worker is at most ``in_flight`` chunks ahead of the learner, so the
update-to-data ratio holds and the policy a worker acts with is at most ``policy_sync_every +
in_flight * sampling_chunk`` steps old (with one worker).

Where the workers run is a `Workers` group: processes on this machine
(`agent_client.training.sampling.process_workers`, ``sampling = "processes"``) or Ray actors
wherever Ray places them (`agent_client.training.sampling.ray_workers`, ``sampling = "ray"``).
Each worker is a `SamplingWorker` (`agent_client.training.sampling.worker`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Protocol

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import BridgeError, UsageError
from agent_client.training.sampling.collect import Collected
from agent_client.training.sampling.exploration import learning, noise_scale_at
from agent_client.training.sampling.worker import Chunk, SamplingFailed, Settings, WorkerSpec
from protocol.messages import OptionValue

if TYPE_CHECKING:
    from agent_client.envs.vector_env import RemoteVectorEnv
    from agent_client.rl.features import FeatureMap
    from agent_client.rl.lanes import LaneChoice
    from agent_client.training.config import TrainConfig


class Workers(Protocol):
    """A group of `SamplingWorker`s somewhere; each answers one request at a time, in order."""

    def start(self, specs: Sequence[WorkerSpec], first_seed: int) -> None:
        """Start worker i on ``specs[i]`` (episode seeds ``first_seed + i + n * k``)."""

    def share(self, policy_state: dict[str, Any]) -> Any:
        """The policy copy in the form `ask` sends it (stored once, sent to many)."""

    def ask(self, index: int, n_steps: int, settings: Settings, policy: Any | None) -> None:
        """Ask worker `index` for a chunk of at least `n_steps` steps; does not wait (a
        worker answers its requests in the order they were asked)."""

    def drop_episodes(self, index: int) -> None:
        """Have worker `index` start a new episode after the requests asked before this (a
        worker may cut them short: their answers are discarded)."""

    def wait(self, indices: Sequence[int], timeout_s: float) -> list[int]:
        """The workers among `indices` whose next answer is ready, waiting up to `timeout_s`
        for one; [] when none came."""

    def answer(self, index: int) -> Chunk:
        """Worker `index`'s next answer (ready); `SamplingFailed` (saying why) if it raised or
        exited."""

    def close(self) -> None:
        """Stop every worker (each says goodbye to its server and stops its own simulator)."""


class ChunkCollector:
    """Training episodes on N servers, one worker each, sampled while the learner updates."""

    def __init__(
        self,
        workers: Workers,
        specs: Sequence[WorkerSpec],
        policy_state: Callable[[], dict[str, Any]],
        settings: Callable[[], Settings],
        next_seed: Callable[[], int],
        *,
        chunk_steps: int = 64,
        sync_every: int = 500,
        in_flight: int = 1,
        hand_over: Sequence[RemoteEnv] = (),
        names: Sequence[str] = (),
    ) -> None:
        """`specs`: one per worker; `policy_state` the learner's current policy, `settings`
        its exploration schedule.

        `hand_over`: this process's own connections to the workers' servers, closed when
        sampling starts so that each worker can take its server. `names` say which worker is
        which in errors (default: the specs' addresses).
        """
        if in_flight < 1:
            raise ValueError(f"in_flight must be at least 1, got {in_flight}")
        self.workers = workers
        self.specs = list(specs)
        self.servers = list(names) or [spec.address for spec in self.specs]
        self.policy_state = policy_state
        self.settings = settings
        self.next_seed = next_seed
        self.chunk_steps = chunk_steps
        self.sync_every = sync_every
        self.in_flight = in_flight
        self.hand_over = list(hand_over)
        self._started = False
        self._pending = [0] * len(self.specs)
        """Per worker: requests whose answer is due."""
        self._stale = [0] * len(self.specs)
        """Per worker: of its due answers, the first ones, asked for before `drop_episodes`:
        discarded."""
        self._policy: Any = None
        self._policy_version = 0
        self._worker_versions = [0] * len(self.specs)
        self._since_sync = 0
        spec = self.specs[0]
        steps_s = chunk_steps * spec.timeout_s
        self.chunk_timeout_s = steps_s + spec.reset_timeout_s + spec.retry_for_s
        """The longest a chunk can take: every step and a reset at their deadlines, one outage."""
        self.chunks = 0

    # ----------------------------------------------------------------------- Collector

    def send(self) -> None:
        if not self._started:
            self._start()
        if self._policy is None or self._since_sync >= self.sync_every:
            self._policy = self.workers.share(self.policy_state())
            self._policy_version += 1
            self._since_sync = 0
        settings = self.settings()
        for index in range(len(self.specs)):
            while self._pending[index] < self.in_flight:
                fresh = self._worker_versions[index] != self._policy_version
                self._worker_versions[index] = self._policy_version
                policy = self._policy if fresh else None
                self.workers.ask(index, self.chunk_steps, settings, policy)
                self._pending[index] += 1

    def receive(self) -> Collected:
        collected = Collected()
        while not collected.transitions and not collected.finished and any(self._pending):
            busy = [index for index, due in enumerate(self._pending) if due]
            ready = self.workers.wait(busy, self.chunk_timeout_s)
            if not ready:
                names = ", ".join(self.servers[i] for i in busy)
                raise SamplingFailed(
                    f"no sampling worker returned a chunk within {self.chunk_timeout_s:g} s "
                    f"(workers of {names})"
                )
            for index in ready:
                self._pending[index] -= 1
                stale = self._stale[index] > 0  # asked for before drop_episodes: not wanted
                if stale:
                    self._stale[index] -= 1
                try:
                    chunk = self.workers.answer(index)
                except SamplingFailed as exc:
                    if stale:
                        continue
                    where = f"sampling worker {index} ({self.servers[index]})"
                    raise SamplingFailed(f"{where} failed: {exc}") from exc
                if stale:
                    continue
                self.chunks += 1
                collected.extend(chunk)
        self._since_sync += len(collected.transitions)
        return collected

    def drop_episodes(self) -> None:
        """Discard the chunks in flight and start new episodes on every worker."""
        self._stale = list(self._pending)
        if self._started:
            for index in range(len(self.specs)):
                self.workers.drop_episodes(index)

    def drop_episode(self, index: int) -> None:
        """Nothing to drop: this process does not step the servers itself."""

    def release(self, timeout_s: float) -> None:
        """Stop the workers and take their servers back on this process's own connections (for
        what follows a run: a greedy drive, another `run`); a server that does not answer
        within `timeout_s` leaves its connection closed. The next `send` starts the workers
        again."""
        self.close()
        for env in self.hand_over:
            with contextlib.suppress(BridgeError):  # its next use says it is not connected
                env.reconnect(timeout_s)

    def close(self) -> None:
        """Stop the workers; each says goodbye to its server."""
        if self._started:
            self._started = False
            self._pending = [0] * len(self.specs)
            self._stale = [0] * len(self.specs)
            self._policy = None  # workers started again get the policy with their first ask
            self.workers.close()

    # ----------------------------------------------------------------------- helpers

    def _start(self) -> None:
        for env in self.hand_over:
            env.close()
        self._started = True
        try:
            self.workers.start(self.specs, self.next_seed())
        except BaseException:
            self.close()
            raise


def chunk_collector(
    config: TrainConfig,
    vec: RemoteVectorEnv,
    features: FeatureMap,
    lanes: LaneChoice,
    reset_options: Mapping[str, OptionValue],
    *,
    sampling: str,
    residual: str,
    warmup_policy: str,
    policy_state: Callable[[], dict[str, Any]],
    global_step: Callable[[], int],
    lane_epsilon: Callable[[], float],
    next_seed: Callable[[], int],
    retry_for_s: float,
    eval_servers: int,
) -> ChunkCollector:
    """The trainer's `ChunkCollector` for `sampling` (processes or ray): one worker per server
    of `vec` (whose connections it takes over), or ``config.simulators`` workers that each
    start a simulator of their own; the trainer's features, lane choice and exploration
    schedule."""
    if config.eval_every > 0 and eval_servers == 0:
        raise UsageError(
            f"sampling = {sampling} gives every training server to a sampling worker: "
            "evaluate on servers of their own (--eval-server ADDRESS; a simulator of their own "
            "started here did not serve the run's scenarios as the training server does) or "
            "not at all (--set eval_every=0)"
        )
    env, learner = vec.envs[0], config.learner
    spec = WorkerSpec(
        address=env.address,
        scenario=list(config.scenarios),
        reward=env.reward_fn,
        options=dict(env.requested_options),
        reset_options=dict(reset_options),
        features=features.name,
        lane_phase_every=features.lane_phase_every,
        n_lanes=lanes.n_choices,
        lane_every=lanes.every,
        lane_gap_rule=lanes.gap_rule,
        lane_route_masks=lanes.route_masks,
        noise=learner.noise,
        noise_sigma=learner.noise_sigma,
        noise_theta=learner.noise_theta,
        noise_dt=learner.noise_dt,
        warmup_policy=warmup_policy,
        seed=config.seed,
        timeout_s=env.timeout_s,
        retry_for_s=retry_for_s,
        residual=residual,
        reset_timeout_s=env.reset_timeout_s,
        simulator_args=config.simulator_args if config.simulators else None,
        residual_reach=config.residual_reach,
        residual_shield=config.residual_shield,
        residual_lanes=config.residual_lanes,
        safety_layer=config.safety_layer_training,
        override_penalty=config.override_penalty,
        learn_own_decision=config.learn_own_decision,
    )
    if config.simulators:
        specs = [spec] * config.simulators
        names = [f"worker {i}'s own simulator" for i in range(config.simulators)]
    else:
        specs = [replace(spec, address=address) for address in vec.addresses]
        names = list(vec.addresses)

    def settings() -> Settings:  # the schedule of `Trainer._choose`
        step = global_step()
        return Settings(learning(config, step), noise_scale_at(config, step), lane_epsilon())

    workers: Workers
    if sampling == "ray":
        from agent_client.training.sampling.ray_workers import RayWorkers

        workers = RayWorkers(config.ray_address)
    else:
        from agent_client.training.sampling.process_workers import ProcessWorkers

        workers = ProcessWorkers()
    return ChunkCollector(
        workers, specs, policy_state, settings, next_seed, chunk_steps=config.sampling_chunk,
        sync_every=config.policy_sync_every, in_flight=config.chunks_in_flight,
        hand_over=vec.envs, names=names,
    )  # fmt: skip
