"""Evaluations on servers of their own, one worker process per server.

Where training waits for an evaluation, one client driving two servers in lock-step keeps three
processes busy on two cores, and the client's share of every step (choosing the action,
checking the reply, scoring it) is the slowest link. With a worker process per server
(`agent_client.training.evaluations.worker`) each pair of client and server steps on its own,
and the same episodes run 1.4-1.5x as fast on the 2-core VM (docs/learner-design.md,
"Evaluations during training: design and measurements").

Seeds are handed out in order to whichever worker is free, and the failure screen judges the
finished episodes in seed order (`judge_in_order`), as the lock-step evaluator does: the same
policy gets the same verdict, episodes and steps whichever worker finishes first.

A job can also run in the background (`start`, then `poll` now and then, `finish` for its
verdict): the trainer does so while it trains, with the workers (and their servers) in the
kernel's idle scheduling class, so that they use only the CPU time training leaves.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import select
import subprocess
import sys
import time
from collections import deque
from collections.abc import Iterator, Sequence
from typing import Any

from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.errors import BridgeError, ServerLost, ServerTimeout
from agent_client.evaluation.metrics import EpisodeSummary
from agent_client.training.evaluations.inline import EvaluationJob, judge_in_order
from agent_client.training.evaluations.worker import (
    ALIVE_EVERY_S,
    Pipe,
    driver_message,
    raise_error,
)
from protocol.messages import OptionValue

log = logging.getLogger(__name__)

STOP_GRACE_S = 10.0
"""How long a worker may take to stop its episode and say so before it is replaced."""


class _WorkerProcess:
    """The learner's handle on one worker: its process, its pipe, what it is doing."""

    def __init__(self, address: str, write_timeout_s: float) -> None:
        self.address = address
        self.process = subprocess.Popen(
            [sys.executable, "-m", "agent_client.training.evaluations.worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            # A group of its own (a Ctrl-C to the terminal is the learner's), in the learner's
            # session: with the kernel's autogroup scheduling a session of its own would be a
            # scheduling group of its own, and the workers then ran at half the speed.
            process_group=0,
        )
        assert self.process.stdin is not None and self.process.stdout is not None
        self.pipe = Pipe(self.process.stdout.fileno(), self.process.stdin.fileno(), write_timeout_s)
        self._ids = itertools.count(1)
        self.awaiting: int | None = None
        """The id of the request whose answer is due (None: nothing asked)."""
        self.running: int | None = None
        """The seed index of the episode it drives, None when idle."""
        self.last_heard = time.monotonic()
        self.closed = False

    @property
    def where(self) -> str:
        return f"evaluation worker for {self.address}"

    def request(self, message: dict[str, Any]) -> None:
        """Send a request; its answer is the one due next."""
        self.awaiting = next(self._ids)
        self.last_heard = time.monotonic()
        self.send({**message, "id": self.awaiting})

    def send(self, message: dict[str, Any]) -> None:
        """Send `message`; `ServerLost` if the process is gone, `ServerTimeout` (and the worker
        closed) if it stopped reading."""
        if self.closed:
            raise ServerLost(f"the {self.where} was closed")
        try:
            self.pipe.send(message)
        except TimeoutError as exc:  # part of a message may be in the pipe: it cannot go on
            self.close(kill=True)
            raise ServerTimeout(f"the {self.where} stopped reading: {exc}") from None
        except OSError:  # a broken pipe: it died
            raise self._lost() from None

    def answer(self, message: dict[str, Any] | None) -> dict[str, Any] | None:
        """`message` if it answers the request due (the error it reports raised); None for
        ``alive`` and for what is left over from an earlier request."""
        if message is None or message.get("id") != self.awaiting:
            return None
        self.last_heard = time.monotonic()
        if message.get("op") == "alive":
            return None
        self.awaiting = None
        if message.get("op") == "error":
            self.running = None
            raise_error(message, self.where)
        return message

    def wait_answer(self, timeout_s: float) -> dict[str, Any]:
        """The answer to the request due; `ServerTimeout` after `timeout_s` without a word."""
        while True:
            quiet = time.monotonic() - self.last_heard
            message = self.receive(max(0.0, timeout_s - quiet))
            if message is None and time.monotonic() - self.last_heard >= timeout_s:
                raise ServerTimeout(f"the {self.where} said nothing in {timeout_s:g} s")
            answer = self.answer(message)
            if answer is not None:
                return answer

    def receive(self, timeout_s: float) -> dict[str, Any] | None:
        """Its next message (None after `timeout_s`); `ServerLost` if the process is gone."""
        if self.closed:
            raise ServerLost(f"the {self.where} was closed")
        try:
            return self.pipe.receive(timeout_s)
        except EOFError:
            raise self._lost() from None

    def _lost(self) -> ServerLost:
        """The error for a worker whose pipe broke (killed if it is somehow still running)."""
        self.running = self.awaiting = None
        try:
            status = self.process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.process.kill()
            status = self.process.wait(timeout=10)
        return ServerLost(f"the {self.where} exited (status {status})")

    def close(self, kill: bool = False) -> None:
        """Close its pipes (it exits) and reap it; killed at once with `kill`, or if it does
        not exit in time."""
        self.closed = True
        process = self.process
        for pipe in (process.stdin, process.stdout):
            if pipe is not None:
                pipe.close()
        if kill:
            process.kill()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:  # unkillable for now: the OS reaps it later
                log.warning("the %s did not exit", self.where)


class EvaluationPool:
    """Runs `EvaluationJob`s, one at a time, one worker process per evaluation server."""

    def __init__(
        self,
        addresses: Sequence[str],
        scenario: str | Sequence[str],
        reward: str,
        reward_params: dict[str, Any],
        options: dict[str, OptionValue],
        timeout_s: float = STEP_TIMEOUT_S,
        idle_priority: bool = False,
        reset_timeout_s: float = RESET_TIMEOUT_S,
    ) -> None:
        """Start a worker per address and wait until each has shaken hands with its server.
        `idle_priority`: the workers run in the idle scheduling class (for background jobs)."""
        if not addresses:
            raise ValueError("an evaluation pool needs at least one server")
        self._connect = {
            "op": "connect",
            "scenario": scenario if isinstance(scenario, str) else list(scenario),
            "reward": reward,
            "reward_params": dict(reward_params),
            "options": dict(options),
            "timeout_s": timeout_s,
            "reset_timeout_s": reset_timeout_s,
        }
        self.idle_priority = idle_priority
        self.silence_s = max(timeout_s, reset_timeout_s) + 10 * ALIVE_EVERY_S
        """A worker silent for longer while the learner waits is hung: its own waits on its
        server end sooner, and at work it says it is alive every `ALIVE_EVERY_S`."""
        self.workers: list[_WorkerProcess] = []
        self.job: EvaluationJob | None = None
        """The job under way (None: `start` may begin one)."""
        self._queue: deque[tuple[int, int]] = deque()
        self._done: dict[int, EpisodeSummary] = {}
        self._judged = 0
        self._result: list[EpisodeSummary] | None = None
        try:
            for address in addresses:
                self.workers.append(self._start(address))
            for worker in self.workers:
                worker.wait_answer(self.silence_s)
        except BaseException:
            self.close()
            raise

    @property
    def busy(self) -> bool:
        return self.job is not None

    def run(self, job: EvaluationJob) -> list[EpisodeSummary]:
        """Drive `job` to its end (`job.driver` an `IDMDriver`, an `IDMMobilDriver` or a
        `PolicyDriver`). The
        summaries in seed order; `job.stopped` set if it ended early."""
        self.start(job)
        return self.finish()

    def start(self, job: EvaluationJob) -> None:
        """Give the workers `job`'s driver and their first seeds, and return: `poll` moves the
        job on, `finish` waits for its end."""
        if self.job is not None:
            raise RuntimeError("an evaluation is already running")
        driver = driver_message(job.driver)
        job.stopped = None
        self.job, self._result = job, None
        self._queue = deque(enumerate(job.seeds))
        self._done, self._judged = {}, 0
        if not job.seeds:
            self._result = []
            return
        with self._guard():
            for worker in self.workers:
                worker.request(driver)
            for worker in self.workers:
                worker.wait_answer(self.silence_s)
            self._dispatch()

    def poll(self) -> bool:
        """Read what the workers have said, without waiting, and hand the next seeds out;
        True once the job is done (`finish` then returns at once)."""
        if self.job is None:
            raise RuntimeError("no evaluation is running")
        with self._guard():
            while self._result is None and self._advance(timeout_s=0.0):
                pass
        return self._result is not None

    def finish(self) -> list[EpisodeSummary]:
        """Wait for the job's end: the summaries in seed order; `job.stopped` set if it ended
        early. A worker silent for `silence_s` from now on is hung (`ServerTimeout`)."""
        if self.job is None:
            raise RuntimeError("no evaluation is running")
        now = time.monotonic()
        for worker in self.workers:  # in the background, starved of CPU, it may have been quiet
            worker.last_heard = max(worker.last_heard, now)
        with self._guard():
            while self._result is None:
                self._advance(timeout_s=None)
        summaries, self._result, self.job = self._result, None, None
        return summaries

    def cancel(self) -> None:
        """Give the job under way up (its running episodes are stopped); never raises."""
        if self.job is not None:
            self._stop_running()
        self.job, self._result = None, None

    def reconnect(self, timeout_s: float) -> None:
        """After `ServerUnavailable`: each worker connects afresh, waiting up to `timeout_s`
        for its server; a worker that died, hung or was busy is replaced. A job under way is
        given up."""
        self.cancel()
        for index, worker in enumerate(self.workers):
            if worker.closed or worker.process.poll() is not None or worker.awaiting is not None:
                worker.close(kill=True)
                self.workers[index] = self._start(worker.address, wait_s=timeout_s)
            else:
                worker.request({"op": "reconnect", "timeout_s": timeout_s})
        for worker in self.workers:
            try:
                worker.wait_answer(timeout_s + self.silence_s)
            except ServerTimeout:
                if worker.awaiting is not None:  # silent, not a timeout it reported: hung
                    worker.close(kill=True)  # the next reconnect starts another
                raise

    def close(self) -> None:
        """Stop every worker (never blocks for long)."""
        workers, self.workers = self.workers, []
        self.job = None
        for worker in workers:
            worker.close()

    # ----------------------------------------------------------------------- internals

    @contextlib.contextmanager
    def _guard(self) -> Iterator[None]:
        """A job that fails is given up: its episodes are stopped (or, on Ctrl-C, the workers
        driving them killed, there is no time to stop them), and the error raised."""
        try:
            yield
        except Exception:
            self.cancel()
            raise
        except BaseException:
            for worker in self.workers:
                if worker.running is not None:
                    worker.close(kill=True)
            self.job, self._result = None, None
            raise

    def _dispatch(self) -> None:
        """Hand the next seeds, in order, to the idle workers."""
        for worker in self.workers:
            if worker.running is None and self._queue:
                index, seed = self._queue.popleft()
                worker.request({"op": "episode", "index": index, "seed": seed})
                worker.running = index

    def _advance(self, timeout_s: float | None) -> bool:
        """Take one answer (waiting up to `timeout_s`, None: as long as a worker is heard
        from) and act on it; False if none came. Once the judged seeds pass every seed or fail,
        the result is kept and the episodes still running are stopped."""
        job = self.job
        assert job is not None
        answer = self._next_answer(timeout_s)
        if answer is None:
            return False
        worker, message = answer
        worker.running = None
        if message.get("op") == "summary":  # else "stopped": only after a stop
            self._done[int(message["index"])] = EpisodeSummary(**message["summary"])
            self._judged, job.stopped = judge_in_order(job, self._done, self._judged)
            if job.stopped is not None or self._judged == len(job.seeds):
                self._result = [self._done[i] for i in range(self._judged)]
                self._stop_running()  # the episodes under way when the job ended early
                return True
        self._dispatch()
        return True

    def _start(self, address: str, wait_s: float = 0.0) -> _WorkerProcess:
        """A new worker, connecting to `address` (waiting up to `wait_s` for it to be up);
        its ``ready`` is the answer due."""
        worker = _WorkerProcess(address, write_timeout_s=self.silence_s)
        try:
            if self.idle_priority:
                _set_idle_priority(worker.process.pid)
            worker.request({**self._connect, "address": address, "wait_s": wait_s})
        except BaseException:
            worker.close(kill=True)
            raise
        return worker

    def _next_answer(self, timeout_s: float | None) -> tuple[_WorkerProcess, dict[str, Any]] | None:
        """The next answer of a busy worker, its error raised as the client's own exception;
        None after `timeout_s`. With `timeout_s` None, `ServerTimeout` for a worker silent for
        `silence_s`."""
        busy = [worker for worker in self.workers if worker.running is not None]
        if not busy:
            raise ServerLost("no evaluation worker is driving an episode")
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            ready = [worker for worker in busy if worker.pipe.has_message()]
            if not ready:
                now = time.monotonic()
                if deadline is None:
                    silent = [w for w in busy if now - w.last_heard >= self.silence_s]
                    if silent:
                        raise ServerTimeout(
                            f"the {silent[0].where} said nothing in {self.silence_s:g} s"
                        )
                    remaining = min(w.last_heard for w in busy) + self.silence_s - now
                else:
                    remaining = max(0.0, deadline - now)
                fds = {worker.pipe.read_fd: worker for worker in busy}
                readable, _, _ = select.select(list(fds), [], [], remaining)
                ready = [fds[fd] for fd in readable]
                if not ready and deadline is not None and time.monotonic() >= deadline:
                    return None
            for worker in ready:
                answer = worker.answer(worker.receive(0.0))
                if answer is not None:
                    return worker, answer

    def _stop_running(self) -> None:
        """Stop the episodes still running and read their answers (a summary or ``stopped``
        that crossed the stop, or an error), so the next job starts on quiet pipes. A worker
        that is gone, or does not answer within `STOP_GRACE_S` of the stop, is replaced; one
        that cannot be is left closed (the next job's `ServerLost` has `reconnect` start
        another). Never raises: the job's own outcome stands."""
        stopping = [w for w in self.workers if w.running is not None and not w.closed]
        for worker in stopping:
            worker.last_heard = time.monotonic()  # the grace counts from the stop
            with contextlib.suppress(BridgeError):  # gone: replaced below
                worker.send({"op": "stop"})
        for worker in stopping:
            try:
                worker.wait_answer(STOP_GRACE_S)
                replace = False
            except BridgeError:  # an error answers the request; silence or death do not
                replace = worker.awaiting is not None or worker.process.poll() is not None
            except Exception:  # whatever it sent (a frame it cannot read...), it cannot go on
                log.exception("the %s failed", worker.where)
                replace = True
            worker.running = None
            if replace:
                self._replace(worker)

    def _replace(self, worker: _WorkerProcess) -> None:
        """Kill `worker` and start another on its server (left closed if that fails)."""
        worker.close(kill=True)
        try:
            replacement = self._start(worker.address, wait_s=STOP_GRACE_S)
        except (OSError, BridgeError):  # the next job's ServerLost tells the learner
            return
        try:
            replacement.wait_answer(STOP_GRACE_S + self.silence_s)
        except Exception:  # a replacement that cannot connect is not kept
            replacement.close(kill=True)
            return
        self.workers[self.workers.index(worker)] = replacement


def _set_idle_priority(pid: int) -> None:
    """Move process `pid` to the idle scheduling class, where the platform has one."""
    if hasattr(os, "SCHED_IDLE"):
        with contextlib.suppress(ProcessLookupError):  # it died already: the next read says so
            os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
