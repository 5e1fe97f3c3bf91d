"""The protocol's state machine: hello, reset, step..., close, in front of one backend.

`Session.handle` turns one request frame into one reply frame and never raises: every fault of
the client becomes an `Error` reply and the server goes on serving. The serving loops
(`sim_server.serve`) move frames between a transport and the session.
"""

from __future__ import annotations

import logging
import secrets
import time
from dataclasses import dataclass, replace

from protocol.codec import DEFAULT_MAX_FRAME_BYTES, decode_request, encode
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import (
    Bye,
    Close,
    Error,
    Hello,
    Message,
    MultiObservation,
    MultiStep,
    OptionValue,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.schema import OBSERVATION_FIELDS, fields_for
from protocol.version import (
    PROTOCOL_VERSION,
    ROAD_VERSION,
    SIGNAL_VERSION,
    STOP_LINE_VERSION,
    format_version,
    is_compatible,
)
from sim_server import __version__
from sim_server.backends.base import Backend
from sim_server.backends.options import merge_options
from sim_server.errors import BackendError

log = logging.getLogger("sim_server")

_BEFORE_ROAD = (ROAD_VERSION[0], ROAD_VERSION[1] - 1)
"""The last version whose flat vector has no road fields."""
_BEFORE_STOP_LINE = (STOP_LINE_VERSION[0], STOP_LINE_VERSION[1] - 1)
"""The last version whose flat vector has no stop line."""
_BEFORE_SIGNAL = (SIGNAL_VERSION[0], SIGNAL_VERSION[1] - 1)
"""The last version whose flat vector has no traffic light."""

DEFAULT_SESSION_TIMEOUT_S = 600.0
"""Silence after which another client may take over a client that is still connected."""


@dataclass
class _Episode:
    """Sequence state of the running (or just finished) episode."""

    last_seq: int
    last_reply: bytes
    running: bool
    egos: tuple[str, ...] | None = None
    """A multi-ego episode (a reset that named ``egos``): the ids of the egos still driving,
    which the next `MultiStep` must command exactly; None for a one-ego episode."""


class Session:
    """Protocol state machine in front of a backend: hello, reset, step..., close."""

    def __init__(
        self,
        backend: Backend,
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        session_timeout_s: float = DEFAULT_SESSION_TIMEOUT_S,
    ) -> None:
        self.backend = backend
        self.max_frame_bytes = max_frame_bytes
        self.session_timeout_s = session_timeout_s
        self._scenarios: dict[str, ScenarioInfo] = {s.name: s for s in backend.scenarios()}
        ours = Welcome(
            protocol=PROTOCOL_VERSION,
            server=f"sim_server {__version__}",
            backend=backend.name,
            backend_version=backend.version,
            scenarios=tuple(self._scenarios.values()),
            observation_fields=OBSERVATION_FIELDS,
            action=backend.action_schema,
            sensor_range=backend.sensor_range,
            max_frame_bytes=max_frame_bytes,
        )
        welcome = backend.welcome(ours)
        self._welcome = encode(welcome)
        # A client refuses a flat-vector field it does not know: one older than 1.8 is
        # announced the fields of its version (the named observation it reads either way).
        self._welcome_before_signal, self._welcome_before_stop_line, self._welcome_before_road = (
            encode(replace(welcome, observation_fields=fields_for(version)))
            if welcome is ours
            else self._welcome
            for version in (_BEFORE_SIGNAL, _BEFORE_STOP_LINE, _BEFORE_ROAD)
        )
        self.owner: bytes | None = None
        self.owner_connected = False
        self._last_seen = 0.0
        self._episode: _Episode | None = None

    # ----------------------------------------------------------------------- dispatch

    def handle(self, peer: bytes, frame: bytes, now: float | None = None) -> bytes:
        """Answer one request frame from `peer` with one reply frame."""
        now = time.monotonic() if now is None else now
        try:
            request = decode_request(frame, self.max_frame_bytes)
            self._check_owner(peer, request, now)
            reply = self._dispatch(peer, request)
            self._last_seen = now
            if peer == self.owner:
                self.owner_connected = True
            return reply
        except ProtocolError as exc:
            return encode(Error(exc.code.value, exc.message))
        except BackendError as exc:
            return encode(Error(exc.code.value, exc.message))
        except Exception:  # a backend bug must not take the server down
            log.exception("unexpected failure while handling a request")
            if self._episode is not None:
                self._episode.running = False
            return encode(
                Error(
                    ErrorCode.SIMULATOR_ERROR.value, "internal simulator error; see the server log"
                )
            )

    def owner_disconnected(self) -> None:
        """The owner's connection is gone: another client's hello may take over at once.

        The episode stays: the same client may come back on a fresh socket (its routing id is
        kept) and retry its last step.
        """
        if self.owner is not None and self.owner_connected:
            log.info("client disconnected; the simulator is free for the next client")
        self.owner_connected = False

    def _check_owner(self, peer: bytes, request: Message, now: float) -> None:
        if self.owner is None or peer == self.owner:
            return
        if isinstance(request, Hello):
            if not self.owner_connected:
                log.info("a new client takes over from a disconnected one")
                self._end_session()
                return
            if now - self._last_seen > self.session_timeout_s:
                log.info("session of an idle client expired; a new client takes over")
                self._end_session()
                return
        raise ProtocolError(
            ErrorCode.BUSY,
            "another client holds this simulator; start another server, serve several clients "
            "on one address (sim-server --pool N) or retry later",
        )

    def _dispatch(self, peer: bytes, request: Message) -> bytes:
        if isinstance(request, Hello):
            return self._hello(peer, request)
        if self.owner is None:
            raise ProtocolError(
                ErrorCode.OUT_OF_ORDER, f"{request.TYPE} before hello: say hello first"
            )
        if isinstance(request, Step):
            return self._step(request)
        if isinstance(request, MultiStep):
            return self._multi_step(request)
        if isinstance(request, Reset):
            return self._reset(request)
        if isinstance(request, Close):
            self._end_session()
            return encode(Bye())
        raise ProtocolError(ErrorCode.UNKNOWN_TYPE, f"{request.TYPE} is not a request")

    def _hello(self, peer: bytes, hello: Hello) -> bytes:
        if not is_compatible(PROTOCOL_VERSION, hello.protocol):
            raise ProtocolError(
                ErrorCode.VERSION_MISMATCH,
                f"client speaks protocol {format_version(hello.protocol)}, server speaks "
                f"{format_version(PROTOCOL_VERSION)}: major versions must match",
            )
        if self.owner != peer:
            log.info("hello from %s", _printable(hello.client) or "an unnamed client")
        self.owner = peer
        self._episode = None
        if hello.protocol >= SIGNAL_VERSION:
            return self._welcome
        if hello.protocol >= STOP_LINE_VERSION:
            return self._welcome_before_signal
        if hello.protocol >= ROAD_VERSION:
            return self._welcome_before_stop_line
        return self._welcome_before_road

    def _reset(self, reset: Reset) -> bytes:
        info = self._scenarios.get(reset.scenario)
        if info is None:
            raise ProtocolError(
                ErrorCode.UNKNOWN_SCENARIO,
                f"unknown scenario {reset.scenario[:64]!r}; offered: {', '.join(self._scenarios)}",
            )
        options = merge_options(info, reset.options)
        seed = reset.seed if reset.seed is not None else secrets.randbelow(2**31)
        if not 0 <= seed < 2**31:
            raise ProtocolError(ErrorCode.INVALID_NUMBER, f"seed {seed} is outside 0..2^31-1")
        egos = _egos(options, reset.options) if reset.many_egos else 0
        self._episode = None
        if egos:
            many = self.backend.reset_many(reset.scenario, seed, options, egos)
            reply = encode(many)
            self._episode = _Episode(0, reply, not _ended(many), _running(many))
            return reply
        obs = self.backend.reset(reset.scenario, seed, options)
        reply = encode(obs)
        self._episode = _Episode(last_seq=0, last_reply=reply, running=True)
        return reply

    def _ordered(self, request: Step | MultiStep) -> _Episode | bytes:
        """The running episode a step may advance, or the cached reply of a retried step."""
        episode = self._episode
        if episode is None:
            raise ProtocolError(
                ErrorCode.OUT_OF_ORDER, f"{request.TYPE} before reset: send reset first"
            )
        if request.seq == episode.last_seq and request.seq > 0:
            return episode.last_reply  # a retried step: answer again, do not advance
        if not episode.running:
            raise ProtocolError(ErrorCode.OUT_OF_ORDER, "the episode has ended: send reset")
        if request.seq != episode.last_seq + 1:
            raise ProtocolError(
                ErrorCode.SEQUENCE_ERROR,
                f"{request.TYPE} seq {request.seq}: expected {episode.last_seq + 1} (or "
                f"{episode.last_seq} to repeat the last step)",
            )
        many = episode.egos is not None
        if many != isinstance(request, MultiStep):
            wanted, why = ("multi_step", "its reset named egos") if many else ("step", "one ego")
            raise ProtocolError(
                ErrorCode.OUT_OF_ORDER, f"{request.TYPE} in an episode of {why}: send {wanted}"
            )
        return episode

    def _step(self, step: Step) -> bytes:
        episode = self._ordered(step)
        if isinstance(episode, bytes):
            return episode
        _check_lane_change(step.lane_change, "lane_change")
        try:
            obs = self.backend.step(step.seq, step.acceleration, step.lane_change)
        except BackendError:
            episode.running = False
            raise
        reply = encode(obs)
        episode.last_seq, episode.last_reply = step.seq, reply
        episode.running = not (obs.terminated or obs.truncated)
        return reply

    def _multi_step(self, step: MultiStep) -> bytes:
        episode = self._ordered(step)
        if isinstance(episode, bytes):
            return episode
        assert episode.egos is not None
        commands = _commands(step, episode.egos)
        try:
            many = self.backend.step_many(step.seq, commands)
        except BackendError:
            episode.running = False
            raise
        reply = encode(many)
        episode.last_seq, episode.last_reply = step.seq, reply
        episode.running = not _ended(many)
        episode.egos = _running(many)
        return reply

    def _end_session(self) -> None:
        self.owner = None
        self.owner_connected = False
        self._episode = None


def _check_lane_change(value: int, name: str) -> None:
    if value not in (-1, 0, 1):
        raise ProtocolError(ErrorCode.INVALID_NUMBER, f"{name} {value} is not -1, 0 or 1")


def _egos(options: dict[str, OptionValue], named: dict[str, OptionValue]) -> int:
    """The number of egos a multi-ego reset asks for (`options` merged, `named` the reset's
    own): one that names ``ego_share`` leaves it to the share, and 1 is passed on."""
    egos = options.get("egos", 1)
    assert isinstance(egos, int)  # merge_options checked its type against the default
    if egos < 1:
        raise ProtocolError(ErrorCode.INVALID_OPTION, f"option egos must be >= 1, got {egos}")
    if "ego_share" in named:
        value = options["ego_share"]
        assert isinstance(value, float)
        if "egos" in named:
            raise ProtocolError(
                ErrorCode.INVALID_OPTION,
                "name egos (a number of egos) or ego_share (a share of the traffic), not both",
            )
        if not 0.0 < value <= 1.0:
            raise ProtocolError(
                ErrorCode.INVALID_OPTION,
                f"option ego_share must be within (0, 1], got {value:g} (for all-human "
                "traffic, let the simulator drive one ego: ego_driver)",
            )
    return egos


def _running(many: MultiObservation) -> tuple[str, ...]:
    """The egos a next `MultiStep` must command: those that have not ended."""
    return tuple(e.id for e in many.egos if not (e.terminated or e.truncated))


def _ended(many: MultiObservation) -> bool:
    return many.terminated or many.truncated or not _running(many)


def _commands(step: MultiStep, running: tuple[str, ...]) -> dict[str, tuple[float, int]]:
    """The commands by ego id: exactly one for every running ego, each lane change valid."""
    commands: dict[str, tuple[float, int]] = {}
    for i, command in enumerate(step.commands):
        if command.id in commands:
            raise ProtocolError(
                ErrorCode.INVALID_MESSAGE, f"commands[{i}]: a second command for {command.id!r}"
            )
        _check_lane_change(command.lane_change, f"commands[{i}].lane_change")
        commands[command.id] = (command.acceleration, command.lane_change)
    unknown = [ego for ego in commands if ego not in running]
    missing = [ego for ego in running if ego not in commands]
    if unknown or missing:
        words = [f"no running ego {', '.join(map(repr, unknown))}"] if unknown else []
        words += [f"no command for {', '.join(map(repr, missing))}"] if missing else []
        raise ProtocolError(
            ErrorCode.INVALID_MESSAGE,
            f"multi_step {step.seq}: {'; '.join(words)} (running: {', '.join(running)})",
        )
    return commands


def _printable(text: str, limit: int = 64) -> str:
    """A client-chosen name made safe for one log line."""
    cleaned = "".join(c if c.isprintable() else "?" for c in text[:limit])
    return cleaned + ("..." if len(text) > limit else "")
