"""The conformance kit against in-process servers: a correct one passes, each broken one fails.

The servers (`tests.agent_client.conformance.toys`) are our real ZeroMQ serving loop and
`Session` with the fake backend, in a thread; each broken variant breaks exactly one rule of
docs/protocol.md.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import pytest
import zmq

from agent_client.cli.main import main
from agent_client.conformance import FAIL, PASS, SKIP, WARN, ConformanceReport, run_checks
from protocol.codec import encode
from protocol.messages import Close, Hello
from protocol.transport.zeromq import connect_req
from protocol.version import PROTOCOL_VERSION, format_version
from tests.agent_client.conformance.toys import (
    AcceptsAnyCommands,
    AcceptsBin,
    ActionAtSeqZero,
    AnswersAnotherSeq,
    AnswersLate,
    AnswersTwice,
    AppliedLaneChangeFive,
    BothFlags,
    ClosesForOthers,
    DropsRequestId,
    IgnoresSeed,
    IntegerDefault,
    KeepsDeadOwner,
    LaneOutOfRange,
    ListsEgosTwice,
    MultiWrongSeq,
    NaNSpeed,
    NoDecisionInterval,
    NoEgos,
    NoHandover,
    NoRetryCache,
    NoStepLength,
    NoVersionCheck,
    OldNoStepLength,
    OldProtocol,
    OneEgoOnly,
    ReasonWhileRunning,
    RefusedResetEndsEpisode,
    SeqZeroIsARetry,
    SilentOnGarbage,
    ToyServer,
    UnclippedAcceleration,
    UnknownReason,
    VagueVersionMessage,
    WrongErrorCode,
    WrongSeq,
    WrongStepLength,
)

OURS = format_version(PROTOCOL_VERSION)

CHECKS = [
    "transport", "handshake", "version_refusal", "schema", "reset", "step", "reconnect",
    "ownership", "termination", "ordering", "bad_requests", "error_codes", "determinism",
    "multi_ego", "close",
]  # fmt: skip


def statuses(report: ConformanceReport) -> dict[str, str]:
    return {result.name: result.status for result in report.results}


@pytest.fixture
def toy() -> Iterator[ToyServer]:
    with ToyServer() as server:
        yield server


def test_a_conforming_server_passes_every_check(toy: ToyServer) -> None:
    report = run_checks(toy.address, timeout_s=5.0)
    assert [r.name for r in report.results] == CHECKS
    assert statuses(report) == dict.fromkeys(CHECKS, PASS), report.format_table()
    assert report.exit_code == 0
    assert toy.session.owner is None  # the kit left the server free


def test_cli_prints_json_and_exits_0(toy: ToyServer, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--server", toy.address, "--json", "--timeout", "5"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True
    assert report["scenario"] == "cf"
    assert [c["name"] for c in report["checks"]] == CHECKS
    assert all(c["detail"] for c in report["checks"])


def test_cli_prints_a_table(toy: ToyServer, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--server", toy.address, "--scenario", "cf"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["check", "result", "detail"]
    assert f"CONFORMS - {len(CHECKS)} passed, 0 warnings, 0 failed" in out


BROKEN: list[tuple[type[ToyServer], str, str]] = [
    (DropsRequestId, "transport", "without the request-id frame"),
    (AnswersTwice, "transport", "exactly one reply"),
    (AnswersLate, "step", "no reply from"),
    (AnswersAnotherSeq, "step", "observation.seq = 1: 2 in the reply to step 2"),
    (NoHandover, "reconnect", "ZMQ_ROUTER_HANDOVER"),
    (KeepsDeadOwner, "ownership", "still answered busy"),
    (ClosesForOthers, "ownership", "expected error busy, got bye"),
    (NoVersionCheck, "version_refusal", "expected error version_mismatch"),
    (IntegerDefault, "schema", "max_episode_time = 300: a float option"),
    (NoStepLength, "schema", "step_length: required since protocol 1.2"),
    (WrongStepLength, "step", "instead of one decision of 0.05 s"),
    (NaNSpeed, "schema", "observation.ego.speed: nan is not a finite number"),
    (LaneOutOfRange, "schema", "observation.ego.lane = 7: a lane of the road at the ego, 0..0"),
    (ActionAtSeqZero, "schema", 'observation.action: zeros and "" at seq 0'),
    (AppliedLaneChangeFive, "step", "observation.action.lane_change = 5: 0 (refused) or 0"),
    (WrongSeq, "step", "observation.seq = 2: 1 in the reply to step 1"),
    (NoRetryCache, "step", "retry"),
    (UnclippedAcceleration, "step", "observation.action.acceleration = 1000: within the announced"),
    (ReasonWhileRunning, "step", "observation.reason = 'collision'"),
    (BothFlags, "termination", "observation.truncated = True: never true with terminated"),
    (UnknownReason, "termination", "observation.reason = 'timeout': a truncated episode's reason"),
    (SeqZeroIsARetry, "ordering", "step 0 after reset: expected error sequence_error"),
    (RefusedResetEndsEpisode, "ordering", "step 2"),
    (WrongErrorCode, "reset", "seed 2^31: expected error invalid_number, got invalid_message"),
    (SilentOnGarbage, "bad_requests", "garbage bytes: no reply from"),
    (AcceptsBin, "error_codes", "a bin scenario: expected error decode_error"),
    (MultiWrongSeq, "multi_ego", "multi_observation.seq = 3: 2 in the reply to multi_step 2"),
    (ListsEgosTwice, "multi_ego", "multi_observation.egos[1].id = 'ego': each ego once"),
    (
        AcceptsAnyCommands,
        "multi_ego",
        "a multi_step without commands: expected error invalid_message, got multi_observation",
    ),
]
"""Each broken server, the check it fails and words of that check's detail."""


@pytest.mark.parametrize(
    ("server_class", "failing", "words"), BROKEN, ids=[c.__name__ for c, _, _ in BROKEN]
)
def test_a_broken_server_fails_its_check_with_the_rule(
    server_class: type[ToyServer], failing: str, words: str
) -> None:
    with server_class() as server:
        started = time.monotonic()
        report = run_checks(server.address, timeout_s=1.0)
        elapsed = time.monotonic() - started
    result = {r.name: r for r in report.results}[failing]
    assert result.status == FAIL, report.format_table()
    assert words in result.detail, report.format_table()
    assert report.exit_code == 1
    assert elapsed < 60, report.format_table()
    failed_before = [r.name for r in report.results[: CHECKS.index(failing)] if r.status == FAIL]
    assert failed_before in ([], ["transport"]), report.format_table()


def test_a_server_without_the_request_id_frame_is_failed_at_once() -> None:
    """The hang of issue 14: the kit says why, runs nothing it cannot, and ends quickly."""
    with DropsRequestId() as server:
        started = time.monotonic()
        report = run_checks(server.address, timeout_s=3.0)
        elapsed = time.monotonic() - started
    status = statuses(report)
    assert status["transport"] == FAIL and status["handshake"] == FAIL
    assert "lack the request-id frame" in report.results[1].detail
    assert {status[name] for name in CHECKS[2:]} == {SKIP}
    assert elapsed < 5.0


def test_cli_exit_1_and_the_failing_row(capsys: pytest.CaptureFixture[str]) -> None:
    with WrongSeq() as server:
        assert main(["check", "--server", server.address, "--timeout", "1"]) == 1
    rows = [line.split()[:2] for line in capsys.readouterr().out.splitlines()]
    assert ["step", FAIL] in rows


@pytest.mark.parametrize(
    ("server_class", "warned", "words"),
    [
        (OldNoStepLength, "schema", "announces no step_length (protocol 1.1): assuming 0.1 s"),
        (VagueVersionMessage, "version_refusal", f"does not name 2.0 and {OURS}"),
    ],
)
def test_what_the_protocol_allows_but_should_not_be_is_a_warning(
    server_class: type[ToyServer], warned: str, words: str
) -> None:
    with server_class() as server:
        report = run_checks(server.address, timeout_s=2.0)
    result = {r.name: r for r in report.results}[warned]
    assert result.status == WARN and words in result.detail, report.format_table()
    assert report.exit_code == 0, report.format_table()


def test_a_scenario_without_decision_interval_conforms() -> None:
    with NoDecisionInterval() as server:
        report = run_checks(server.address, timeout_s=2.0)
    assert report.exit_code == 0, report.format_table()
    assert "each 0.1 s long" in {r.name: r for r in report.results}["step"].detail


def test_details_name_the_fault() -> None:
    with NoRetryCache() as server:
        detail = {r.name: r.detail for r in run_checks(server.address, timeout_s=2.0).results}
    assert "retry" in detail["step"]
    with SilentOnGarbage() as server:
        detail = {r.name: r.detail for r in run_checks(server.address, timeout_s=0.5).results}
    assert detail["bad_requests"].startswith("garbage bytes: no reply from")
    assert "within 0.5 s" in detail["bad_requests"]


def test_a_server_that_ignores_seeds_gets_a_warning_not_a_failure() -> None:
    with IgnoresSeed() as server:
        report = run_checks(server.address, timeout_s=5.0)
    assert statuses(report)["determinism"] == WARN
    assert "seeds seem ignored" in report.results[CHECKS.index("determinism")].detail
    assert report.exit_code == 0


def test_unreachable_server_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "--server", "tcp://127.0.0.1:1", "--timeout", "0.5"]) == 2
    assert "no reply from tcp://127.0.0.1:1 within 0.5 s" in capsys.readouterr().err
    assert main(["check", "--server", "tcp://127.0.0.1:1", "--timeout", "0.5", "--json"]) == 2
    assert json.loads(capsys.readouterr().out)["ok"] is False


def test_busy_server_and_bad_arguments_exit_2(
    toy: ToyServer, capsys: pytest.CaptureFixture[str]
) -> None:
    context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    other = connect_req(context, toy.address)
    try:
        for message in (Hello(PROTOCOL_VERSION), None, Close()):
            if message is None:
                assert main(["check", "--server", toy.address, "--timeout", "2"]) == 2
                assert "busy with another client" in capsys.readouterr().err
                continue
            other.send(encode(message))
            assert other.poll(5000)
            other.recv()
    finally:
        other.close(linger=0)
        context.term()
    assert main(["check", "--server", "localhost:5555"]) == 2
    assert "expected tcp://HOST:PORT" in capsys.readouterr().err
    assert main(["check", "--server", toy.address, "--scenario", "nowhere"]) == 2
    assert "offers no scenario 'nowhere'; offered: cf" in capsys.readouterr().err
    assert toy.session.owner is None


@pytest.mark.parametrize(
    ("server_class", "words"),
    [
        (ToyServer, "egos 2: 2 egos (ego.0, ego.1), 3 multi_steps judged"),
        (OneEgoOnly, "egos 2: invalid_option (one ego only)"),
        (NoEgos, "scenario cf offers no option egos (one ego only): nothing to check"),
        (OldProtocol, "protocol 1.3: many egos came with 1.4, nothing to check"),
    ],
    ids=["many", "one-ego-only", "no-egos-option", "protocol-1.3"],
)
def test_the_multi_ego_check_runs_what_the_server_offers(
    server_class: type[ToyServer], words: str
) -> None:
    with server_class() as server:
        report = run_checks(server.address, timeout_s=5.0)
    result = {r.name: r for r in report.results}["multi_ego"]
    assert result.status == PASS and words in result.detail, report.format_table()
    if server_class is not OldProtocol:  # its welcome's version differs from its behaviour
        assert report.exit_code == 0, report.format_table()
