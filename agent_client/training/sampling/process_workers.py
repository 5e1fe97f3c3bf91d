"""Sampling workers in processes of their own: `ProcessWorkers`, the `Workers` group of
``sampling = "processes"``.

One process per server (or per simulator it starts), each a `SamplingWorker` behind a pipe, so
that stepping the servers never waits for the learner's update and the update never waits for a
lock-step round trip: on a machine with a core for the learner and cores for the simulators the
learner updates all the time while the workers sample. The processes are started with
``spawn`` (a fork of a process that has run torch is not safe) and never import torch: the
policy copy they act with is numpy (`agent_client.rl.greedy`).

The pipe is private to the learner and the process it started, as in Stable-Baselines3's
``SubprocVecEnv`` and Tianshou's subprocess workers: requests and chunks cross it as Python
objects (pickled by `multiprocessing`); nothing read from a network is unpickled. A worker
whose learner is gone (its pipe closed, or its parent changed) stops and says goodbye to its
server; a simulator it started stops with it (``--exit-with-parent``).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator, Sequence
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any

from agent_client.training.sampling.worker import (
    Chunk,
    SamplingFailed,
    SamplingWorker,
    Settings,
    WorkerSpec,
    policy_arrays,
)
from agent_client.training.simulators import READY_TIMEOUT_S

START_TIMEOUT_S = 60.0
"""How long a worker process may take to start Python and connect to its server (its own
simulator's start-up comes on top)."""
CLOSE_GRACE_S = 10.0
"""How long a worker may take to say goodbye to its server before it is killed."""
LEARNER_CHECK_S = 1.0
"""How often an idle worker checks that its learner is still there."""


class ProcessWorkers:
    """`SamplingWorker`s in processes of their own on this machine, one per spec."""

    def __init__(self) -> None:
        self._context = multiprocessing.get_context("spawn")
        self.processes: list[BaseProcess] = []
        self.pipes: list[Connection] = []
        self._failed: dict[int, str] = {}
        """Workers that could not be asked (their pipe broke): why, for `answer`."""

    def start(self, specs: Sequence[WorkerSpec], first_seed: int) -> None:
        for index, spec in enumerate(specs):
            pipe, child = self._context.Pipe()
            process = self._context.Process(
                target=serve,
                args=(child, spec, index, len(specs), first_seed),
                name=f"av-bridge sampling worker {index}",
                daemon=True,  # stopped at the learner's exit if close() was never reached
            )
            with _ctrl_c_ignored():
                process.start()
            child.close()
            self.processes.append(process)
            self.pipes.append(pipe)
        for index, spec in enumerate(specs):
            self._wait_ready(index, spec)

    def share(self, policy_state: dict[str, Any]) -> Any:
        return policy_arrays(policy_state)

    def ask(self, index: int, n_steps: int, settings: Settings, policy: Any | None) -> None:
        try:
            self.pipes[index].send(("sample", n_steps, settings, policy))
        except OSError as exc:  # it exited: `answer` says so
            self._failed[index] = self._exited(index, exc)

    def drop_episodes(self, index: int) -> None:
        with contextlib.suppress(OSError):  # an exited worker is reported by `answer`
            self.pipes[index].send(("drop",))

    def wait(self, indices: Sequence[int], timeout_s: float) -> list[int]:
        failed = [i for i in indices if i in self._failed]
        if failed:
            return failed
        by_pipe = {self.pipes[i]: i for i in indices}
        return sorted(by_pipe[pipe] for pipe in wait(list(by_pipe), timeout_s))  # type: ignore[index]

    def answer(self, index: int) -> Chunk:
        pipe = self.pipes[index]
        if index in self._failed and not self._readable(pipe):  # answers it sent come first
            raise SamplingFailed(self._failed.pop(index))
        try:
            kind, content = pipe.recv()
        except (EOFError, OSError) as exc:
            raise SamplingFailed(self._exited(index, exc)) from exc
        if kind != "chunk":
            raise SamplingFailed(str(content))
        return content  # type: ignore[no-any-return]

    def close(self) -> None:
        """Ask every worker to stop and wait `CLOSE_GRACE_S` for them together, reading (and
        dropping) the chunks they were sampling meanwhile, so that none blocks on a full pipe
        before its goodbye; kill the rest."""
        for pipe in self.pipes:
            with contextlib.suppress(OSError):
                pipe.send(("close",))
        deadline = time.monotonic() + CLOSE_GRACE_S
        open_pipes = list(self.pipes)
        while open_pipes and any(p.is_alive() for p in self.processes):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            for ready in wait(open_pipes, min(remaining, LEARNER_CHECK_S)):
                assert isinstance(ready, Connection)
                try:
                    ready.recv()
                except (EOFError, OSError):  # it has exited: nothing more to read
                    open_pipes.remove(ready)
        for process in self.processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.kill()
                process.join(CLOSE_GRACE_S)
        for pipe in self.pipes:
            pipe.close()
        self.processes, self.pipes = [], []
        self._failed.clear()

    def _wait_ready(self, index: int, spec: WorkerSpec) -> None:
        """The worker's first message: ready, or why it could not start."""
        timeout_s = START_TIMEOUT_S + spec.timeout_s
        if spec.simulator_args is not None:
            timeout_s += READY_TIMEOUT_S
        where = "its own simulator" if spec.simulator_args is not None else spec.address
        if not self.pipes[index].poll(timeout_s):
            raise SamplingFailed(
                f"sampling worker {index} ({where}) did not start within {timeout_s:g} s"
            )
        try:
            kind, content = self.pipes[index].recv()
        except (EOFError, OSError) as exc:
            why = self._exited(index, exc)
            raise SamplingFailed(
                f"sampling worker {index} ({where}): {why} before it could start; in a script "
                'of your own, start training under `if __name__ == "__main__":` (the '
                "workers are started with multiprocessing's spawn, which imports the script "
                'again), or set sampling = "local"'
            ) from exc
        if kind != "ready":
            raise SamplingFailed(f"sampling worker {index} ({where}) could not start: {content}")

    @staticmethod
    def _readable(pipe: Connection) -> bool:
        try:
            return pipe.poll()
        except (EOFError, OSError):
            return False

    def _exited(self, index: int, exc: BaseException) -> str:
        process = self.processes[index]
        process.join(1.0)
        code = process.exitcode
        return f"its process exited (exit code {code})" if code is not None else f"{exc!r}"


@contextlib.contextmanager
def _ctrl_c_ignored() -> Iterator[None]:
    """SIGINT ignored while a worker is spawned: the child inherits the ignored disposition
    (Python keeps it), so a Ctrl-C in the terminal while it imports, before `serve` moves it
    to a process group of its own, is the learner's alone (a blocked mask would not do: the
    spawn clears it). A Ctrl-C in the few milliseconds of the spawn itself is lost; the next
    one counts. Only the main thread can change a signal's handler: a worker started from
    another thread has that second unprotected."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def serve(pipe: Connection, spec: WorkerSpec, index: int, stride: int, first_seed: int) -> None:
    """A worker process's life: answer the learner's requests until it says close or is gone."""
    # Ctrl-C and a SIGTERM to the learner's process group are the learner's: it closes us, and
    # we stop by ourselves when it is gone. A group of our own (in its session: with the
    # kernel's autogroup scheduling a session of its own would be a scheduling group of its
    # own, as the evaluation workers found), SIGTERM left as it is (multiprocessing stops a
    # daemonic worker with it at the learner's exit).
    with contextlib.suppress(OSError):
        os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        worker = SamplingWorker(spec, index, stride, first_seed)
    except Exception as exc:  # sent to the learner, which raises it
        with contextlib.suppress(OSError):
            pipe.send(("error", _why(exc)))
        return
    requests = Requests(pipe, os.getppid())
    try:
        pipe.send(("ready", None))
        for request in requests:
            if request[0] == "sample":
                _, n_steps, settings, policy = request
                if requests.interrupted():  # asked ahead of a drop or close: not wanted
                    n_steps = 0  # (the policy copy it carries is taken all the same)
                try:
                    # a drop or a close asked while it runs ends it after a step: the
                    # learner reads what came, and a close is quick even in a long chunk
                    chunk = worker.sample(n_steps, settings, policy, requests.interrupted)
                    reply: tuple[str, Any] = ("chunk", chunk)
                except Exception as exc:  # the learner decides what a failure means
                    reply = ("error", _why(exc))
                pipe.send(reply)
            elif request[0] == "drop":
                worker.drop_episodes()
            else:  # close
                return
    except (EOFError, OSError):  # the learner is gone
        return
    finally:
        worker.close()


class Requests:
    """The learner's requests in the order it sent them, until it is gone (its end closed, or
    we were orphaned). A thread reads them as they come, so that the learner's sends never wait
    on ours: with two chunks in flight, a chunk and a policy copy each larger than the pipe's
    buffer, sent both ways at once, would otherwise wait on each other for ever. A drop or a
    close behind the request in hand interrupts it; a sample request (the next chunk, asked
    in advance) waits its turn."""

    def __init__(self, pipe: Connection, parent: int) -> None:
        self.pipe = pipe
        self.parent = parent
        self.queued: deque[tuple[Any, ...] | None] = deque()
        """Read, not yet handed out; None: the learner is gone."""
        self._inbox: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        threading.Thread(target=self._read, name="learner requests", daemon=True).start()

    def _read(self) -> None:
        """Every request as it comes, until the learner's end is closed (or we exit)."""
        try:
            while True:  # ends with the pipe: EOF once the learner closes it or is gone
                self._inbox.put(self.pipe.recv())
        except (EOFError, OSError):
            self._inbox.put(None)

    def __iter__(self) -> Iterator[tuple[Any, ...]]:
        while os.getppid() == self.parent or self.queued:
            if not self.queued:
                try:
                    self.queued.append(self._inbox.get(timeout=LEARNER_CHECK_S))
                except queue.Empty:
                    continue
            request = self.queued.popleft()
            if request is None:
                return
            yield request

    def interrupted(self) -> bool:
        """Whether a drop or a close came behind the request in hand, or the learner is gone."""
        while not self._inbox.empty():  # one reader of it: what is there stays there
            self.queued.append(self._inbox.get_nowait())
        return any(request is None or request[0] != "sample" for request in self.queued)


def _why(exc: Exception) -> str:
    return str(exc) or type(exc).__name__
