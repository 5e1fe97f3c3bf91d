"""Sampling workers as Ray actors: `RayWorkers`, the `Workers` group of ``sampling = "ray"``.

One `SamplingWorker` actor per server (or per simulator it starts), wherever Ray places it;
`ChunkCollector` (`agent_client.training.sampling.chunks`) asks them for chunks while the learner
updates. With ``ray_address = ""`` a local Ray is started (bound to loopback) and stopped with
the workers; ``"auto"`` joins the cluster this machine belongs to, ``"ray://HOST:10001"`` one
through Ray Client (docs/ray.md). Needs ``pip install 'av-bridge[ray]'``.
"""

from __future__ import annotations

import contextlib
import os
from collections import deque
from collections.abc import Sequence
from typing import Any

from agent_client.errors import UsageError
from agent_client.training.sampling.worker import (
    Chunk,
    SamplingFailed,
    SamplingWorker,
    Settings,
    WorkerSpec,
    policy_arrays,
)
from protocol.transport.security import CLIENT_SECRET_ENV, SERVER_KEY_ENV

LOOPBACK_ONLY = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's switch that, set to 0, makes a local Ray bind 127.0.0.1 instead of the host's address."""


class RayWorkers:
    """`SamplingWorker` Ray actors, one per spec, on a local Ray or a cluster."""

    def __init__(self, ray_address: str = "") -> None:
        try:
            import ray
        except ImportError as exc:
            raise UsageError("sampling = ray needs Ray: pip install 'av-bridge[ray]'") from exc
        self._ray = ray
        self.ray_address = ray_address
        self.actors: list[Any] = []
        self._refs: dict[int, deque[Any]] = {}
        """Worker index -> object refs of the chunks asked of it, in order."""
        self._started_ray = False

    def start(self, specs: Sequence[WorkerSpec], first_seed: int) -> None:
        ray = self._ray
        if not ray.is_initialized():
            if self.ray_address:
                ray.init(address=self.ray_address, log_to_driver=False)
            else:
                os.environ.setdefault(LOOPBACK_ONLY, "0")
                cpus = max(os.cpu_count() or 1, len(specs) + 1)
                ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
            self._started_ray = True
        keys = {k: os.environ[k] for k in (SERVER_KEY_ENV, CLIENT_SECRET_ENV) if k in os.environ}
        actor = ray.remote(num_cpus=1, runtime_env={"env_vars": keys} if keys else None)(
            SamplingWorker
        )
        n = len(specs)
        self.actors = [actor.remote(spec, i, n, first_seed) for i, spec in enumerate(specs)]

    def share(self, policy_state: dict[str, Any]) -> Any:
        return self._ray.put(policy_arrays(policy_state))  # numpy: a worker needs no torch

    def ask(self, index: int, n_steps: int, settings: Settings, policy: Any | None) -> None:
        ref = self.actors[index].sample.remote(n_steps, settings, policy)
        self._refs.setdefault(index, deque()).append(ref)

    def drop_episodes(self, index: int) -> None:
        self.actors[index].drop_episodes.remote()  # runs after the chunks asked before it

    def wait(self, indices: Sequence[int], timeout_s: float) -> list[int]:
        ray = self._ray
        refs = {self._refs[i][0]: i for i in indices}
        first, _ = ray.wait(list(refs), num_returns=1, timeout=timeout_s)
        if not first:
            return []
        ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=0)
        return [refs[ref] for ref in ready]

    def answer(self, index: int) -> Chunk:
        try:
            return self._ray.get(self._refs[index].popleft())
        except self._ray.exceptions.RayError as exc:
            cause = getattr(exc, "cause", None) or exc
            raise SamplingFailed(str(cause)) from exc

    def close(self) -> None:
        """Stop the actors (each says goodbye to its server) and a Ray started here."""
        ray = self._ray
        if self.actors:
            with contextlib.suppress(ray.exceptions.RayError):  # the actors are killed next
                ray.get([actor.close.remote() for actor in self.actors], timeout=10)
            for actor in self.actors:
                ray.kill(actor)
            self.actors = []
        self._refs.clear()
        if self._started_ray:
            ray.shutdown()
            self._started_ray = False
