"""Blocking evaluations on servers of their own, one worker process per server.

While training waits for an evaluation, one client driving two servers in lock-step keeps three
processes busy on two cores, and the client's share of every step (choosing the action,
checking the reply, scoring it) is the slowest link. With a worker process per server
(`agent_client.training.eval_worker`) each pair of client and server steps on its own, and the
same episodes run ~1.4x as fast on the 2-core VM (docs/learner.md, "Evaluations during
training").

Seeds are handed out in order to whichever worker is free. The failure screen judges the
finished episodes in seed order (the first k seeds once all of them have finished), not in the
order the workers happen to finish them, so the same policy gets the same verdict, episodes and
steps whatever the timing: an evaluation stops at the first k whose figures have failed a target
whatever the other seeds give, and the episodes beyond k that had finished are dropped.
"""

from __future__ import annotations

import select
import subprocess
import sys
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.errors import ServerLost, ServerTimeout
from agent_client.evaluation.metrics import EpisodeSummary
from agent_client.training.eval_worker import ALIVE_EVERY_S, Pipe, driver_message, raise_error
from agent_client.training.evaluator import EvaluationJob, certain_failure
from protocol.messages import OptionValue

STOP_GRACE_S = 10.0
"""How long a worker may take to stop its episode and say so before it is given up."""


class _WorkerProcess:
    """The learner's handle on one worker: its process, its pipe, what it is running."""

    def __init__(self, address: str) -> None:
        self.address = address
        self.process = subprocess.Popen(
            [sys.executable, "-m", "agent_client.training.eval_worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            # A group of its own (a Ctrl-C to the terminal is the learner's), in the learner's
            # session: with the kernel's autogroup scheduling a session of its own would be a
            # scheduling group of its own, and the workers then ran at half the speed.
            process_group=0,
        )
        assert self.process.stdin is not None and self.process.stdout is not None
        self.pipe = Pipe(self.process.stdout.fileno(), self.process.stdin.fileno())
        self.running: int | None = None
        """The seed index of the episode it drives, None when idle."""

    @property
    def where(self) -> str:
        return f"evaluation worker for {self.address}"

    def send(self, message: dict[str, Any]) -> None:
        """Send `message`; `ServerLost` if the process is gone."""
        try:
            self.pipe.send(message)
        except OSError:  # a broken pipe: it died
            raise self._lost() from None

    def receive(self, timeout_s: float) -> dict[str, Any] | None:
        """Its next message (None after `timeout_s`); `ServerLost` if the process is gone."""
        try:
            return self.pipe.receive(timeout_s)
        except EOFError:
            raise self._lost() from None

    def _lost(self) -> ServerLost:
        self.running = None
        return ServerLost(f"the {self.where} exited (status {self.process.wait(timeout=10)})")

    def expect_ready(self, timeout_s: float) -> None:
        """Wait for ``ready``; the worker's error raised as the client's own exception."""
        deadline = time.monotonic() + timeout_s
        while True:
            message = self.receive(max(0.0, deadline - time.monotonic()))
            if message is None:
                raise ServerTimeout(f"the {self.where} was not ready within {timeout_s:g} s")
            if message.get("op") == "error":
                raise_error(message, self.where)
            if message.get("op") == "ready":
                return

    def close(self, kill: bool = False) -> None:
        """Close its stdin (it exits) and reap it; killed at once with `kill`, or if it does
        not exit in time."""
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
            process.wait(timeout=10)


class EvaluationPool:
    """Runs `EvaluationJob`s to their end, one worker process per evaluation server."""

    def __init__(
        self,
        addresses: Sequence[str],
        scenario: str,
        reward: str,
        reward_params: dict[str, Any],
        options: dict[str, OptionValue],
        timeout_s: float = STEP_TIMEOUT_S,
    ) -> None:
        """Start a worker per address and wait until each has shaken hands with its server."""
        if not addresses:
            raise ValueError("an evaluation pool needs at least one server")
        self._connect = {
            "op": "connect",
            "scenario": scenario,
            "reward": reward,
            "reward_params": dict(reward_params),
            "options": dict(options),
            "timeout_s": timeout_s,
        }
        self.silence_s = max(timeout_s, RESET_TIMEOUT_S) + 10 * ALIVE_EVERY_S
        """A worker quiet for longer is hung: its own waits on the server end sooner."""
        self.workers: list[_WorkerProcess] = []
        self._jobs = 0
        try:
            for address in addresses:
                self.workers.append(self._start(address))
            for worker in self.workers:
                worker.expect_ready(self.silence_s)
        except BaseException:
            self.close()
            raise

    @property
    def addresses(self) -> list[str]:
        return [worker.address for worker in self.workers]

    def run(self, job: EvaluationJob) -> list[EpisodeSummary]:
        """Drive `job` to its end (`job.driver` an `IDMDriver` or a `PolicyDriver`). The
        summaries in seed order; `job.stopped` set if it ended early."""
        driver = driver_message(job.driver)
        if not job.seeds:
            return []
        self._jobs += 1
        job_id = self._jobs
        for worker in self.workers:
            worker.send(driver)
        queue = deque(enumerate(job.seeds))
        done: dict[int, EpisodeSummary] = {}
        judged = 0  # the seeds 0..judged-1 have finished and passed the screen
        try:
            while True:
                for worker in self.workers:
                    if worker.running is None and queue:
                        index, seed = queue.popleft()
                        worker.send({"op": "episode", "job": job_id, "index": index,
                                          "seed": seed})  # fmt: skip
                        worker.running = index
                worker, message = self._next_message()
                if message.get("job") != job_id or message.get("op") != "summary":
                    continue
                worker.running = None
                done[int(message["index"])] = EpisodeSummary(**message["summary"])
                while judged < len(job.seeds) and judged in done:
                    judged += 1
                    finished = [done[i] for i in range(judged)]
                    if judged < len(job.seeds):
                        job.stopped = certain_failure(job, finished, range(judged, len(job.seeds)))
                    if job.stopped is not None or judged == len(job.seeds):
                        return finished
        finally:
            self._stop_running()

    def reconnect(self, timeout_s: float) -> None:
        """After `ServerUnavailable`: each worker connects afresh (waiting up to `timeout_s`
        for its server); a worker that died or hung is started again."""
        for index, worker in enumerate(self.workers):
            if worker.process.poll() is None and worker.running is None:
                worker.send({"op": "reconnect", "timeout_s": timeout_s})
            else:
                worker.close(kill=True)
                worker = self.workers[index] = self._start(worker.address, timeout_s)
            worker.expect_ready(timeout_s + self.silence_s)

    def close(self) -> None:
        """Stop every worker (never blocks for long)."""
        for worker in self.workers:
            worker.close()
        self.workers = []

    # ----------------------------------------------------------------------- internals

    def _start(self, address: str, wait_s: float = 0.0) -> _WorkerProcess:
        """A new worker, connecting to `address` (waiting up to `wait_s` for it to be up)."""
        worker = _WorkerProcess(address)
        worker.send({**self._connect, "address": address, "wait_s": wait_s})
        return worker

    def _next_message(self) -> tuple[_WorkerProcess, dict[str, Any]]:
        """The next message of a busy worker (``alive`` ones skipped); its error raised as the
        client's own exception; `ServerTimeout` if none has spoken for `silence_s`."""
        busy = [worker for worker in self.workers if worker.running is not None]
        deadline = time.monotonic() + self.silence_s
        while True:
            ready = [worker for worker in busy if worker.pipe.has_message()]
            if not ready:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise ServerTimeout(
                        f"no evaluation worker said anything in {self.silence_s:g} s "
                        f"({', '.join(worker.address for worker in busy)})"
                    )
                fds = {worker.pipe.read_fd: worker for worker in busy}
                readable, _, _ = select.select(list(fds), [], [], remaining)
                ready = [fds[fd] for fd in readable]
            for worker in ready:
                message = worker.receive(0.0)
                if message is None or message.get("op") == "alive":
                    deadline = time.monotonic() + self.silence_s
                    continue
                if message.get("op") == "error":
                    worker.running = None
                    raise_error(message, worker.where)
                return worker, message

    def _stop_running(self) -> None:
        """Stop the episodes still running and read their last word (a summary or ``stopped``
        that crossed the stop, or an error), so the next job starts on quiet pipes. A worker
        that does not answer in `STOP_GRACE_S` is started again."""
        for worker in self.workers:
            if worker.running is not None:
                try:
                    worker.send({"op": "stop"})
                except ServerLost:  # died meanwhile: `reconnect` starts it again
                    continue
        for index, worker in enumerate(self.workers):
            deadline = time.monotonic() + STOP_GRACE_S
            try:
                while worker.running is not None:
                    message = worker.receive(max(0.0, deadline - time.monotonic()))
                    if message is None:
                        raise ServerTimeout(f"the {worker.where} did not stop")
                    if message.get("op") in ("summary", "stopped", "error"):
                        worker.running = None
            except (ServerLost, ServerTimeout):
                worker.close(kill=True)
                self.workers[index] = self._start(worker.address)
