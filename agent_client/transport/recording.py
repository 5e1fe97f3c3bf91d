"""`WireRecorder`: every frame a command's channels send and receive, kept as a recording.

The recorder taps channels (`Channel.tap`): each tapped channel, one session with a server,
writes its own stream file, frame for frame; ``manifest.json`` says what was recorded, and
once the recorder is closed, which episodes each stream holds. The format is
`protocol.recording`'s (docs/recording.md); ``sim-server --backend replay`` serves it back.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Self

from agent_client.errors import UsageError
from agent_client.transport.channel import Channel
from protocol.messages import Error, Observation
from protocol.recording import (
    RecordedEpisode,
    RecordingError,
    Stream,
    StreamWriter,
    read_stream,
    stream_name,
    write_manifest,
)
from protocol.version import PROTOCOL_VERSION, format_version


class WireRecorder:
    """Records the sessions of the channels it taps into `folder` (created if missing).

    `about` goes into the manifest as it is (JSON values): what the command recorded, e.g.
    its server, scenario, options and seeds.
    """

    def __init__(self, folder: Path, **about: Any) -> None:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UsageError(f"{folder}: cannot create the recording folder: {exc}") from exc
        self.folder = folder
        self.about = about
        self._created = datetime.now(UTC).isoformat(timespec="seconds")
        self._streams: list[tuple[StreamWriter, str]] = []
        self._closed = False
        self._write_manifest(finished=False)

    def tap(self, channel: Channel) -> None:
        """Record every frame of `channel` from now on, in a stream file of its own."""
        writer = StreamWriter(self.folder / stream_name(len(self._streams)))
        self._streams.append((writer, channel.address))
        channel.tap = writer
        self._write_manifest(finished=False)

    def close(self) -> None:
        """Flush the streams and complete the manifest with their episodes (once)."""
        if self._closed:
            return
        self._closed = True
        for writer, _ in self._streams:
            writer.close()
        self._write_manifest(finished=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _write_manifest(self, finished: bool) -> None:
        """The manifest; the streams' welcomes and episodes once they are `finished`."""
        streams: list[dict[str, Any]] = []
        episodes: list[dict[str, Any]] = []
        for writer, address in self._streams:
            entry: dict[str, Any] = {"file": writer.path.name, "server": address}
            if finished:
                stream = _read_back(writer)
                entry.update(_welcome_summary(stream))
                first = len(episodes)
                episodes += [_episode_summary(e, first + i) for i, e in enumerate(stream.episodes)]
            streams.append(entry)
        manifest: dict[str, Any] = {
            "protocol": format_version(PROTOCOL_VERSION),
            "created": self._created,
            **self.about,
            "complete": finished,
            "streams": streams,
        }
        if finished:
            manifest["episodes"] = episodes
        write_manifest(self.folder, manifest)


def _read_back(writer: StreamWriter) -> Stream:
    """The stream `writer` wrote, read as the server saw it."""
    try:
        return read_stream(writer.path)
    except RecordingError:  # written by us: only a full disk truncates it
        return Stream(writer.path.name, None, [])


def _welcome_summary(stream: Stream) -> dict[str, Any]:
    """Who answered the session: the welcome's server, backend and protocol version."""
    welcome = stream.welcome
    if welcome is None:
        return {"welcome": None}
    return {
        "welcome": {
            "server": welcome.server,
            "backend": welcome.backend,
            "backend_version": welcome.backend_version,
            "protocol": format_version(welcome.protocol),
        }
    }


def _episode_summary(episode: RecordedEpisode, index: int) -> dict[str, Any]:
    """One line of the manifest's episode index: what started it and how it ended."""
    return {
        "episode": index,
        "stream": episode.stream,
        "scenario": episode.reset.scenario,
        "seed": episode.reset.seed,
        "options": dict(episode.reset.options),
        "steps": len(episode.steps),
        "end": _end(episode),
    }


def _end(episode: RecordedEpisode) -> str:
    """The end reason, ``error: CODE`` for an error reply, or ``unfinished``."""
    last = episode.steps[-1].reply if episode.steps else episode.reply
    if isinstance(last, Error):
        return f"error: {last.code}"
    assert isinstance(last, Observation)
    return last.reason if last.terminated or last.truncated else "unfinished"
