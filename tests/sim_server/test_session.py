"""The protocol state machine, driven frame by frame (no sockets, fake backend)."""

from __future__ import annotations

from dataclasses import replace

import msgpack
import pytest

from protocol.codec import decode_reply, encode
from protocol.errors import ErrorCode
from protocol.messages import (
    Bye,
    Close,
    Command,
    Error,
    Hello,
    Message,
    MultiObservation,
    MultiStep,
    Observation,
    OptionValue,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.base import SINGLE_EGO_ID, Backend
from sim_server.backends.fake import FakeBackend
from sim_server.backends.options import SHARE_OPTIONS
from sim_server.errors import BackendError
from sim_server.session import Session

PEER = b"peer-1"


def ask(session: Session, message: Message, peer: bytes = PEER, now: float = 0.0) -> Message:
    return decode_reply(session.handle(peer, encode(message), now))


def ask_raw(session: Session, frame: bytes, peer: bytes = PEER) -> object:
    return decode_reply(session.handle(peer, frame, 0.0))


@pytest.fixture
def session() -> Session:
    return Session(FakeBackend(), max_frame_bytes=4096, session_timeout_s=5.0)


def started(session: Session) -> Observation:
    assert isinstance(ask(session, Hello(PROTOCOL_VERSION)), Welcome)
    obs = ask(session, Reset("cf", 1))
    assert isinstance(obs, Observation)
    return obs


def error_code(reply: object) -> str:
    assert isinstance(reply, Error), reply
    return reply.code


def test_handshake_announces_versions_schema_and_scenarios(session: Session) -> None:
    welcome = ask(session, Hello(PROTOCOL_VERSION, "t"))
    assert isinstance(welcome, Welcome)
    assert welcome.protocol == PROTOCOL_VERSION
    assert welcome.backend == "fake"
    assert [s.name for s in welcome.scenarios] == ["cf"]
    assert welcome.action.acceleration_min < 0 < welcome.action.acceleration_max
    assert welcome.observation_fields[0].name == "time"
    assert welcome.max_frame_bytes == 4096


@pytest.mark.parametrize(
    ("version", "fields"), [((1, 5), 32), ((1, 0), 32), ((1, 6), 36), ((1, 7), 37), ((1, 8), 40)]
)
def test_a_client_is_announced_the_flat_vector_of_its_version(
    session: Session, version: tuple[int, int], fields: int
) -> None:
    """A 1.5 client refuses a field it does not know: it is not told of the road's four."""
    welcome = ask(session, Hello(version))
    assert isinstance(welcome, Welcome)
    assert len(welcome.observation_fields) == fields
    assert welcome.protocol == PROTOCOL_VERSION
    obs = ask(session, Reset("cf", 1))
    assert isinstance(obs, Observation)
    assert obs.road is not None  # the named observation carries it; older readers skip it


def test_major_version_mismatch_is_refused_naming_both(session: Session) -> None:
    reply = ask(session, Hello((PROTOCOL_VERSION[0] + 1, 0)))
    assert error_code(reply) == "version_mismatch"
    assert isinstance(reply, Error)
    assert f"{PROTOCOL_VERSION[0] + 1}.0" in reply.message
    assert f"{PROTOCOL_VERSION[0]}.{PROTOCOL_VERSION[1]}" in reply.message


def test_requests_before_hello_are_out_of_order(session: Session) -> None:
    assert error_code(ask(session, Reset("cf", 1))) == "out_of_order"
    assert error_code(ask(session, Step(1, 0.0))) == "out_of_order"


def test_step_before_reset_is_out_of_order(session: Session) -> None:
    ask(session, Hello(PROTOCOL_VERSION))
    assert error_code(ask(session, Step(1, 0.0))) == "out_of_order"


def test_an_episode_runs_with_sequence_numbers(session: Session) -> None:
    assert started(session).seq == 0
    for seq in range(1, 4):
        obs = ask(session, Step(seq, 0.5))
        assert isinstance(obs, Observation)
        assert obs.seq == seq


def test_a_reset_without_seed_is_served_with_a_seed_of_the_servers_choosing(
    session: Session,
) -> None:
    ask(session, Hello(PROTOCOL_VERSION))
    obs = ask(session, Reset("cf", None))
    assert isinstance(obs, Observation)
    assert obs.seq == 0
    assert isinstance(ask(session, Step(1, 0.0)), Observation)


def test_a_repeated_step_is_answered_from_cache_without_advancing(session: Session) -> None:
    started(session)
    first = session.handle(PEER, encode(Step(1, 1.0)), 0.0)
    again = session.handle(PEER, encode(Step(1, 1.0)), 0.0)
    assert first == again
    second = decode_reply(session.handle(PEER, encode(Step(2, 1.0)), 0.0))
    once = decode_reply(first)
    assert isinstance(second, Observation) and isinstance(once, Observation)
    assert second.time == pytest.approx(once.time + 0.1)


def test_a_skipped_sequence_number_is_refused(session: Session) -> None:
    started(session)
    assert error_code(ask(session, Step(5, 0.0))) == "sequence_error"
    assert isinstance(ask(session, Step(1, 0.0)), Observation)


def test_lane_change_outside_minus_one_to_one_is_refused(session: Session) -> None:
    started(session)
    assert error_code(ask(session, Step(1, 0.0, 2))) == "invalid_number"


def test_options_are_checked_by_name_and_type(session: Session) -> None:
    ask(session, Hello(PROTOCOL_VERSION))
    assert error_code(ask(session, Reset("cf", 1, {"warp": 1}))) == "invalid_option"
    assert (
        error_code(ask(session, Reset("cf", 1, {"decision_interval": "fast"}))) == "invalid_option"
    )
    assert error_code(ask(session, Reset("mars", 1))) == "unknown_scenario"
    assert error_code(ask(session, Reset("cf", -5))) == "invalid_number"
    assert isinstance(ask(session, Reset("cf", 1, {"decision_interval": 1})), Observation)


@pytest.mark.parametrize(
    ("frame", "code"),
    [
        (b"\x00\xff garbage", "decode_error"),
        (msgpack.packb({"type": "hello", "protocol": [1, 0], "client": "x" * 5000}), "frame_too_large"),
        (msgpack.packb({"type": "step", "seq": 1, "acceleration": float("nan")}), "invalid_number"),
        (msgpack.packb({"type": "step", "seq": 1}), "invalid_message"),
        (msgpack.packb({"type": "teleport"}), "unknown_type"),
    ],
)  # fmt: skip
def test_bad_input_gets_an_error_and_the_session_goes_on(
    session: Session, frame: bytes, code: str
) -> None:
    started(session)
    assert error_code(ask_raw(session, frame)) == code
    assert isinstance(ask(session, Step(1, 0.0)), Observation)


def test_a_second_client_is_busy_until_the_first_goes_quiet(session: Session) -> None:
    started(session)
    assert error_code(ask(session, Hello(PROTOCOL_VERSION), peer=b"other", now=1.0)) == "busy"
    assert error_code(ask(session, Step(1, 0.0), peer=b"other", now=1.0)) == "busy"
    # After the session timeout (5 s of silence) a new client's hello takes over.
    assert isinstance(ask(session, Hello(PROTOCOL_VERSION), peer=b"other", now=10.0), Welcome)
    assert error_code(ask(session, Step(1, 0.0), peer=PEER, now=10.5)) == "busy"


def test_close_frees_the_simulator_for_another_client(session: Session) -> None:
    started(session)
    assert isinstance(ask(session, Close()), Bye)
    assert isinstance(ask(session, Hello(PROTOCOL_VERSION), peer=b"other", now=0.1), Welcome)


def test_a_finished_episode_refuses_further_steps_but_repeats_its_last_reply(
    session: Session,
) -> None:
    started(session)
    seq, obs = 0, None
    while obs is None or not (obs.terminated or obs.truncated):
        seq += 1
        reply = ask(session, Step(seq, 3.0))  # full throttle: crash or end of road
        assert isinstance(reply, Observation)
        obs = reply
    assert obs.reason in {"collision", "end_of_road"}
    assert obs.ceiling is not None
    assert ask(session, Step(seq, 3.0)) == obs
    assert error_code(ask(session, Step(seq + 1, 0.0))) == "out_of_order"


class ExplodingBackend(FakeBackend):
    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        if acceleration > 2:
            raise RuntimeError("simulated bug")
        if acceleration < -5:
            raise BackendError(__import__("protocol").ErrorCode.SIMULATOR_ERROR, "sim died")
        return super().step(seq, acceleration, lane_change)


def test_backend_failures_become_error_replies() -> None:
    session = Session(ExplodingBackend())
    started(session)
    assert error_code(ask(session, Step(1, 2.5))) == "simulator_error"
    assert error_code(ask(session, Step(1, 0.0))) == "out_of_order"  # episode is over
    assert isinstance(ask(session, Reset("cf", 2)), Observation)
    assert error_code(ask(session, Step(1, -5.5))) == "simulator_error"
    assert isinstance(ask(session, Reset("cf", 3)), Observation)


@pytest.mark.parametrize("version", [(1, 0), (1, 1), (1, 99)])
def test_clients_of_every_minor_version_are_served(
    session: Session, version: tuple[int, int]
) -> None:
    welcome = ask(session, Hello(version))
    assert isinstance(welcome, Welcome) and welcome.protocol == PROTOCOL_VERSION
    assert isinstance(ask(session, Reset("cf", 1)), Observation)
    assert isinstance(ask(session, Step(1, 0.0)), Observation)


def test_the_corners_of_the_state_machine(session: Session) -> None:
    """docs/protocol.md §7.4: each corner gets one answer."""
    started(session)
    for seq in (0, -1, 2):
        assert error_code(ask(session, Step(seq, 0.0))) == "sequence_error"
    assert isinstance(ask(session, Step(1, 0.0)), Observation)
    assert error_code(ask(session, Reset("nowhere", 1))) == "unknown_scenario"
    assert error_code(ask(session, Reset("cf", 1, {"warmup": None}))) == "invalid_option"
    assert isinstance(ask(session, Step(2, 0.0)), Observation)  # refused resets kept the episode
    assert error_code(ask(session, Close(), peer=b"other")) == "busy"  # not the owner's close
    assert isinstance(ask(session, Step(3, 0.0)), Observation)
    assert isinstance(ask(session, Hello(PROTOCOL_VERSION)), Welcome)
    assert error_code(ask(session, Step(4, 0.0))) == "out_of_order"  # hello ended the episode


def test_a_failed_reset_ends_the_running_episode() -> None:
    class NoEntry(FakeBackend):
        def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
            if seed == 9:
                raise BackendError(ErrorCode.INSERTION_FAILED, "the ego could not enter")
            return super().reset(scenario, seed, options)

    session = Session(NoEntry())
    started(session)
    assert error_code(ask(session, Reset("cf", 9))) == "insertion_failed"
    assert error_code(ask(session, Step(1, 0.0))) == "out_of_order"


# --------------------------------------------------------------------------- many egos (1.4)


def multi_started(session: Session, egos: int = 1) -> MultiObservation:
    assert isinstance(ask(session, Hello(PROTOCOL_VERSION)), Welcome)
    first = ask(session, Reset("cf", 1, {"egos": egos, "max_episode_time": 1.0}))
    assert isinstance(first, MultiObservation), first
    return first


def test_a_reset_naming_egos_is_a_multi_ego_episode_even_with_one(session: Session) -> None:
    first = multi_started(session)
    assert first.seq == 0 and [e.id for e in first.egos] == [SINGLE_EGO_ID]
    single = Session(FakeBackend())
    ask(single, Hello(PROTOCOL_VERSION))
    alone = ask(single, Reset("cf", 1, {"max_episode_time": 1.0}))
    assert isinstance(alone, Observation)
    assert first.egos[0].ego == alone.ego and first.time == alone.time  # the same episode
    many = ask(session, MultiStep(1, (Command(SINGLE_EGO_ID, 0.5),)))
    assert isinstance(many, MultiObservation) and many.seq == 1
    assert ask(session, MultiStep(1, (Command(SINGLE_EGO_ID, 0.5),))) == many  # a retry


def test_steps_must_match_the_episode_kind(session: Session) -> None:
    multi_started(session)
    assert error_code(ask(session, Step(1, 0.5))) == ErrorCode.OUT_OF_ORDER
    started(session)
    reply = ask(session, MultiStep(1, (Command(SINGLE_EGO_ID, 0.5),)))
    assert error_code(reply) == ErrorCode.OUT_OF_ORDER


@pytest.mark.parametrize(
    ("commands", "words"),
    [
        ((), "no command for 'ego'"),
        ((Command("ego.7", 0.5),), "no running ego 'ego.7'; no command for 'ego'"),
        ((Command(SINGLE_EGO_ID, 0.5), Command(SINGLE_EGO_ID, 1.0)), "a second command"),
    ],
)
def test_commands_must_be_one_per_running_ego(
    session: Session, commands: tuple[Command, ...], words: str
) -> None:
    multi_started(session)
    reply = ask(session, MultiStep(1, commands))
    assert error_code(reply) == ErrorCode.INVALID_MESSAGE
    assert isinstance(reply, Error) and words in reply.message
    assert isinstance(ask(session, MultiStep(1, (Command(SINGLE_EGO_ID, 0.5),))), MultiObservation)


def test_a_bad_lane_change_in_a_command_is_named(session: Session) -> None:
    multi_started(session)
    reply = ask(session, MultiStep(1, (Command(SINGLE_EGO_ID, 0.5, 2),)))
    assert isinstance(reply, Error) and reply.code == ErrorCode.INVALID_NUMBER
    assert "commands[0].lane_change 2" in reply.message


class OneEgo(FakeBackend):
    """The fake as a backend that drives one ego: the base class's adapters only."""

    max_egos = 1
    reset_many = Backend.reset_many
    step_many = Backend.step_many


def test_a_one_ego_backend_refuses_more_egos() -> None:
    session = Session(OneEgo())
    ask(session, Hello(PROTOCOL_VERSION))
    reply = ask(session, Reset("cf", 1, {"egos": 3}))
    assert isinstance(reply, Error) and reply.code == ErrorCode.INVALID_OPTION
    assert "at most 1 ego" in reply.message


def test_a_multi_ego_episode_ends_when_its_last_ego_ends(session: Session) -> None:
    first = multi_started(session)
    many = first
    while not (many.terminated or many.truncated):
        reply = ask(session, MultiStep(many.seq + 1, (Command(SINGLE_EGO_ID, 0.0),)))
        assert isinstance(reply, MultiObservation)
        many = reply
    assert many.truncated and many.egos[0].truncated and many.reason == "time_limit"
    after = ask(session, MultiStep(many.seq + 1, (Command(SINGLE_EGO_ID, 0.0),)))
    assert error_code(after) == ErrorCode.OUT_OF_ORDER


# --------------------------------------------------------------------------- ego_share (1.5)


class SharingFake(FakeBackend):
    """The fake announcing ``ego_share`` (it serves a share with its own egos): what the session
    itself checks of a share."""

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return tuple(
            replace(info, options={**info.options, **SHARE_OPTIONS}) for info in super().scenarios()
        )


def test_a_reset_naming_ego_share_is_a_multi_ego_episode() -> None:
    session = Session(SharingFake())
    ask(session, Hello(PROTOCOL_VERSION))
    first = ask(session, Reset("cf", 1, {"ego_share": 0.5, "max_episode_time": 1.0}))
    assert isinstance(first, MultiObservation) and first.seq == 0


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ({"ego_share": 0.5, "egos": 2}, "name egos (a number of egos) or ego_share"),
        ({"ego_share": 0.5, "egos": 1}, "name egos (a number of egos) or ego_share"),
        ({"ego_share": 0.0}, "option ego_share must be within (0, 1], got 0"),
        ({"ego_share": -0.5}, "option ego_share must be within (0, 1], got -0.5"),
        ({"ego_share": 1.5}, "option ego_share must be within (0, 1], got 1.5"),
        ({"ego_share": "half"}, "option ego_share must be float, got str"),
    ],
)
def test_a_bad_ego_share_is_refused_and_the_running_episode_goes_on(
    options: dict[str, OptionValue], words: str
) -> None:
    session = Session(SharingFake())
    ask(session, Hello(PROTOCOL_VERSION))
    first = ask(session, Reset("cf", 1, {"egos": 2}))
    assert isinstance(first, MultiObservation)
    reply = ask(session, Reset("cf", 1, options))
    assert isinstance(reply, Error) and reply.code == ErrorCode.INVALID_OPTION
    assert words in reply.message
    commands = tuple(Command(ego.id, 0.5) for ego in first.egos)
    assert isinstance(ask(session, MultiStep(1, commands)), MultiObservation)


def test_a_backend_that_does_not_offer_ego_share_refuses_it(session: Session) -> None:
    ask(session, Hello(PROTOCOL_VERSION))
    reply = ask(session, Reset("cf", 1, {"ego_share": 0.5}))
    assert isinstance(reply, Error) and reply.code == ErrorCode.INVALID_OPTION
    assert "has no option 'ego_share'" in reply.message
