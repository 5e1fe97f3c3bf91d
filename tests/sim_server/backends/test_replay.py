"""The replay backend: a recording made through the client's channel against a conforming
in-process server (fake backend) is served back bit for bit, and every request that departs
from it is refused with its error while the server goes on serving (docs/recording.md)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from agent_client.drivers.episode import Driver, run_episode
from agent_client.drivers.idm import IDMDriver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import ServerError
from agent_client.transport import connect
from agent_client.transport.recording import WireRecorder
from protocol.codec import encode
from protocol.messages import Error, Hello, Observation, Reset, ScenarioInfo, Step, Welcome
from protocol.recording import REPLY, load, read_records, stream_name, write_manifest
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.replay import ReplayBackend
from sim_server.errors import BackendError
from sim_server.serve.zeromq import Server
from sim_server.session import Session
from tests.agent_client.conformance.toys import ToyServer
from tests.protocol.test_recording import WELCOME, observation, write

OPTIONS = {"length": 150.0}
SEEDS = [3, 4]


class Throttle:
    """A driver that always asks for the same acceleration (another policy than IDM)."""

    def __init__(self, acceleration: float) -> None:
        self.acceleration = acceleration

    def act(self, obs: Observation) -> tuple[float, int]:
        return self.acceleration, 0


def drive(address: str, folder: Path, runs: list[tuple[Driver, int]]) -> list[list[Observation]]:
    """Drive each (driver, seed) through one recorded `RemoteEnv`; every episode's observations."""
    with WireRecorder(folder, command="test") as recorder:
        env = RemoteEnv(address, "cf", recorder=recorder, **OPTIONS)
        try:
            return [run_episode(env, d, seed, i).observations for i, (d, seed) in enumerate(runs)]
        finally:
            env.close()


RUNS: list[tuple[Driver, int]] = [(IDMDriver(), 3), (IDMDriver(), 4), (Throttle(0.5), 3)]


@contextmanager
def replay_server(folder: Path) -> Iterator[str]:
    """`sim-server --backend replay` in a thread: our serving loop and session."""
    server = Server(Session(ReplayBackend(folder)), "tcp://127.0.0.1:0")
    thread = threading.Thread(target=server.serve, daemon=True)
    thread.start()
    try:
        yield str(server.endpoint)
    finally:
        server.stop()
        thread.join(timeout=5)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[list[Observation]]]:
    folder = tmp_path_factory.mktemp("replay") / "recording"
    with ToyServer() as server:
        return folder, drive(server.address, folder, RUNS)


@pytest.fixture(scope="module")
def replayed(recorded: tuple[Path, list[list[Observation]]]) -> Iterator[str]:
    with replay_server(recorded[0]) as address:
        yield address


def reply_frames(folder: Path) -> list[bytes]:
    path = folder / stream_name(0)
    return [record.frame for record in read_records(path) if record.direction == REPLY]


def test_the_same_drivers_and_seeds_get_the_same_frames_bit_for_bit(
    recorded: tuple[Path, list[list[Observation]]], replayed: str, tmp_path: Path
) -> None:
    folder, observations = recorded
    again = drive(replayed, tmp_path / "again", RUNS)
    assert again == observations
    assert reply_frames(tmp_path / "again") == reply_frames(folder)  # the welcome included


def test_the_welcome_is_the_recorded_one(
    recorded: tuple[Path, list[list[Observation]]], replayed: str
) -> None:
    with connect(replayed) as channel:
        welcome = channel.hello()
    assert welcome == load(recorded[0]).welcome
    assert welcome.backend == "fake"


def refused(channel: object, request: Reset | Step) -> Error:
    reply = channel.exchange(request)  # type: ignore[attr-defined]
    assert isinstance(reply, Error), reply
    return reply


@pytest.mark.parametrize(
    ("reset", "code", "words"),
    [
        (Reset("cf", 9, OPTIONS), "invalid_number", ["seed 9", "3, 4"]),
        (Reset("cf", 3, {"length": 300.0}), "invalid_option", ["length = 300.0", "150.0"]),
        (Reset("cf", 3, {}), "invalid_option", ["length = 1000.0"]),
    ],
)
def test_a_departing_reset_is_refused_and_the_server_goes_on(
    replayed: str, reset: Reset, code: str, words: list[str]
) -> None:
    with connect(replayed) as channel:
        channel.hello()
        error = refused(channel, reset)
        assert error.code == code
        assert "depart" in error.message
        for word in words:
            assert word in error.message
        assert isinstance(channel.request(Reset("cf", 4, OPTIONS)), Observation)


@pytest.mark.parametrize(
    ("step", "words"),
    [
        (lambda recorded: Step(1, recorded.acceleration + 1e-9, 0), ["step 1", "acceleration"]),
        (lambda recorded: Step(1, recorded.acceleration, -1), ["lane change -1"]),
    ],
)
def test_a_departing_step_is_refused_and_the_server_goes_on(
    recorded: tuple[Path, list[list[Observation]]], replayed: str, step: object, words: list[str]
) -> None:
    first = load(recorded[0]).episodes[1].steps[0].step  # IDM on seed 4: the only seed-4 episode
    with connect(replayed) as channel:
        channel.hello()
        channel.request(Reset("cf", 4, OPTIONS))
        error = refused(channel, step(first))  # type: ignore[operator]
        assert error.code == "invalid_number"
        for word in [*words, repr(first.acceleration)]:
            assert word in error.message
        assert refused(channel, Step(2, 0.0)).code == "out_of_order"  # that episode is over
        channel.request(Reset("cf", 4, OPTIONS))
        assert isinstance(channel.request(first), Observation)


def test_two_drivers_on_one_seed_each_replay_their_own_episode(
    recorded: tuple[Path, list[list[Observation]]], replayed: str
) -> None:
    with connect(replayed) as channel:
        channel.hello()
        channel.request(Reset("cf", 3, OPTIONS))
        reply = channel.request(Step(1, 0.5, 0))
    assert reply == recorded[1][2][1]  # the Throttle episode's first step, not IDM's


def hand_made(folder: Path, conversation: list[tuple[object, object]]) -> Path:
    folder.mkdir()
    write_manifest(folder, {"command": "test"})
    write(folder / stream_name(0), conversation)  # type: ignore[arg-type]
    return folder


TWO_SCENARIOS = Welcome(
    PROTOCOL_VERSION,
    WELCOME.server,
    WELCOME.backend,
    WELCOME.backend_version,
    (*WELCOME.scenarios, ScenarioInfo("cflc", "three lanes", {}, 0.1)),
    WELCOME.observation_fields,
    WELCOME.action,
    WELCOME.sensor_range,
    WELCOME.max_frame_bytes,
)


def test_a_scenario_never_recorded_is_unknown(tmp_path: Path) -> None:
    folder = hand_made(
        tmp_path / "rec",
        [(Hello(PROTOCOL_VERSION), TWO_SCENARIOS), (Reset("cf", 1), observation(0))],
    )
    backend = ReplayBackend(folder)
    assert [s.name for s in backend.scenarios()] == ["cf", "cflc"]
    with pytest.raises(BackendError, match="recorded scenarios: cf") as caught:
        backend.reset("cflc", 1, {})
    assert caught.value.code == "unknown_scenario"
    assert backend.reset("cf", 1, {"flow": 1500.0}) == observation(0)


def test_a_recorded_error_is_replayed_and_a_step_beyond_the_recording_is_out_of_order(
    tmp_path: Path,
) -> None:
    folder = hand_made(
        tmp_path / "rec",
        [
            (Hello(PROTOCOL_VERSION), WELCOME),
            (Reset("cf", 1), Error("insertion_failed", "the ego could not enter within 60 s")),
            (Reset("cf", 2), observation(0)),
            (Step(1, 0.5, 0), observation(1)),  # the recording stops while the episode runs
        ],
    )
    backend = ReplayBackend(folder)
    with pytest.raises(BackendError, match="could not enter within 60 s") as caught:
        backend.reset("cf", 1, {"flow": 1500.0})
    assert caught.value.code == "insertion_failed"
    backend.reset("cf", 2, {"flow": 1500.0})
    assert backend.step(1, 0.5, 0) == observation(1)
    with pytest.raises(BackendError, match="beyond the recording") as beyond:
        backend.step(2, 0.5, 0)
    assert beyond.value.code == "out_of_order"


def test_the_client_sees_a_departure_as_a_server_error(replayed: str) -> None:
    env = RemoteEnv(replayed, "cf", **OPTIONS)
    try:
        with pytest.raises(ServerError, match="seed 99 departs from the recording"):
            env.reset(seed=99)
        obs, _ = env.reset(seed=3)
    finally:
        env.close()
    assert obs.dtype.name == "float32"


def test_every_frame_of_the_recording_is_a_protocol_frame(
    recorded: tuple[Path, list[list[Observation]]],
) -> None:
    frames = reply_frames(recorded[0])
    assert frames[0] == encode(load(recorded[0]).welcome)
    assert len(frames) == sum(len(o) for o in recorded[1]) + 2  # + welcome and bye
