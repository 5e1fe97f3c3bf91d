"""One evaluation server's driver, in a process of its own: a worker of `EvaluationPool`.

``python -m agent_client.training.eval_worker`` talks to the learner over its stdin and stdout in
the direct transport's frames (a 4-byte length, then a msgpack map; no pickle). It connects to
one evaluation server, then drives the episodes it is given one at a time with IDM or a policy
(its weights come in the message: the worker never imports torch), and answers each with the
episode's summary. While an episode runs it looks for a stop every `STOP_POLL_STEPS` steps and
says it is alive every `ALIVE_EVERY_S`, so the learner can end an evaluation that has failed
at once and tell a hung worker from a long episode.

Messages (each a map with an ``op``), learner to worker: ``connect`` (the server, the scenario,
the reward and the reset options), ``driver`` (IDM's parameters, or a policy's weights),
``episode`` (an index and a seed), ``stop``, ``reconnect``; worker to learner: ``ready``,
``summary``, ``stopped``, ``alive``, ``error`` (a `kind` the learner raises again as the
client's own exception).
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

from agent_client.drivers.episode import Driver, Episode
from agent_client.drivers.idm import IDMDriver, IDMParams
from agent_client.drivers.policy import ActionScale, PolicyDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import (
    AuthenticationFailed,
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
from agent_client.rl.lanes import LaneChoice
from agent_client.rl.rewards import make_reward
from protocol.transport.direct import FrameReader, frame

STOP_POLL_STEPS = 16
"""How often (in steps) a running episode looks for a stop from the learner."""
ALIVE_EVERY_S = 1.0
"""How often a worker in a long episode tells the learner it is alive."""
CONNECT_RETRY_S = 0.2
"""Pause between connection attempts to a server that is not back yet (``wait_s``)."""
MAX_MESSAGE_BYTES = 1 << 24

ERROR_KINDS: dict[str, type[Exception]] = {
    "timeout": ServerTimeout,
    "lost": ServerLost,
    "authentication": AuthenticationFailed,
    "malformed": MalformedReply,
    "usage": UsageError,
}
"""The client's exceptions a worker reports by name (`ServerError` carries its code too)."""


class EvaluationWorkerFailed(RuntimeError):
    """A worker failed in a way that is not the server's (a bug, a bad policy file)."""


_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(dict[str, Any])


class Pipe:
    """Messages over a pair of descriptors: a blocking writer and a reader with deadlines."""

    def __init__(self, read_fd: int, write_fd: int) -> None:
        self.read_fd = read_fd
        self.write_fd = write_fd
        self._reader = FrameReader(max_bytes=MAX_MESSAGE_BYTES)
        self._frames: list[bytes] = []

    def send(self, message: dict[str, Any]) -> None:
        data = memoryview(frame(_encoder.encode(message)))
        while data:
            data = data[os.write(self.write_fd, data) :]

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
    kind = next((k for k, cls in ERROR_KINDS.items() if isinstance(exc, cls)), "other")
    text = str(exc) if kind != "other" else f"{type(exc).__name__}: {exc}"
    return {"op": "error", "kind": kind, "message": text}


def raise_error(message: dict[str, Any], where: str) -> None:
    """Raise the exception an ``error`` message describes, naming the worker's server."""
    text = f"{where}: {message.get('message', '')}"
    if message.get("kind") == "server":
        raise ServerError(str(message.get("code", "")), text)
    raise ERROR_KINDS.get(str(message.get("kind")), EvaluationWorkerFailed)(text)


# ----------------------------------------------------------------------- the worker


class _Worker:
    """The worker's state: its connection and who drives."""

    def __init__(self, pipe: Pipe) -> None:
        self.pipe = pipe
        self.env: RemoteEnv | None = None
        self.driver: Driver | None = None
        self._last_sent = time.monotonic()

    def handle(self, message: dict[str, Any]) -> None:
        op = message.get("op")
        if op == "connect":
            self.connect(message)
        elif op == "driver":
            self.driver = driver_from_message(message)
        elif op == "episode":
            self.episode(int(message["job"]), int(message["index"]), int(message["seed"]))
        elif op == "reconnect":
            self._env().reconnect(float(message["timeout_s"]))
            self.send({"op": "ready"})
        elif op != "stop":  # a stop for an episode that had already ended: nothing to stop
            raise EvaluationWorkerFailed(f"unknown message {op!r}")

    def connect(self, message: dict[str, Any]) -> None:
        """Connect to the server with the learner's scenario, reward and reset options."""
        if self.env is not None:
            self.env.close()
            self.env = None
        deadline = time.monotonic() + float(message.get("wait_s", 0.0))
        while self.env is None:
            try:
                self.env = RemoteEnv(
                    str(message["address"]),
                    str(message["scenario"]),
                    reward=make_reward(str(message["reward"]), **message["reward_params"]),
                    timeout_s=float(message["timeout_s"]),
                    **message["options"],
                )
            except ServerUnavailable:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(CONNECT_RETRY_S)
        self.send({"op": "ready"})

    def _env(self) -> RemoteEnv:
        if self.env is None:
            raise EvaluationWorkerFailed("not connected: connect first")
        return self.env

    def episode(self, job: int, index: int, seed: int) -> None:
        """Drive one episode; its summary, or ``stopped`` if the learner stopped it."""
        env, driver = self._env(), self.driver
        if driver is None:
            raise EvaluationWorkerFailed("no driver: send one first")
        env.send_reset(seed=seed)
        obs = env.receive_reset_observation()
        episode = Episode(episode=index, seed=seed, step_length=env.step_length)
        episode.add(obs)
        steps = 0
        while not (obs.terminated or obs.truncated):
            acceleration, lane_change = driver.act(obs)
            env.send_command(acceleration, lane_change)
            obs, reward = env.receive_observation()
            episode.add(obs, reward)
            steps += 1
            if steps % STOP_POLL_STEPS == 0 and self.stop_requested():
                self.send({"op": "stopped", "job": job, "index": index})
                return
        summary = episode_summary(episode).to_dict()
        self.send({"op": "summary", "job": job, "index": index, "summary": summary})

    def stop_requested(self) -> bool:
        """Whether the learner sent a stop; says it is alive when it has been quiet long."""
        if time.monotonic() - self._last_sent > ALIVE_EVERY_S:
            self.send({"op": "alive"})
        message = self.pipe.receive(0.0)
        if message is None:
            return False
        if message.get("op") != "stop":
            raise EvaluationWorkerFailed(f"{message.get('op')!r} during an episode")
        return True

    def send(self, message: dict[str, Any]) -> None:
        self.pipe.send(message)
        self._last_sent = time.monotonic()


def driver_message(driver: Driver) -> dict[str, Any]:
    """The ``driver`` message that has a worker drive as `driver` does: IDM's parameters, or a
    policy's weights (float32 arrays as bytes) with its features, lanes and action scale."""
    if isinstance(driver, IDMDriver):
        return {"op": "driver", "kind": "idm", "params": driver.params.to_dict()}
    if not isinstance(driver, PolicyDriver):
        raise ValueError(f"an evaluation worker drives IDM or a policy, not {driver!r}")
    policy, critic = driver.policy, driver.policy.critic
    return {
        "op": "driver",
        "kind": "policy",
        "actor": [_array(p) for p in policy.actor.params],
        "critic": None if critic is None else [_array(p) for p in critic.params],
        "obs_dim": policy.obs_dim,
        "n_lanes": policy.n_lane_actions,
        "features": driver.features.name,
        "lane_phase_every": driver.features.lane_phase_every,
        "lanes": [driver.lanes.n_choices, driver.lanes.every, driver.lanes.gap_rule],
        "scale": [driver.scale.low, driver.scale.high],
    }


def driver_from_message(message: dict[str, Any]) -> Driver:
    """The driver a ``driver`` message describes (`driver_message`)."""
    if message.get("kind") == "idm":
        return IDMDriver(IDMParams(**message["params"]))
    critic = message["critic"]
    policy = GreedyPolicy(
        [_from_array(p) for p in message["actor"]],
        None if critic is None else [_from_array(p) for p in critic],
        int(message["obs_dim"]),
        int(message["n_lanes"]),
    )
    features = FeatureMap(str(message["features"]), int(message["lane_phase_every"]))
    n_choices, every, gap_rule = message["lanes"]
    low, high = message["scale"]
    lanes = LaneChoice(int(n_choices), int(every), bool(gap_rule))
    return PolicyDriver(policy, features, ActionScale(float(low), float(high)), lanes)


def _array(array: np.ndarray) -> dict[str, Any]:
    data = np.ascontiguousarray(array, dtype=np.float32)
    return {"shape": list(data.shape), "data": data.tobytes()}


def _from_array(message: dict[str, Any]) -> np.ndarray:
    shape = [int(n) for n in message["shape"]]
    return np.frombuffer(message["data"], dtype=np.float32).reshape(shape).copy()


def _messages(pipe: Pipe) -> Iterator[dict[str, Any]]:
    while True:
        try:
            message = pipe.receive(None)
        except EOFError:
            return
        if message is not None:
            yield message


def serve(pipe: Pipe) -> None:
    """Answer the learner's messages until it closes the pipe. A failure is reported, not
    fatal: the learner decides (a reconnect, another episode, or giving the run up)."""
    worker = _Worker(pipe)
    try:
        for message in _messages(pipe):
            try:
                worker.handle(message)
            except (EOFError, BrokenPipeError):
                raise
            except Exception as exc:  # reported to the learner, which raises it there
                worker.send({**error_message(exc), "job": message.get("job")})
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
