"""`RemoteEnv` and its scenario: what the kit passes, the learner runs on.

Options a scenario lacks (``decision_interval``), step lengths a 1.0/1.1 server left out, option
defaults of the wrong type, insertion failures retried on other seeds, and 1.0/1.1 servers.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from agent_client.cli.main import main
from agent_client.defaults import INSERTION_ATTEMPTS
from agent_client.envs.remote_env import RemoteEnv
from agent_client.envs.scenario import retry_seed
from agent_client.envs.vector_env import RemoteVectorEnv
from agent_client.errors import InsertionFailed, InvalidReply, UsageError
from protocol.codec import encode
from protocol.messages import Error, Reset
from tests.agent_client.conformance.toys import (
    IntegerDefault,
    NoDecisionInterval,
    NoStepLength,
    OldNoStepLength,
    ToyServer,
    request_of,
    rewrite_wire,
    zero_reward,
)

ACTION = {"acceleration": np.zeros(1, np.float32), "lane_change": 0}


def env_at(address: str, **options: object) -> RemoteEnv:
    return RemoteEnv(address, "cf", reward=zero_reward, timeout_s=2.0, **options)  # type: ignore[arg-type]


def run_episode_steps(env: RemoteEnv, steps: int = 3) -> list[int]:
    _, info = env.reset(seed=1)
    seqs = [info["observation"].seq]
    for _ in range(steps):
        *_, info = env.step(ACTION)
        seqs.append(info["observation"].seq)
    return seqs


# --------------------------------------------------------------------------- decision_interval


def test_a_scenario_without_decision_interval_runs_the_learner() -> None:
    with NoDecisionInterval() as server:
        env = env_at(server.address, decision_interval=0.1)  # its step length: dropped
        try:
            assert "decision_interval" not in env.options
            assert run_episode_steps(env) == [0, 1, 2, 3]
        finally:
            env.close()
        vector = RemoteVectorEnv([server.address], "cf", reward=zero_reward, decision_interval=0.1)
        vector.close()


def test_a_decision_interval_the_scenario_cannot_apply_is_a_usage_error() -> None:
    with NoDecisionInterval() as server:
        with pytest.raises(UsageError, match=r"no decision_interval option.*0\.1 s") as caught:
            env_at(server.address, decision_interval=1.0)
        assert "ask for 0.1" in str(caught.value)
        assert server.session.owner is None  # the refused client said goodbye


def test_an_unknown_option_is_still_a_usage_error() -> None:
    with ToyServer() as server, pytest.raises(UsageError, match="has no option 'flow'; known:"):
        env_at(server.address, flow=1200)


# --------------------------------------------------------------------------- the welcome


def test_a_1_1_server_without_step_length_gets_one_assumed_with_a_warning() -> None:
    with OldNoStepLength() as server:
        with pytest.warns(UserWarning, match=r"no step_length \(protocol 1\.1\): assuming 0\.1 s"):
            env = env_at(server.address)
        try:
            assert env.step_length == 0.1
            assert run_episode_steps(env) == [0, 1, 2, 3]
        finally:
            env.close()


@pytest.mark.parametrize(
    ("server_class", "field"),
    [
        (NoStepLength, "welcome.scenarios[0].step_length"),
        (IntegerDefault, "welcome.scenarios[0].options.max_episode_time"),
    ],
)
def test_a_welcome_that_breaks_a_rule_is_refused_naming_it(
    server_class: type[ToyServer], field: str
) -> None:
    with server_class() as server:
        with pytest.raises(InvalidReply) as caught:
            env_at(server.address)
        assert caught.value.field == field
        assert server.session.owner is None


class Protocol10(ToyServer):
    """A 1.0 server: no step_length, no changing_lane, no lane_change_aborted."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        reply = self.handle(peer, frame)
        reply = rewrite_wire(reply, "welcome", ("protocol",), [1, 0])
        reply = rewrite_wire(reply, "welcome", ("scenarios", 0, "step_length"), ...)
        reply = rewrite_wire(reply, "observation", ("ego", "changing_lane"), ...)
        return rewrite_wire(reply, "observation", ("events", "lane_change_aborted"), ...)


def test_a_1_0_server_still_drives() -> None:
    with Protocol10() as server:
        with pytest.warns(UserWarning, match=r"protocol 1\.0"):
            env = env_at(server.address)
        try:
            assert run_episode_steps(env, 5) == [0, 1, 2, 3, 4, 5]
            assert env.welcome.protocol == (1, 0)
        finally:
            env.close()


# --------------------------------------------------------------------------- insertion failures


class InsertionFails(ToyServer):
    """Answers the first `failures` resets with insertion_failed; records the seeds asked."""

    failures = 2

    def __init__(self) -> None:
        super().__init__()
        self.seeds: list[int | None] = []

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        request = request_of(frame)
        if isinstance(request, Reset):
            self.seeds.append(request.seed)
            if len(self.seeds) <= self.failures:
                return encode(Error("insertion_failed", "the ego could not enter within 60 s"))
        return self.handle(peer, frame)


class NeverInserts(InsertionFails):
    failures = 1000


def test_an_insertion_failure_is_retried_on_another_seed(caplog: pytest.LogCaptureFixture) -> None:
    with InsertionFails() as server:
        env = env_at(server.address)
        try:
            with caplog.at_level(logging.WARNING, "agent_client"):
                _, info = env.reset(seed=7)
        finally:
            env.close()
    assert server.seeds == [7, retry_seed(7, 1), retry_seed(7, 2)]
    assert info["seed"] == retry_seed(7, 2)  # the episode's real seed
    assert "could not enter with seed 7" in caplog.text
    assert len(set(server.seeds)) == 3 and all(0 <= s < 2**31 for s in server.seeds)  # type: ignore[operator]


def test_an_ego_that_never_enters_ends_with_a_clear_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with NeverInserts() as server:
        env = env_at(server.address)
        try:
            with pytest.raises(InsertionFailed) as caught:
                env.reset(seed=3)
        finally:
            env.close()
        assert len(server.seeds) == INSERTION_ATTEMPTS
        assert caught.value.seeds == server.seeds
        assert main(["drive", "--server", server.address, "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert f"could not enter in {INSERTION_ATTEMPTS} attempt(s)" in err
    assert "the ego could not enter within 60 s" in err


def test_drive_retries_an_insertion_failure(capsys: pytest.CaptureFixture[str]) -> None:
    with InsertionFails() as server:
        assert main(["drive", "--server", server.address, "--episodes", "1", "--json"]) == 0
    assert capsys.readouterr().out.count("\n") == 1  # one episode, driven
