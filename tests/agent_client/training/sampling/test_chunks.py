"""`ChunkCollector`'s schedule over sampling workers, with workers faked in this process: each
worker asked until it has its requests in flight, policy copies sent when due, answers from
before a drop discarded, failures named, restarted workers given the policy, servers handed
back."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from agent_client.training.sampling.chunks import ChunkCollector
from agent_client.training.sampling.collect import Collected, Slot, Transition
from agent_client.training.sampling.worker import Chunk, SamplingFailed, Settings
from tests.integration.test_ray_sampling import spec


def transition(value: float) -> Transition:
    x = np.full(2, value, np.float32)
    mask = np.ones(1, bool)
    return Transition(x, value, 0, value, x, False, mask, mask)


@dataclass
class FakeWorkers:
    """Workers that answer at once: `steps` transitions per chunk, numbered by ask."""

    steps: int = 3
    asked: list[tuple[int, Any]] = field(default_factory=list)
    """(worker, policy sent) per ask."""
    answers: dict[int, list[Chunk | str]] = field(default_factory=dict)
    started: int = 0
    closed: int = 0
    drops: list[int] = field(default_factory=list)

    def start(self, specs: Sequence[Any], first_seed: int) -> None:
        self.started += 1

    def share(self, policy_state: dict[str, Any]) -> Any:
        return dict(policy_state)

    def ask(self, index: int, n_steps: int, settings: Settings, policy: Any | None) -> None:
        number = len(self.asked)  # its transitions carry the ask's number
        self.asked.append((index, policy))
        chunk = Chunk(transitions=[transition(number) for _ in range(self.steps)])
        self.answers.setdefault(index, []).append(chunk)

    def drop_episodes(self, index: int) -> None:
        self.drops.append(index)

    def wait(self, indices: Sequence[int], timeout_s: float) -> list[int]:
        return [i for i in indices if self.answers.get(i)]

    def answer(self, index: int) -> Chunk:
        answer = self.answers[index].pop(0)
        if isinstance(answer, str):
            raise SamplingFailed(answer)
        return answer

    def close(self) -> None:
        self.closed += 1


def collector(
    workers: FakeWorkers, n: int = 2, sync_every: int = 10, in_flight: int = 1
) -> ChunkCollector:
    policy = {"version": 0}
    return ChunkCollector(
        workers, [spec(f"tcp://127.0.0.1:{5555 + i}") for i in range(n)], lambda: policy,
        lambda: Settings(True), lambda: 100, chunk_steps=3, sync_every=sync_every,
        in_flight=in_flight,
    )  # fmt: skip


def test_each_idle_worker_is_asked_once_with_the_policy_when_it_is_due() -> None:
    workers = FakeWorkers()
    chunks = collector(workers, sync_every=10, in_flight=1)
    chunks.send()
    assert [(i, p is not None) for i, p in workers.asked] == [(0, True), (1, True)]
    assert len(chunks.receive().transitions) == 6
    chunks.send()  # 6 of 10 transitions since the copy: none sent
    assert [p is not None for _, p in workers.asked[2:]] == [False, False]
    chunks.receive()
    chunks.send()  # 12 since: a fresh copy to each
    assert [p is not None for _, p in workers.asked[4:]] == [True, True]


def test_answers_asked_for_before_a_drop_are_discarded_even_failed_ones() -> None:
    workers = FakeWorkers()
    chunks = collector(workers)
    chunks.send()
    workers.answers[1] = ["its server went away"]  # what it was sampling when dropped
    chunks.drop_episodes()
    assert workers.drops == [0, 1]
    assert chunks.receive().transitions == []  # both answers were from before the drop
    chunks.send()
    assert len(chunks.receive().transitions) == 6


def test_with_two_in_flight_a_worker_has_its_next_chunk_asked_before_it_answers() -> None:
    workers = FakeWorkers()
    chunks = collector(workers, in_flight=2)
    chunks.send()  # the policy with the first request only
    assert [(i, p is not None) for i, p in workers.asked] == [
        (0, True), (0, False), (1, True), (1, False),
    ]  # fmt: skip
    assert len(chunks.receive().transitions) == 6  # one answer of each: one still due of each
    chunks.send()  # each topped up to two again
    assert [i for i, _ in workers.asked[4:]] == [0, 1]
    assert len(chunks.receive().transitions) == 6


def test_with_two_in_flight_a_drop_discards_every_answer_asked_before_it() -> None:
    workers = FakeWorkers()
    chunks = collector(workers, in_flight=2)
    chunks.send()
    workers.answers[1][1] = "its server went away"  # the chunk it was asked ahead for
    chunks.drop_episodes()
    assert chunks.receive().transitions == []  # all four from before the drop
    chunks.send()
    assert len(workers.asked) == 8
    assert len(chunks.receive().transitions) == 6


def test_after_a_drop_the_answers_asked_before_it_go_and_the_later_ones_count() -> None:
    workers = FakeWorkers()
    chunks = collector(workers, in_flight=2)
    chunks.send()  # asks 0, 1 of worker 0; 2, 3 of worker 1
    assert asked_numbers(chunks.receive()) == [0, 2]
    chunks.drop_episodes()  # 1 and 3 were asked before it
    chunks.send()  # 4 of worker 0, 5 of worker 1
    assert asked_numbers(chunks.receive()) == [4, 5]  # none due now
    chunks.send()  # 6, 7 and 8, 9
    assert asked_numbers(chunks.receive()) == [6, 8]
    chunks.drop_episodes()
    chunks.drop_episodes()  # twice: still only 7 and 9 were asked before
    chunks.send()  # 10, 11
    assert asked_numbers(chunks.receive()) == [10, 11]


def asked_numbers(collected: Collected) -> list[int]:
    return sorted({int(t.u) for t in collected.transitions})


def test_in_flight_must_be_at_least_one() -> None:
    with pytest.raises(ValueError, match="in_flight must be at least 1, got 0"):
        collector(FakeWorkers(), in_flight=0)


def test_a_failed_worker_is_named_with_its_server() -> None:
    workers = FakeWorkers()
    chunks = collector(workers)
    chunks.send()
    workers.answers[1] = ["its process exited (exit code -9)"]
    with pytest.raises(SamplingFailed, match=r"worker 1 \(tcp://127.0.0.1:5556\) failed: .*-9"):
        chunks.receive()


def test_workers_started_again_after_a_release_get_the_policy_first() -> None:
    workers = FakeWorkers()
    chunks = collector(workers)
    chunks.send()
    chunks.receive()
    chunks.release(timeout_s=1.0)  # the run's end: no server to take back here
    assert workers.closed == 1
    chunks.send()  # a second run
    assert workers.started == 2
    assert [p is not None for _, p in workers.asked[-2:]] == [True, True]


def test_finished_episodes_keep_where_they_ended_among_the_transitions() -> None:
    first = Chunk(transitions=[transition(0)] * 5, finished=[slot(ended_at=2)], reconnects=1)
    second = Chunk(transitions=[transition(1)] * 4, finished=[slot(ended_at=None)])
    collected = Collected()
    collected.extend(first)
    collected.extend(second)
    assert [s.ended_at for s in collected.finished] == [2, 9]
    assert len(collected.transitions) == 9 and collected.reconnects == 1


def slot(ended_at: int | None) -> Slot:
    return Slot(0, None, np.zeros(2), np.ones(1, bool), None, ended_at=ended_at)  # type: ignore[arg-type]
