"""The recording format: a client's wire stream kept on disk, frame for frame (docs/recording.md).

A recording is a folder: ``manifest.json`` (what was recorded, by which client, from which
server) and one stream file per session, ``session-NNN.avbr``: the 8 bytes `MAGIC`, then one
record per frame, in the order the client sent and received them: a direction byte (`REQUEST`
or `REPLY`), a 4-byte little-endian length and the frame exactly as it went over the wire.
Nothing is pickled: frames are read back with the codec's own checks.

Both sides read recordings through this module: the replay backend
(`sim_server.backends.replay`) serves one back, the learner exports one to a table. `episodes`
reads a stream as the server's state machine did (docs/protocol.md §3), so each side sees the
same episodes.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from protocol.codec import decode_reply, decode_request
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import Bye, Close, Error, Hello, Message, Observation, Reset, Step, Welcome

FORMAT = "av-bridge-recording"
"""The manifest's ``format``."""
FORMAT_VERSION = 1
"""The manifest's ``format_version``; a reader refuses any other."""
MAGIC = b"AVBREC\x00\x01"
"""The first 8 bytes of every stream file: the format's name and version."""
MANIFEST = "manifest.json"
STREAM_PATTERN = "session-*.avbr"
REQUEST = 0x3E
"""Direction byte ``>`` of a frame the client sent."""
REPLY = 0x3C
"""Direction byte ``<`` of a frame the client received."""
MAX_RECORD_BYTES = 16 * 1024 * 1024
"""The largest frame a record may hold (the ZeroMQ socket's own cap)."""

_HEAD = struct.Struct("<BI")
_SESSION_CODES = frozenset(
    {
        ErrorCode.DECODE_ERROR,
        ErrorCode.FRAME_TOO_LARGE,
        ErrorCode.INVALID_MESSAGE,
        ErrorCode.UNKNOWN_TYPE,
        ErrorCode.OUT_OF_ORDER,
        ErrorCode.VERSION_MISMATCH,
        ErrorCode.SEQUENCE_ERROR,
        ErrorCode.BUSY,
    }
)
"""Error codes a session answers before the simulator sees a step: such a step changed nothing."""
_REFUSED_RESETS = _SESSION_CODES | {ErrorCode.UNKNOWN_SCENARIO, ErrorCode.INVALID_NUMBER}
"""Error codes of a reset the session refuses itself: the running episode goes on (§7.4).
``invalid_option`` may come from either: its reset is kept, and the episode goes on (a step
after a simulator's refusal was answered ``out_of_order`` and does not count)."""


class RecordingError(ValueError):
    """A recording that cannot be read: the message names the file and what is wrong."""


def stream_name(index: int) -> str:
    """The file name of a recording's stream number `index` (from 0)."""
    return f"session-{index:03d}.avbr"


# --------------------------------------------------------------------------- writing


class StreamWriter:
    """Appends the frames of one session to a new stream file (buffered; `close` flushes)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: BinaryIO = path.open("xb")  # never overwrite another session
        self._file.write(MAGIC)

    def request(self, frame: bytes) -> None:
        """Record a frame the client sent."""
        self._write(REQUEST, frame)

    def reply(self, frame: bytes) -> None:
        """Record a frame the client received."""
        self._write(REPLY, frame)

    def _write(self, direction: int, frame: bytes) -> None:
        if not self._file.closed:
            self._file.write(_HEAD.pack(direction, len(frame)))
            self._file.write(frame)

    def close(self) -> None:
        """Flush and close the file (further frames are dropped)."""
        self._file.close()


def write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    """Write ``manifest.json`` (the format's name and version first), replacing it atomically."""
    content = {"format": FORMAT, "format_version": FORMAT_VERSION, **manifest}
    temporary = folder / (MANIFEST + ".tmp")
    temporary.write_text(json.dumps(content, indent=2) + "\n")
    temporary.replace(folder / MANIFEST)


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True, slots=True)
class Record:
    """One frame as it went over the wire: `direction` is `REQUEST` or `REPLY`."""

    direction: int
    frame: bytes


def read_records(path: Path, cut_short: bool = False) -> Iterator[Record]:
    """The records of one stream file, in order; `RecordingError` if it is not one.

    `cut_short`: the writer may have been killed, so a truncated last record is dropped instead
    of refused (a recording whose manifest is not ``complete``)."""
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise RecordingError(f"{path}: not a recording stream (it does not start with {MAGIC!r})")
    offset = len(MAGIC)
    while offset < len(data):
        start = offset + _HEAD.size
        if start > len(data):
            if cut_short:
                return
            raise RecordingError(f"{path}: truncated record header at byte {offset}")
        direction, length = _HEAD.unpack_from(data, offset)
        if direction not in (REQUEST, REPLY) or length > MAX_RECORD_BYTES:
            raise RecordingError(f"{path}: corrupt record at byte {offset}")
        if start + length > len(data):
            if cut_short:
                return
            raise RecordingError(f"{path}: truncated frame at byte {start}")
        yield Record(direction, data[start : start + length])
        offset = start + length


@dataclass(frozen=True, slots=True)
class Exchange:
    """A request and the reply that answered it (None: no reply was recorded, e.g. a timeout).

    A frame the codec refuses is kept as None beside its bytes."""

    request: Message | None
    request_frame: bytes
    reply: Message | None = None
    reply_frame: bytes = b""


def exchanges(records: Iterator[Record] | list[Record]) -> list[Exchange]:
    """Pair each request with the reply recorded after it (a reply answers the last request)."""
    paired: list[Exchange] = []
    for record in records:
        if record.direction == REQUEST:
            paired.append(Exchange(_decoded(decode_request, record.frame), record.frame))
        elif paired and not paired[-1].reply_frame:
            last = paired[-1]
            reply = _decoded(decode_reply, record.frame)
            paired[-1] = Exchange(last.request, last.request_frame, reply, record.frame)
    return paired


def _decoded(decode: Callable[[bytes, int], Message], frame: bytes) -> Message | None:
    """The message of a recorded frame, or None if the codec refuses it."""
    try:
        return decode(frame, MAX_RECORD_BYTES)
    except ProtocolError:
        return None


@dataclass(frozen=True, slots=True)
class RecordedStep:
    """A step the simulator applied, and its reply (an observation, or the error that ended the
    episode)."""

    step: Step
    reply: Observation | Error


@dataclass(slots=True)
class RecordedEpisode:
    """A reset the simulator saw, its reply and the steps it applied, in order."""

    stream: str
    reset: Reset
    reply: Observation | Error
    steps: list[RecordedStep] = field(default_factory=list)

    @property
    def observations(self) -> list[Observation]:
        """The observations of the episode: seq 0, then one per applied step."""
        replies = [self.reply, *(s.reply for s in self.steps)]
        return [reply for reply in replies if isinstance(reply, Observation)]

    @property
    def running(self) -> bool:
        """True if the recorded episode did not end (its last reply is a running observation)."""
        last = self.steps[-1].reply if self.steps else self.reply
        return isinstance(last, Observation) and not (last.terminated or last.truncated)


@dataclass(frozen=True, slots=True)
class Stream:
    """One session of a recording: its welcome (None if none was recorded) and its episodes."""

    name: str
    welcome: Welcome | None
    episodes: list[RecordedEpisode]


def read_stream(path: Path, cut_short: bool = False) -> Stream:
    """Read one stream file as the server's state machine saw it (see `episodes`; `cut_short`
    as for `read_records`)."""
    paired = exchanges(list(read_records(path, cut_short)))
    return Stream(path.name, _first_welcome(paired), episodes(paired, path.name))


def _first_welcome(paired: list[Exchange]) -> Welcome | None:
    """The welcome that answered the session's first successful hello."""
    for exchange in paired:
        if isinstance(exchange.request, Hello) and isinstance(exchange.reply, Welcome):
            return exchange.reply
    return None


def episodes(paired: list[Exchange], stream: str = "") -> list[RecordedEpisode]:
    """The episodes of a session: every reset with a reply, and the steps the simulator applied.

    A reset counts unless the session refused it itself (then the running episode goes on). A
    step counts if it is the episode's next one (seq last+1 while it runs, a valid lane change)
    and got an observation of its seq or an error a session does not give itself; a retried
    step, a refused one and everything after a hello or a close do not.
    """
    found: list[RecordedEpisode] = []
    current: RecordedEpisode | None = None
    for exchange in paired:
        request, reply = exchange.request, exchange.reply
        if _ends_session(request, reply):
            current = None
        elif isinstance(request, Reset) and isinstance(reply, Observation | Error):
            if isinstance(reply, Error) and reply.code in _REFUSED_RESETS:
                continue  # refused by the session: the simulator never saw it
            entry = RecordedEpisode(stream, request, reply)
            found.append(entry)
            if isinstance(reply, Observation):
                current = entry
            elif reply.code != ErrorCode.INVALID_OPTION:  # the session's or the simulator's
                current = None
        elif (
            isinstance(request, Step) and current is not None and _applied(current, request, reply)
        ):
            assert isinstance(reply, Observation | Error)
            current.steps.append(RecordedStep(request, reply))
    return found


def _ends_session(request: Message | None, reply: Message | None) -> bool:
    """A hello answered with a welcome, or a close answered with bye: no episode goes on."""
    return (isinstance(request, Hello) and isinstance(reply, Welcome)) or (
        isinstance(request, Close) and isinstance(reply, Bye)
    )


def _applied(episode: RecordedEpisode, step: Step, reply: Message | None) -> bool:
    """Whether the simulator applied `step` (the session passed it on) in `episode`."""
    if not episode.running or step.seq != len(episode.steps) + 1:
        return False
    if step.lane_change not in (-1, 0, 1):
        return False
    if isinstance(reply, Observation):
        return reply.seq == step.seq
    return isinstance(reply, Error) and reply.code not in _SESSION_CODES


# --------------------------------------------------------------------------- a whole folder


@dataclass(frozen=True, slots=True)
class Recording:
    """A recording folder read back: its manifest, its streams and all their episodes."""

    folder: Path
    manifest: dict[str, Any]
    streams: list[Stream]

    @property
    def welcome(self) -> Welcome:
        """The first recorded welcome (`load` checked there is one)."""
        return next(s.welcome for s in self.streams if s.welcome is not None)

    @property
    def episodes(self) -> list[RecordedEpisode]:
        """Every episode of every stream, in recording order."""
        return [episode for stream in self.streams for episode in stream.episodes]


def stream_paths(folder: Path) -> list[Path]:
    """The stream files of a recording folder, in order."""
    return sorted(folder.glob(STREAM_PATTERN))


def read_manifest(folder: Path) -> dict[str, Any]:
    """The manifest of `folder`; `RecordingError` if it is missing, not JSON or of another
    format or version."""
    path = folder / MANIFEST
    if not folder.is_dir():
        raise RecordingError(f"{folder}: no such folder")
    if not path.is_file():
        raise RecordingError(f"{folder}: holds no recording (no {MANIFEST})")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: not JSON: {exc}") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise RecordingError(f"{path}: not a manifest of an {FORMAT}")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise RecordingError(
            f"{path}: format version {manifest.get('format_version')!r}, this reader takes "
            f"{FORMAT_VERSION}"
        )
    return manifest


def load(folder: Path) -> Recording:
    """Read a whole recording folder; `RecordingError` if it holds no readable recording with a
    welcome. A recording whose manifest is not ``complete`` may end in a truncated record."""
    manifest = read_manifest(folder)
    cut_short = manifest.get("complete") is not True  # its writer may have been killed
    streams = [read_stream(path, cut_short) for path in stream_paths(folder)]
    if not any(stream.welcome is not None for stream in streams):
        raise RecordingError(f"{folder}: no recorded welcome in its {STREAM_PATTERN} files")
    return Recording(folder, manifest, streams)
