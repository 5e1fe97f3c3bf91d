"""`Requests`, a sampling process's view of its learner's pipe (a real pipe, in this process):
the next chunk asked ahead waits its turn, a drop or a close behind the chunk in hand
interrupts it, and requests come out in the order they were sent."""

from __future__ import annotations

import multiprocessing
import os

from agent_client.training.process_collect import Requests


def test_a_chunk_asked_ahead_waits_and_a_drop_behind_it_interrupts() -> None:
    learner, worker = multiprocessing.Pipe()
    requests = Requests(worker, os.getppid())
    learner.send(("sample", 64, None, None))
    learner.send(("sample", 64, None, None))
    order = iter(requests)
    assert next(order)[0] == "sample"  # the chunk in hand
    assert not requests.interrupted()  # the next one, asked ahead: not an interruption
    learner.send(("drop",))
    assert requests.interrupted()
    assert [next(order)[0], next(order)[0]] == ["sample", "drop"]
    assert not requests.interrupted()


def test_a_close_interrupts_too() -> None:
    learner, worker = multiprocessing.Pipe()
    requests = Requests(worker, os.getppid())
    assert not requests.interrupted()
    learner.send(("close",))
    assert requests.interrupted()
    assert next(iter(requests)) == ("close",)
