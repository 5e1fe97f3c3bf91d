"""`Requests`, a sampling process's view of its learner's pipe (a real pipe, in this process):
the next chunk asked ahead waits its turn, a drop or a close behind the chunk in hand
interrupts it, requests come out in the order they were sent, and the learner's sends never
wait on the worker's (the deadlock that two large messages crossing would make)."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable

import numpy as np

from agent_client.training.sampling.process_workers import Requests

WAIT_S = 10.0


def until(condition: Callable[[], bool]) -> bool:
    """Whether `condition` holds within `WAIT_S` (the reading thread's hand-over)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return False


def test_a_chunk_asked_ahead_waits_and_a_drop_behind_it_interrupts() -> None:
    learner, worker = multiprocessing.Pipe()
    requests = Requests(worker, os.getppid())
    learner.send(("sample", 64, None, None))
    learner.send(("sample", 64, None, None))
    order = iter(requests)
    assert next(order)[0] == "sample"  # the chunk in hand
    assert until(lambda: not requests.interrupted() and len(requests.queued) == 1)
    learner.send(("drop",))
    assert until(requests.interrupted)
    assert [next(order)[0], next(order)[0]] == ["sample", "drop"]
    assert not requests.interrupted()
    learner.close()


def test_a_close_or_the_learner_gone_interrupts_too() -> None:
    learner, worker = multiprocessing.Pipe()
    requests = Requests(worker, os.getppid())
    assert not requests.interrupted()
    learner.send(("close",))
    assert until(requests.interrupted)
    assert next(iter(requests)) == ("close",)
    learner.close()  # gone: the requests end
    assert until(requests.interrupted)
    assert list(requests) == []


def test_a_large_request_goes_through_while_the_worker_sends_a_large_chunk() -> None:
    """Both larger than the pipe's buffer, sent at once both ways: neither waits for ever."""
    learner, worker = multiprocessing.Pipe()
    requests = Requests(worker, os.getppid())
    big = np.zeros(1_000_000, np.float32)  # 4 MB
    threading.Thread(target=worker.send, args=(("chunk", big),), daemon=True).start()
    asked = threading.Event()

    def learner_asks() -> None:  # a policy copy with it
        learner.send(("sample", 64, None, big))
        asked.set()

    threading.Thread(target=learner_asks, daemon=True).start()
    assert asked.wait(WAIT_S)  # read by the worker's thread, though the worker is sending
    assert until(lambda: not requests.interrupted() and len(requests.queued) == 1)
    kind, chunk = learner.recv()
    assert kind == "chunk" and chunk.shape == big.shape
    learner.close()
