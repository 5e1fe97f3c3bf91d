"""Recording at the channel: every frame sent and received, in order, on either transport, a
malformed reply included; the manifest says what was recorded (docs/recording.md)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import AbstractContextManager
from pathlib import Path

import pytest

from agent_client.envs.remote_env import RemoteEnv
from agent_client.errors import InvalidReply, UsageError
from agent_client.transport import connect
from agent_client.transport.channel import Channel
from agent_client.transport.recording import WireRecorder
from protocol.codec import encode
from protocol.messages import Bye, Close, Hello, Reset, Step
from protocol.recording import MANIFEST, REPLY, REQUEST, read_records, stream_name
from protocol.version import PROTOCOL_VERSION, format_version
from tests.agent_client.conformance.toys import ToyServer, request_of
from tests.agent_client.transport.servers import DirectToy


class GarbledSteps(ToyServer):
    """Answers every step with a frame that is no msgpack map."""

    def answer(self, peer: bytes, frame: bytes) -> bytes | None:
        if isinstance(request_of(frame), Step):
            return b"\x93\x01\x02\x03"
        return self.handle(peer, frame)


@pytest.fixture(params=["zeromq", "direct"])
def server(request: pytest.FixtureRequest) -> Iterator[str]:
    toy: AbstractContextManager[ToyServer | DirectToy] = (
        ToyServer() if request.param == "zeromq" else DirectToy()
    )
    with toy as running:
        yield running.address


def test_a_channel_without_a_tap_records_nothing() -> None:
    assert Channel.tap is None


def test_every_frame_is_recorded_in_order_on_either_transport(server: str, tmp_path: Path) -> None:
    requests = [Hello(PROTOCOL_VERSION, "test"), Reset("cf", 1), Step(1, 0.5), Step(9, 0.5)]
    with WireRecorder(tmp_path / "rec") as recorder, connect(server) as channel:
        recorder.tap(channel)
        replies = [encode(channel.exchange(request)) for request in requests]
        channel.exchange_raw(b"\xc1")  # not msgpack: answered decode_error
    records = list(read_records(tmp_path / "rec" / stream_name(0)))
    assert [r.direction for r in records] == [REQUEST, REPLY] * 5
    assert [r.frame for r in records[0::2]] == [*(encode(r) for r in requests), b"\xc1"]
    assert [r.frame for r in records[1::2]][:4] == replies  # our server's frames re-encode alike


def test_a_malformed_reply_is_recorded_before_it_is_refused(tmp_path: Path) -> None:
    with (
        GarbledSteps() as toy,
        WireRecorder(tmp_path / "rec") as recorder,
        connect(toy.address) as channel,
    ):
        recorder.tap(channel)
        channel.hello()
        channel.request(Reset("cf", 1))
        with pytest.raises(InvalidReply):
            channel.request(Step(1, 0.0))
    frames = [r.frame for r in read_records(tmp_path / "rec" / stream_name(0))]
    assert frames[-1] == b"\x93\x01\x02\x03"


def manifest(folder: Path) -> dict[str, object]:
    result: dict[str, object] = json.loads((folder / MANIFEST).read_text())
    return result


def test_the_manifest_says_what_was_recorded_and_is_completed_at_close(tmp_path: Path) -> None:
    folder = tmp_path / "a" / "b"  # missing parents are made
    with ToyServer() as toy:
        recorder = WireRecorder(folder, command="test", seeds=[5])
        env = RemoteEnv(toy.address, "cf", recorder=recorder, length=100.0)
        assert manifest(folder)["complete"] is False
        env.reset(seed=5)
        env.close()
        recorder.close()
    written = manifest(folder)
    assert written["format"] == "av-bridge-recording" and written["format_version"] == 1
    assert written["protocol"] == format_version(PROTOCOL_VERSION) and written["seeds"] == [5]
    assert written["complete"] is True
    (stream,) = written["streams"]  # type: ignore[misc]
    assert stream["server"] == toy.address and stream["welcome"]["backend"] == "fake"
    (episode,) = written["episodes"]  # type: ignore[misc]
    assert episode == {
        "episode": 0,
        "stream": stream_name(0),
        "scenario": "cf",
        "seed": 5,
        "options": {"length": 100.0},
        "steps": 0,
        "end": "unfinished",
    }


def test_a_reconnect_records_a_new_session(tmp_path: Path) -> None:
    with ToyServer() as toy, WireRecorder(tmp_path / "rec") as recorder:
        env = RemoteEnv(toy.address, "cf", recorder=recorder)
        try:
            env.reconnect(timeout_s=5.0)
            env.reset(seed=1)
        finally:
            env.close()
    first, second = (
        [r.frame for r in read_records(tmp_path / "rec" / stream_name(i))] for i in (0, 1)
    )
    assert len(first) == 2  # hello, welcome: then the channel was closed
    assert len(second) == 6  # hello, welcome, reset, observation, close, bye
    assert second[-2:] == [encode(Close()), encode(Bye())]


def test_an_unusable_folder_is_a_usage_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(UsageError, match="cannot create the recording folder"):
        WireRecorder(blocker / "rec")
