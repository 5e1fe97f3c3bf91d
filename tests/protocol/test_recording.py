"""The recording format: frames written and read back byte for byte, refusals of what is not a
recording, and a stream read as the server's state machine saw it (docs/recording.md)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from protocol.codec import encode
from protocol.messages import (
    ActionSchema,
    Bye,
    Close,
    Error,
    Hello,
    Message,
    Observation,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.recording import (
    MAGIC,
    MANIFEST,
    REPLY,
    REQUEST,
    Record,
    RecordingError,
    StreamWriter,
    exchanges,
    load,
    read_manifest,
    read_records,
    read_stream,
    stream_name,
    write_manifest,
)
from protocol.schema import OBSERVATION_FIELDS
from protocol.version import PROTOCOL_VERSION
from tests.protocol.test_codec import make_observation

WELCOME = Welcome(
    PROTOCOL_VERSION,
    "sim_server test",
    "fake",
    "1",
    (ScenarioInfo("cf", "a road", {"flow": 1500.0}, 0.1),),
    OBSERVATION_FIELDS,
    ActionSchema(-6.0, 3.0),
    200.0,
    65536,
)


def observation(seq: int, **changes: object) -> Observation:
    return replace(make_observation(seq=seq, time=30.0 + seq / 10), **changes)


def write(path: Path, conversation: list[tuple[Message, Message | None]]) -> None:
    """A stream file of requests and their replies (None: the request got no reply)."""
    writer = StreamWriter(path)
    for request, reply in conversation:
        writer.request(encode(request))
        if reply is not None:
            writer.reply(encode(reply))
    writer.close()


def recording(folder: Path, conversation: list[tuple[Message, Message | None]]) -> Path:
    folder.mkdir()
    write_manifest(folder, {"command": "test"})
    write(folder / stream_name(0), conversation)
    return folder


EPISODE = [
    (Hello(PROTOCOL_VERSION, "test"), WELCOME),
    (Reset("cf", 7), observation(0)),
    (Step(1, 0.5, 0), observation(1)),
    (Step(2, -1.25, 0), observation(2, terminated=True, reason="collision")),
    (Close(), Bye()),
]


def test_frames_are_read_back_exactly_as_written_in_order(tmp_path: Path) -> None:
    path = tmp_path / stream_name(0)
    write(path, EPISODE)
    records = list(read_records(path))
    assert path.read_bytes().startswith(MAGIC)
    assert [r.direction for r in records] == [REQUEST, REPLY] * len(EPISODE)
    expected = [encode(m) for pair in EPISODE for m in pair if m is not None]
    assert [r.frame for r in records] == expected


def test_a_writer_never_overwrites_a_stream(tmp_path: Path) -> None:
    path = tmp_path / stream_name(0)
    StreamWriter(path).close()
    with pytest.raises(FileExistsError):
        StreamWriter(path)


@pytest.mark.parametrize(
    ("cut", "message"),
    [(len(MAGIC) + 3, "truncated record header"), (-2, "truncated frame")],
)
def test_a_truncated_stream_is_refused_naming_the_file(
    tmp_path: Path, cut: int, message: str
) -> None:
    path = tmp_path / stream_name(0)
    write(path, EPISODE)
    path.write_bytes(path.read_bytes()[:cut])
    with pytest.raises(RecordingError, match=message) as caught:
        list(read_records(path))
    assert str(path) in str(caught.value)


@pytest.mark.parametrize("complete", [False, True])
def test_a_recording_cut_short_keeps_what_it_holds_unless_it_is_complete(
    tmp_path: Path, complete: bool
) -> None:
    folder = recording(tmp_path / "rec", EPISODE)
    write_manifest(folder, {"complete": complete})
    stream = folder / stream_name(0)
    stream.write_bytes(stream.read_bytes()[:-3])  # the writer was killed in the bye
    if complete:
        with pytest.raises(RecordingError, match="truncated frame"):
            load(folder)
    else:
        assert [len(e.steps) for e in load(folder).episodes] == [2]


def test_a_file_of_another_kind_is_not_a_stream(tmp_path: Path) -> None:
    path = tmp_path / stream_name(0)
    path.write_bytes(b"\x80" * 20)
    with pytest.raises(RecordingError, match="not a recording stream"):
        list(read_records(path))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "holds no recording"),
        ("{not json", "not JSON"),
        (json.dumps({"format": "other"}), "not a manifest"),
        (json.dumps({"format": "av-bridge-recording", "format_version": 99}), "version 99"),
    ],
)
def test_a_bad_manifest_is_refused(tmp_path: Path, content: str | None, message: str) -> None:
    if content is not None:
        (tmp_path / MANIFEST).write_text(content)
    with pytest.raises(RecordingError, match=message):
        read_manifest(tmp_path)


def test_a_missing_folder_is_named(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such folder"):
        load(tmp_path / "nope")


def test_a_recording_without_a_welcome_is_refused(tmp_path: Path) -> None:
    folder = recording(tmp_path / "rec", [(Reset("cf", 1), observation(0))])
    with pytest.raises(RecordingError, match="no recorded welcome"):
        load(folder)


def test_an_episode_keeps_its_reset_and_the_steps_applied(tmp_path: Path) -> None:
    loaded = load(recording(tmp_path / "rec", EPISODE))
    assert loaded.welcome == WELCOME
    assert loaded.manifest["command"] == "test"
    (episode,) = loaded.episodes
    assert episode.reset == Reset("cf", 7)
    assert [s.step.acceleration for s in episode.steps] == [0.5, -1.25]
    assert [o.seq for o in episode.observations] == [0, 1, 2]
    assert not episode.running


def test_retries_and_refusals_of_the_session_are_not_steps(tmp_path: Path) -> None:
    path = tmp_path / stream_name(0)
    write(
        path,
        [
            (Hello(PROTOCOL_VERSION), WELCOME),
            (Reset("cf", 1), observation(0)),
            (Step(1, 0.5), observation(1)),
            (Step(1, 0.5), observation(1)),  # a retry: the cached reply
            (Step(3, 0.5), Error("sequence_error", "expected 2")),
            (Step(2, 0.5, 2), Error("invalid_number", "lane_change 2")),
            (Step(2, 0.25), None),  # a timeout, then the retry answered
            (Step(2, 0.25), observation(2)),
            (Reset("nope", 1), Error("unknown_scenario", "no")),  # the episode goes on
            (Step(3, 0.0), observation(3, truncated=True, reason="time_limit")),
            (Step(4, 0.0), Error("out_of_order", "ended")),
        ],
    )
    (episode,) = read_stream(path).episodes
    assert [(s.step.seq, s.step.acceleration) for s in episode.steps] == [
        (1, 0.5),
        (2, 0.25),
        (3, 0.0),
    ]


def test_a_failed_reset_is_kept_with_its_error_and_ends_the_episode(tmp_path: Path) -> None:
    path = tmp_path / stream_name(0)
    write(
        path,
        [
            (Hello(PROTOCOL_VERSION), WELCOME),
            (Reset("cf", 1), observation(0)),
            (Reset("cf", 2), Error("insertion_failed", "the ego could not enter")),
            (Step(1, 0.5), Error("out_of_order", "no episode")),
            (Reset("cf", 3), observation(0)),
            (Hello(PROTOCOL_VERSION), WELCOME),  # a new hello ends the episode
            (Step(1, 0.5), Error("out_of_order", "after hello")),
        ],
    )
    first, failed, third = read_stream(path).episodes
    assert isinstance(failed.reply, Error) and failed.reply.code == "insertion_failed"
    assert [e.reset.seed for e in (first, failed, third)] == [1, 2, 3]
    assert not first.steps and not failed.steps and not third.steps
    assert third.running


def test_a_malformed_frame_is_kept_as_bytes() -> None:
    refusal = encode(Error("decode_error", "x"))
    paired = exchanges([Record(REQUEST, b"\xc1"), Record(REPLY, refusal)])
    assert paired[0].request is None and paired[0].request_frame == b"\xc1"
    assert isinstance(paired[0].reply, Error)
