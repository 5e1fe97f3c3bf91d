"""A server's readiness line (``listening on ADDRESS``), waited for with a deadline, and
stopping a child process with a grace period: how either side launches a server.

A child's stdout is read by a daemon thread into a queue, so a wait never blocks past its
deadline, two lines that arrive in one read are both seen (a selector on a buffered text stream
misses the second), and a chatty child never fills its pipe. Used by the ``--workers`` and
``--pool`` supervisors, a learner that starts simulators of its own, the tests and the
benchmarks: one implementation.
"""

from __future__ import annotations

import queue
import signal
import subprocess
import threading
import time
import weakref
from typing import IO, Any

LISTENING = "listening on "
"""The prefix of the readiness line every ``sim-server`` prints once it accepts requests."""


class NotReady(RuntimeError):
    """The awaited line did not come: the process exited, closed stdout or ran out of time."""


class LineReader:
    """The lines of one text stream, pumped by a daemon thread until end of file."""

    def __init__(self, stream: IO[str]) -> None:
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._ended = False
        self._thread = threading.Thread(target=self._pump, args=(stream,), daemon=True)
        self._thread.start()

    def _pump(self, stream: IO[str]) -> None:
        try:
            for line in stream:
                self._lines.put(line)
        except (OSError, ValueError):  # closed under us: the owner is cleaning up
            pass
        finally:
            self._lines.put(None)

    def wait_for(self, prefix: str, timeout_s: float) -> str | None:
        """The rest of the next line starting with `prefix` (stripped), or None on EOF/timeout."""
        deadline = time.monotonic() + timeout_s
        while not self._ended:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                line = self._lines.get(timeout=remaining)
            except queue.Empty:
                return None
            if line is None:
                self._ended = True
            elif line.startswith(prefix):
                return line[len(prefix) :].strip()
        return None


_readers: weakref.WeakKeyDictionary[subprocess.Popen[str], LineReader] = weakref.WeakKeyDictionary()
_readers_lock = threading.Lock()


def wait_for_line(process: subprocess.Popen[str], prefix: str, timeout_s: float) -> str:
    """Wait for `process` (started with ``stdout=PIPE, text=True``) to print a line that starts
    with `prefix`; returns the rest of it. Raises `NotReady` (the process left running: the
    caller decides) when the line does not come within `timeout_s`."""
    if process.stdout is None:
        raise ValueError("the process's stdout is not a pipe")
    with _readers_lock:
        reader = _readers.get(process)
        if reader is None:
            reader = _readers[process] = LineReader(process.stdout)
    found = reader.wait_for(prefix, timeout_s)
    if found is None:
        status = process.poll()
        why = f"exited with status {status}" if status is not None else f"not within {timeout_s} s"
        raise NotReady(f"no {prefix.strip()!r} line from {process.args!r}: {why}")
    return found


def stop_process(process: subprocess.Popen[Any], grace_s: float = 10.0, ask: bool = True) -> None:
    """Stop a child: SIGTERM (unless `ask` is False: it is already quitting), wait up to
    `grace_s`, then SIGKILL; always reaped, its stdout pipe closed."""
    if process.poll() is None:
        if ask:
            process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=grace_s)
    if process.stdout is not None:
        process.stdout.close()


def format_listening(endpoint: object) -> str:
    """The readiness line scripts wait for."""
    return f"{LISTENING}{endpoint}"
