"""`Evaluator`: greedy evaluations over held-out seeds on one or several servers, driven in
lock-step (`run`, or `send`/`receive` step by step), against conforming in-process servers
(fake backend)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from agent_client.drivers.idm import IDMDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.evaluation.metrics import aggregate
from agent_client.evaluation.targets import FailureScreen, targets_met
from agent_client.training.evaluations.inline import EvaluationJob, Evaluator
from protocol.messages import Observation
from tests.agent_client.conformance.toys import ToyServer, zero_reward
from tests.agent_client.transport.servers import DirectToy

SEEDS = [7, 3, 11, 5, 9]


class FullThrottle:
    """A driver that never brakes: it reaches its leader on the fake road."""

    def act(self, obs: Observation) -> tuple[float, int]:
        return 3.0, 0


@pytest.fixture
def envs() -> Iterator[list[RemoteEnv]]:
    with ToyServer() as first, ToyServer() as second:
        opened = [
            RemoteEnv(server.address, "cf", reward=zero_reward, timeout_s=5.0)
            for server in (first, second)
        ]
        try:
            yield opened
        finally:
            for env in opened:
                env.close()


def test_run_drives_every_seed_once_and_returns_them_in_seed_order(envs: list[RemoteEnv]) -> None:
    summaries = Evaluator(envs).run(EvaluationJob("idm", IDMDriver(), SEEDS))
    assert [s.seed for s in summaries] == SEEDS
    assert [s.episode for s in summaries] == list(range(len(SEEDS)))
    assert all(s.steps > 1 and s.collisions == 0 for s in summaries)


def test_the_same_seeds_give_the_same_episodes_on_one_server_or_two(
    envs: list[RemoteEnv],
) -> None:
    both = Evaluator(envs).run(EvaluationJob("idm", IDMDriver(), SEEDS))
    one = Evaluator(envs[:1]).run(EvaluationJob("idm", IDMDriver(), SEEDS))
    assert [(s.steps, s.average_speed) for s in both] == [(s.steps, s.average_speed) for s in one]


def test_a_stepwise_evaluation_finishes_only_when_every_seed_is_done(
    envs: list[RemoteEnv],
) -> None:
    evaluator = Evaluator(envs)
    job = EvaluationJob("idm", IDMDriver(), SEEDS[:3], context={"episode": 40})
    evaluator.start(job)
    with pytest.raises(RuntimeError, match="already running"):
        evaluator.start(job)
    iterations, result = 0, None
    while result is None:
        evaluator.send()
        result = evaluator.receive()
        iterations += 1
    finished, summaries = result
    assert finished is job and finished.context == {"episode": 40}
    assert len(summaries) == 3
    assert iterations > max(s.steps for s in summaries)  # one step per iteration, not all at once
    assert not evaluator.busy


def test_stop_on_collision_ends_the_evaluation_at_its_first_crash(envs: list[RemoteEnv]) -> None:
    everything = Evaluator(envs).run(EvaluationJob("policy", FullThrottle(), SEEDS))
    assert all(s.collisions for s in everything)
    stopped = Evaluator(envs).run(
        EvaluationJob("policy", FullThrottle(), SEEDS, stop_on_collision=True)
    )
    assert 1 <= len(stopped) < len(SEEDS)
    assert stopped[0].collisions


def test_an_aborted_evaluation_frees_the_evaluator(envs: list[RemoteEnv]) -> None:
    evaluator = Evaluator(envs)
    evaluator.start(EvaluationJob("idm", IDMDriver(), SEEDS))
    evaluator.send()
    evaluator.receive()
    evaluator.abort()
    assert not evaluator.busy and evaluator.receive() is None
    assert len(evaluator.run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))) == 2


def test_after_an_early_stop_every_connection_is_ready_for_the_next_request() -> None:
    """direct:// has no request ids: a reply left unread would answer the next request."""
    with DirectToy() as first, DirectToy() as second:
        envs = [
            RemoteEnv(s.address, "cf", reward=zero_reward, timeout_s=5.0) for s in (first, second)
        ]
        try:
            crash = EvaluationJob("policy", FullThrottle(), [4, 4, 4, 4], stop_on_collision=True)
            assert len(Evaluator(envs).run(crash)) < 4
            summaries = Evaluator(envs).run(EvaluationJob("idm", IDMDriver(), SEEDS[:2]))
            assert [s.seed for s in summaries] == SEEDS[:2]
        finally:
            for env in envs:
                env.close()


def test_a_screened_evaluation_ends_once_it_has_certainly_failed(envs: list[RemoteEnv]) -> None:
    everything = Evaluator(envs).run(EvaluationJob("idm", IDMDriver(), SEEDS))
    speed = sum(s.average_speed for s in everything) / len(SEEDS)
    # Bounds no faster than IDM itself on every seed, but a target just above it: the first
    # episodes already show the average cannot get there.
    bounds = [s.average_speed for s in everything]
    hopeless = FailureScreen(len(SEEDS), 1.05 * speed, speed_bounds=bounds)
    job = EvaluationJob("idm", IDMDriver(), SEEDS, screen=hopeless)
    stopped = Evaluator(envs).run(job)
    assert job.stopped == "as_fast_as_idm"
    assert 1 <= len(stopped) < len(SEEDS)
    reachable = FailureScreen(len(SEEDS), speed, speed_bounds=bounds)  # IDM exactly: it can
    job = EvaluationJob("idm", IDMDriver(), SEEDS, screen=reachable)
    Evaluator(envs).run(job)
    assert job.stopped != "as_fast_as_idm"
    if job.stopped is not None:  # the toy road's IDM is far from its ceiling: that may show
        assert not targets_met(aggregate(everything), {"average_speed": speed})[job.stopped]


def test_the_screen_judges_the_seeds_in_order(envs: list[RemoteEnv]) -> None:
    """Where an evaluation stops depends on the seeds' order only, not on which server's episode
    ends first: the fewest first seeds that have failed for certain."""
    everything = Evaluator(envs).run(EvaluationJob("idm", IDMDriver(), SEEDS))
    speed = sum(s.average_speed for s in everything) / len(SEEDS)
    bounds = [s.average_speed for s in everything]
    hopeless = FailureScreen(len(SEEDS), 1.05 * speed, speed_bounds=bounds)
    first = next(k for k in range(1, len(SEEDS)) if hopeless.failed(everything[:k], range(k, 5)))
    for servers in (envs, envs[:1]):
        job = EvaluationJob("idm", IDMDriver(), SEEDS, screen=hopeless)
        stopped = Evaluator(servers).run(job)
        assert job.stopped == "as_fast_as_idm"
        assert [s.to_dict() for s in stopped] == [s.to_dict() for s in everything[:first]]
