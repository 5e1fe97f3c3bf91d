"""Sampling on Ray: one asynchronous `SamplingWorker` per sim-server, feeding the learner.

The same `Collector` shape as `LocalCollector`, at the scale of machines: `send` asks every idle
worker for its next chunk of steps (with a fresh policy copy when one is due) and returns at
once; the learner updates meanwhile; `receive` waits for the first chunk to come back and takes
every chunk that is ready. A worker is at most one chunk ahead of the learner, so the
update-to-data ratio holds and the policy a worker acts with is at most
``policy_sync_every + sampling_chunk`` steps old.

With ``ray_address = ""`` a local Ray is started (bound to loopback) and stopped with the
collector; ``"auto"`` joins the cluster this machine belongs to, ``"ray://HOST:10001"`` one through
Ray Client (docs/ray.md). Needs ``pip install 'av-bridge[ray]'``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import BridgeError, UsageError
from agent_client.training.collect import Collected
from agent_client.training.exploration import learning, noise_scale_at
from agent_client.training.sampler import SamplingWorker, Settings, WorkerSpec
from protocol.messages import OptionValue
from protocol.transport.security import CLIENT_SECRET_ENV, SERVER_KEY_ENV

if TYPE_CHECKING:
    from agent_client.envs.vector_env import RemoteVectorEnv
    from agent_client.rl.features import FeatureMap
    from agent_client.rl.lanes import LaneChoice
    from agent_client.training.config import TrainConfig

LOOPBACK_ONLY = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's switch that, set to 0, makes a local Ray bind 127.0.0.1 instead of the host's address."""


class SamplingFailed(BridgeError):
    """A sampling worker raised: its server is gone (and no retry was set) or it failed."""


class RayCollector:
    """Training episodes on N servers, one Ray actor each, sampled while the learner updates."""

    def __init__(
        self,
        spec: WorkerSpec,
        servers: Sequence[str],
        policy_state: Callable[[], dict[str, Any]],
        settings: Callable[[], Settings],
        next_seed: Callable[[], int],
        *,
        chunk_steps: int = 64,
        sync_every: int = 500,
        ray_address: str = "",
        hand_over: Sequence[RemoteEnv] = (),
        simulators: int = 0,
    ) -> None:
        """`spec` is every worker's (its address replaced by each of `servers`);
        `policy_state` the learner's current policy, `settings` its exploration schedule.

        `hand_over`: this process's own connections to `servers`, closed when sampling starts
        so that each worker can take its server (a server serves one client at a time).
        `simulators`: N workers that each start a simulator of their own (`spec`'s
        ``simulator_args``) wherever Ray places them, in place of one worker per server.
        """
        try:
            import ray
        except ImportError as exc:
            raise UsageError("sampling = ray needs Ray: pip install 'av-bridge[ray]'") from exc
        self._ray = ray
        self.spec = spec
        self.own_simulators = simulators > 0
        own = [f"worker {i}'s own simulator" for i in range(simulators)]
        self.servers = own or list(servers)
        self.policy_state = policy_state
        self.settings = settings
        self.next_seed = next_seed
        self.chunk_steps = chunk_steps
        self.sync_every = sync_every
        self.ray_address = ray_address
        self.hand_over = list(hand_over)
        self.workers: list[Any] = []
        self._pending: dict[Any, int] = {}
        """Object ref of a chunk in flight -> worker index."""
        self._stale: set[Any] = set()
        """Refs of chunks asked for before `drop_episodes`: discarded when they arrive."""
        self._policy_ref: Any = None
        self._policy_version = 0
        self._worker_versions: list[int] = []
        self._since_sync = 0
        self._started_ray = False
        steps_s = chunk_steps * spec.timeout_s
        self.chunk_timeout_s = steps_s + spec.reset_timeout_s + spec.retry_for_s
        """The longest a chunk can take: every step and a reset at their deadlines, one outage."""
        self.failed_episodes = 0
        self.reconnects = 0
        self.chunks = 0

    # ----------------------------------------------------------------------- Collector

    def send(self) -> None:
        if not self.workers:
            self._start()
        ray = self._ray
        busy = set(self._pending.values())
        if self._policy_ref is None or self._since_sync >= self.sync_every:
            self._policy_ref = ray.put(self.policy_state())
            self._policy_version += 1
            self._since_sync = 0
        settings = self.settings()
        for index, worker in enumerate(self.workers):
            if index in busy:
                continue
            fresh = self._worker_versions[index] != self._policy_version
            policy = self._policy_ref if fresh else None
            self._worker_versions[index] = self._policy_version
            self._pending[worker.sample.remote(self.chunk_steps, settings, policy)] = index

    def receive(self) -> Collected:
        ray = self._ray
        collected = Collected()
        while not collected.transitions and not collected.finished and self._pending:
            first, _ = ray.wait(list(self._pending), num_returns=1, timeout=self.chunk_timeout_s)
            if not first:
                busy = ", ".join(self.servers[i] for i in sorted(set(self._pending.values())))
                raise SamplingFailed(
                    f"no sampling worker returned a chunk within {self.chunk_timeout_s:g} s "
                    f"(workers of {busy})"
                )
            ready, _ = ray.wait(list(self._pending), num_returns=len(self._pending), timeout=0)
            for ref in ready:
                index = self._pending.pop(ref)
                if ref in self._stale:  # asked for before drop_episodes: not wanted, even failed
                    self._stale.discard(ref)
                    continue
                chunk = self._get(ref, index)
                self.chunks += 1
                self.failed_episodes += chunk.failed_episodes
                self.reconnects += chunk.reconnects
                collected.transitions += chunk.transitions
                collected.finished += chunk.finished
        self._since_sync += len(collected.transitions)
        return collected

    def drop_episodes(self) -> None:
        """Discard the chunks in flight and start new episodes on every worker."""
        self._stale |= set(self._pending)
        for worker in self.workers:
            worker.drop_episodes.remote()

    def drop_episode(self, index: int) -> None:
        """Nothing to drop: this process does not step the servers itself."""

    def close(self) -> None:
        """Stop the workers (each says goodbye to its server) and a Ray started here."""
        ray = self._ray
        if self.workers:
            with contextlib.suppress(ray.exceptions.RayError):  # the actors are killed next
                ray.get([worker.close.remote() for worker in self.workers], timeout=10)
            for worker in self.workers:
                ray.kill(worker)
            self.workers = []
        if self._started_ray:
            ray.shutdown()
            self._started_ray = False

    # ----------------------------------------------------------------------- helpers

    def _start(self) -> None:
        ray = self._ray
        if not ray.is_initialized():
            if self.ray_address:
                ray.init(address=self.ray_address, log_to_driver=False)
            else:
                os.environ.setdefault(LOOPBACK_ONLY, "0")
                cpus = max(os.cpu_count() or 1, len(self.servers) + 1)
                ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
            self._started_ray = True
        for env in self.hand_over:
            env.close()
        keys = {k: os.environ[k] for k in (SERVER_KEY_ENV, CLIENT_SECRET_ENV) if k in os.environ}
        actor = ray.remote(num_cpus=1, runtime_env={"env_vars": keys} if keys else None)(
            SamplingWorker
        )
        first_seed = self.next_seed()
        n = len(self.servers)
        specs = (
            [self.spec] * n
            if self.own_simulators
            else [replace(self.spec, address=address) for address in self.servers]
        )
        self.workers = [
            actor.remote(spec, index, n, first_seed) for index, spec in enumerate(specs)
        ]
        self._worker_versions = [0] * n

    def _get(self, ref: Any, index: int) -> Any:
        try:
            return self._ray.get(ref)
        except self._ray.exceptions.RayError as exc:
            cause = getattr(exc, "cause", None) or exc
            raise SamplingFailed(
                f"sampling worker {index} ({self.servers[index]}) failed: {cause}"
            ) from exc


def ray_collector(
    config: TrainConfig,
    vec: RemoteVectorEnv,
    features: FeatureMap,
    lanes: LaneChoice,
    reset_options: Mapping[str, OptionValue],
    *,
    residual: str,
    warmup_policy: str,
    policy_state: Callable[[], dict[str, Any]],
    global_step: Callable[[], int],
    lane_epsilon: Callable[[], float],
    next_seed: Callable[[], int],
    retry_for_s: float,
    eval_servers: int,
) -> RayCollector:
    """The trainer's `RayCollector`: one worker per server of `vec` (whose connections it takes
    over), the trainer's features, lane choice and exploration schedule."""
    if config.eval_every > 0 and eval_servers == 0:
        raise UsageError(
            "sampling = ray gives every training server to a sampling worker: evaluate on "
            "servers of their own (--eval-server ADDRESS; a simulator of their own started "
            "here did not serve the run's scenarios as the training server does) or not at "
            "all (--set eval_every=0)"
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
    )

    def settings() -> Settings:  # the schedule of `Trainer._choose`
        step = global_step()
        return Settings(learning(config, step), noise_scale_at(config, step), lane_epsilon())

    return RayCollector(
        spec, vec.addresses, policy_state, settings, next_seed,
        chunk_steps=config.sampling_chunk, sync_every=config.policy_sync_every,
        ray_address=config.ray_address, hand_over=vec.envs, simulators=config.simulators,
    )  # fmt: skip
