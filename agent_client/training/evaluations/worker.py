"""One evaluation server's driver, in a process of its own: a worker of `EvaluationPool`.

``python -m agent_client.training.evaluations.worker`` talks to the learner over its stdin and
stdout in the direct transport's frames (a 4-byte length, then a msgpack map; no pickle). It
connects to one evaluation server, then drives the episodes it is given one at a time with IDM,
IDM + MOBIL or a policy (its weights come in the message: the worker never imports torch), and
answers each with the episode's summary. While an episode runs it says it is alive every
`ALIVE_EVERY_S` and looks for a stop every `STOP_POLL_STEPS` steps, so the learner can tell a
hung worker from a long episode and end an evaluation that has failed at once.

Messages are maps with an ``op``. The learner's requests carry an ``id``: ``connect`` (the
server, the scenario or scenarios, the reward and the reset options), ``reconnect``,
``driver`` (IDM's parameters, with MOBIL's, or a policy's weights) and ``episode`` (an index
and a seed); ``stop`` has none.
Every message the worker sends while it handles a request echoes that request's ``id``:
``alive`` while it works, then ``ready`` (after ``connect``, ``reconnect`` and ``driver``),
``summary`` or ``stopped`` (after ``episode``), or ``error`` (a `kind` the learner raises
again as the client's own exception). The learner reads only the answer to the request it
waits for, so nothing left over from an earlier one is ever taken for it.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import time
from collections.abc import Iterator
from typing import Any

import msgspec
import numpy as np

from agent_client.drivers.episode import Driver, run_episode
from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.drivers.mobil import IDMMobilDriver, MobilParams
from agent_client.drivers.policy import ActionScale, PolicyDriver, lane_choice
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import (
    AuthenticationFailed,
    BridgeError,
    FeatureMismatch,
    InsertionFailed,
    MalformedReply,
    ServerError,
    ServerLost,
    ServerTimeout,
    ServerUnavailable,
    UsageError,
)
from agent_client.evaluation.metrics import episode_summary
from agent_client.rl.features import FeatureMap
from agent_client.rl.greedy import GreedyPolicy
from agent_client.rl.rewards import make_reward
from protocol.messages import Observation
from protocol.transport.direct import FrameReader, frame

STOP_POLL_STEPS = 16
"""How often (in steps) a running episode looks for a stop from the learner."""
ALIVE_EVERY_S = 1.0
"""How often a worker at work tells the learner it is alive."""
CONNECT_RETRY_S = 0.2
"""Pause between connection attempts to a server that is not (yet) back (``wait_s``)."""
MAX_MESSAGE_BYTES = 1 << 24
"""The largest message either end reads (a policy's weights travel in one)."""


class EvaluationWorkerFailed(BridgeError):
    """A worker failed in a way that is not the server's (a bug, a message it cannot read)."""


ERROR_KINDS: dict[str, type[BridgeError]] = {
    "timeout": ServerTimeout,
    "lost": ServerLost,
    "unavailable": ServerUnavailable,
    "authentication": AuthenticationFailed,
    "malformed": MalformedReply,
    "usage": UsageError,
    "features": FeatureMismatch,
}
"""The client's exceptions a worker reports by name (`ServerError` and `InsertionFailed`
carry their fields too); anything else comes back as `EvaluationWorkerFailed`."""

_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(dict[str, Any])


class Pipe:
    """Messages over a pair of descriptors, read with deadlines; written with one if
    `write_timeout_s` is given (the learner's end: a stopped worker must not block it)."""

    def __init__(self, read_fd: int, write_fd: int, write_timeout_s: float | None = None) -> None:
        self.read_fd = read_fd
        self.write_fd = write_fd
        self.write_timeout_s = write_timeout_s
        if write_timeout_s is not None:
            os.set_blocking(write_fd, False)
        self._reader = FrameReader(max_bytes=MAX_MESSAGE_BYTES)
        self._frames: list[bytes] = []

    def send(self, message: dict[str, Any]) -> None:
        """Write `message` whole; `TimeoutError` if the other end did not take it all in time
        (part of it may be written), `OSError` (a broken pipe) if it is gone."""
        data = memoryview(frame(_encoder.encode(message)))
        timeout = self.write_timeout_s
        deadline = None if timeout is None else time.monotonic() + timeout
        while data:
            if deadline is not None:
                remaining = deadline - time.monotonic()
                _, writable, _ = select.select([], [self.write_fd], [], max(0.0, remaining))
                if not writable:
                    raise TimeoutError(f"the other end read nothing in {timeout:g} s")
            try:
                data = data[os.write(self.write_fd, data) :]
            except BlockingIOError:  # writable, yet full again: wait for room
                continue

    def receive(self, timeout_s: float | None) -> dict[str, Any] | None:
        """The next message; None if none came within `timeout_s` (None: wait for one).
        `EOFError` when the other end has closed."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._frames:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            readable, _, _ = select.select([self.read_fd], [], [], remaining)
            if not readable:
                return None
            data = os.read(self.read_fd, 1 << 16)
            if not data:
                raise EOFError("the other end closed the pipe")
            self._frames += self._reader.feed(data)
        return _decoder.decode(self._frames.pop(0))

    def has_message(self) -> bool:
        """Whether a whole message is already read (`select` on the descriptor cannot tell)."""
        return bool(self._frames)


def error_message(exc: Exception) -> dict[str, Any]:
    """An exception as an ``error`` message (`raise_error` raises it again in the learner)."""
    if isinstance(exc, ServerError):
        return {"op": "error", "kind": "server", "code": exc.code, "message": exc.message}
    if isinstance(exc, InsertionFailed):
        return {"op": "error", "kind": "insertion", "scenario": exc.scenario, "seeds": exc.seeds,
                "message": exc.message}  # fmt: skip
    kind = next((k for k, cls in ERROR_KINDS.items() if type(exc) is cls), None)
    if kind is None:
        kind = next((k for k, cls in ERROR_KINDS.items() if isinstance(exc, cls)), "other")
    text = str(exc) if kind != "other" else f"{type(exc).__name__}: {exc}"
    return {"op": "error", "kind": kind, "message": text}


def raise_error(message: dict[str, Any], where: str) -> None:
    """Raise the exception an ``error`` message describes, naming the worker's server."""
    text = f"{where}: {message.get('message', '')}"
    kind = message.get("kind")
    if kind == "server":
        raise ServerError(str(message.get("code", "")), text)
    if kind == "insertion":
        seeds = [int(seed) for seed in message.get("seeds", [])]
        raise InsertionFailed(str(message.get("scenario", "")), seeds, text)
    raise ERROR_KINDS.get(str(kind), EvaluationWorkerFailed)(text)


# ----------------------------------------------------------------------- the worker


class _Stopped(Exception):
    """The learner stopped the episode under way."""


class _Worker:
    """The worker's state: its connection, who drives, the request it answers."""

    def __init__(self, pipe: Pipe) -> None:
        self.pipe = pipe
        self.env: RemoteEnv | None = None
        self.driver: Driver | None = None
        self.request_id: int | None = None
        """The ``id`` of the request being handled: every message sent echoes it."""
        self._connection: dict[str, Any] | None = None
        """The last ``connect`` message: what a reconnect without a connection repeats."""
        self._last_sent = time.monotonic()

    def handle(self, message: dict[str, Any]) -> None:
        op = message.get("op")
        if op == "stop":  # for an episode that had already ended: nothing to stop
            return
        self.request_id = message.get("id")
        if op == "connect":
            self.connect(message)
        elif op == "reconnect":
            self.reconnect(float(message["timeout_s"]))
        elif op == "driver":
            self.driver = None  # a driver that cannot be built never leaves the last in place
            self.driver = driver_from_message(message)
            self.send({"op": "ready"})
        elif op == "episode":
            self.episode(int(message["index"]), int(message["seed"]))
        else:
            raise EvaluationWorkerFailed(f"unknown message {op!r}")

    def connect(self, message: dict[str, Any]) -> None:
        """Connect with the learner's scenario, reward and reset options; a server not up yet
        (or still holding a client that is gone) is retried for ``wait_s``."""
        self._connection = message
        if self.env is not None:
            self.env.close()
            self.env = None
        deadline = time.monotonic() + float(message.get("wait_s", 0.0))
        while self.env is None:
            try:
                scenario = message["scenario"]
                self.env = RemoteEnv(
                    str(message["address"]),
                    scenario if isinstance(scenario, str) else [str(s) for s in scenario],
                    reward=make_reward(str(message["reward"]), **message["reward_params"]),
                    timeout_s=float(message["timeout_s"]),
                    reset_timeout_s=float(message["reset_timeout_s"]),
                    **message["options"],
                )
            except (ServerUnavailable, ServerError) as exc:
                busy = isinstance(exc, ServerError) and exc.code == "busy"
                if not (busy or isinstance(exc, ServerUnavailable)):
                    raise
                if time.monotonic() >= deadline:
                    raise
                self.alive()
                time.sleep(CONNECT_RETRY_S)
        self.send({"op": "ready"})

    def reconnect(self, timeout_s: float) -> None:
        """Connect afresh, waiting up to `timeout_s` for the server (also after a first
        connection that failed)."""
        if self.env is None:
            if self._connection is None:
                raise EvaluationWorkerFailed("not connected: connect first")
            self.connect({**self._connection, "wait_s": timeout_s})
            return
        self.env.reconnect(timeout_s)
        self.send({"op": "ready"})

    def episode(self, index: int, seed: int) -> None:
        """Drive one episode; its summary, or ``stopped`` if the learner stopped it."""
        env, driver = self.env, self.driver
        if env is None or driver is None:
            raise EvaluationWorkerFailed("no connection or no driver: connect and send one first")
        steps = 0

        def between_steps(
            before: Observation, action: object, reward: float, after: Observation
        ) -> None:
            nonlocal steps
            steps += 1
            self.alive()
            if steps % STOP_POLL_STEPS == 0 and self.stop_requested():
                raise _Stopped

        try:
            episode = run_episode(env, driver, seed, index, on_step=between_steps)
        except _Stopped:
            self.send({"op": "stopped", "index": index})
            return
        summary = episode_summary(episode).to_dict()
        self.send({"op": "summary", "index": index, "summary": summary})

    def alive(self) -> None:
        """Tell the learner it is alive, if it has been quiet for `ALIVE_EVERY_S`."""
        if time.monotonic() - self._last_sent > ALIVE_EVERY_S:
            self.send({"op": "alive"})

    def stop_requested(self) -> bool:
        """Whether the learner sent a stop (the only message it sends during an episode)."""
        message = self.pipe.receive(0.0)
        if message is None:
            return False
        if message.get("op") != "stop":
            raise EvaluationWorkerFailed(f"{message.get('op')!r} during an episode")
        return True

    def send(self, message: dict[str, Any]) -> None:
        self.pipe.send({**message, "id": self.request_id})
        self._last_sent = time.monotonic()


def driver_message(driver: Driver) -> dict[str, Any]:
    """The ``driver`` request that has a worker drive as `driver` does: IDM's (and MOBIL's)
    parameters, or a policy's weights (float32 arrays as bytes) with its features, lanes and
    action scale."""
    if isinstance(driver, IDMDriver):
        return {"op": "driver", "kind": "idm", "params": driver.params.to_dict()}
    if isinstance(driver, IDMMobilDriver):
        params, mobil = driver.params.to_dict(), driver.mobil.to_dict()
        return {"op": "driver", "kind": "idm+mobil", "params": params, "mobil": mobil}
    if not isinstance(driver, PolicyDriver):
        raise ValueError(f"an evaluation worker drives IDM (+ MOBIL) or a policy, not {driver!r}")
    policy, critic = driver.policy, driver.policy.critic
    arrays = [*policy.actor.params, *(critic.params if critic is not None else ())]
    size = sum(np.asarray(p, dtype=np.float32).nbytes for p in arrays)
    if size > MAX_MESSAGE_BYTES // 2:
        raise UsageError(
            f"the policy's networks take {size / 2**20:.0f} MiB, more than an evaluation worker "
            f"reads ({MAX_MESSAGE_BYTES // 2**21} MiB): evaluate inline (--inline-evaluations)"
        )
    return {
        "op": "driver",
        "kind": "policy",
        "actor": [_array(p) for p in policy.actor.params],
        "critic": None if critic is None else [_array(p) for p in critic.params],
        "obs_dim": policy.obs_dim,
        "n_lanes": policy.n_lane_actions,
        "features": driver.features.name,
        "lane_phase_every": driver.features.lane_phase_every,
        "lanes": [
            driver.lanes.n_choices,
            driver.lanes.every,
            driver.lanes.gap_rule,
            driver.lanes.route_masks,
            "own"
            if driver.lanes.reference is None
            else "default"
            if driver.lanes.n_choices == 4
            else "follow",
        ],
        "scale": [driver.scale.low, driver.scale.high, driver.scale.reach, driver.scale.shield],
        "residual": driver.scale.residual,
        "interval": driver.scale.interval,
    }


def driver_from_message(message: dict[str, Any]) -> Driver:
    """The driver a ``driver`` message describes (`driver_message`)."""
    if message.get("kind") == "idm":
        return IDMDriver(IDMParams(**message["params"]))
    if message.get("kind") == "idm+mobil":
        return IDMMobilDriver(IDMParams(**message["params"]), MobilParams(**message["mobil"]))
    critic = message["critic"]
    policy = GreedyPolicy(
        [_from_array(p) for p in message["actor"]],
        None if critic is None else [_from_array(p) for p in critic],
        int(message["obs_dim"]),
        int(message["n_lanes"]),
    )
    features = FeatureMap(str(message["features"]), int(message["lane_phase_every"]))
    n_choices, every, gap_rule, route_masks, reference_lanes = message["lanes"]
    low, high, reach, shield = message["scale"]
    residual, interval = str(message["residual"]), float(message["interval"])
    lanes = lane_choice(
        int(n_choices), int(every), bool(gap_rule), residual, bool(route_masks),
        str(reference_lanes),
    )  # fmt: skip
    scale = ActionScale(float(low), float(high), residual, interval, float(reach), bool(shield))
    return PolicyDriver(policy, features, scale, lanes)


def _array(array: np.ndarray) -> dict[str, Any]:
    data = np.ascontiguousarray(array, dtype=np.float32)
    return {"shape": list(data.shape), "data": data.tobytes()}


def _from_array(message: dict[str, Any]) -> np.ndarray:
    shape = [int(n) for n in message["shape"]]
    return np.frombuffer(message["data"], dtype=np.float32).reshape(shape).copy()


def _messages(pipe: Pipe) -> Iterator[dict[str, Any]]:
    while True:
        message = pipe.receive(None)
        if message is not None:
            yield message


def serve(pipe: Pipe) -> None:
    """Answer the learner's requests until it closes the pipe. A failure is reported, not
    fatal: the learner decides (a reconnect, another episode, or giving the run up)."""
    worker = _Worker(pipe)
    try:
        for message in _messages(pipe):
            try:
                worker.handle(message)
            except (EOFError, BrokenPipeError):
                raise
            except Exception as exc:  # reported to the learner, which raises it there
                worker.send(error_message(exc))
    except (EOFError, BrokenPipeError):  # the learner closed the pipe (mid-episode): done
        pass
    finally:
        if worker.env is not None:
            worker.env.close()


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the learner stops us when it stops
    sys.stdout.flush()
    frames = os.dup(1)  # the messages' own descriptor: a stray print goes to stderr instead
    os.dup2(2, 1)
    serve(Pipe(sys.stdin.fileno(), frames))


if __name__ == "__main__":
    main()
