"""The one interface of a client transport: a request/reply channel with deadlines.

An implementation moves frames (`send_raw`, `receive_frame`); encoding, decoding and the
typed helpers are here, once, for every transport and for the conformance kit.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Protocol, Self

from agent_client.errors import InvalidReply, ServerError
from protocol.codec import decode_reply, encode
from protocol.errors import ProtocolError
from protocol.messages import Error, Hello, MultiStep, Reply, Request, Reset, Step, Welcome
from protocol.version import PROTOCOL_VERSION

CLIENT_NAME = "agent_client"


class FrameTap(Protocol):
    """Sees every frame a channel sends and receives, in order (a recording's stream,
    `protocol.recording.StreamWriter`)."""

    def request(self, frame: bytes) -> None: ...

    def reply(self, frame: bytes) -> None: ...


class Channel(ABC):
    """A request/reply channel to one server, with per-request deadlines (either transport).

    Subclasses move frames (`send_raw`, `receive_frame`); everything typed is here.
    """

    address: str
    timeout_s: float
    routing_id: bytes
    sent: Request | None = None
    """The request in flight, or the last one answered (None after `send_raw`): what a reply
    is checked against (`agent_client.transport.replies`)."""
    tap: FrameTap | None = None
    """What records this channel's frames (`agent_client.transport.recording`), or None: then
    recording costs one attribute test per frame."""
    answered = False
    """The server has answered on this channel: a reply that is late now comes from a server
    that is up and still working (`no_reply`), not from one that may be down."""

    @abstractmethod
    def send_raw(self, frame: bytes) -> None:
        """Send an already encoded frame (tests use it for malformed input)."""

    @abstractmethod
    def receive_frame(self, timeout_s: float | None = None) -> bytes:
        """The reply frame to what was sent, within the deadline; raises `ServerUnavailable`."""

    @abstractmethod
    def drop(self) -> None:
        """Forget the current connection (the next send opens a fresh one)."""

    @abstractmethod
    def close(self) -> None:
        """Close everything; never blocks."""

    def request(self, message: Request, timeout_s: float | None = None) -> Reply:
        """Send one request and return the reply; an `Error` reply raises `ServerError`."""
        self.send(message)
        return self.receive_checked(timeout_s)

    def exchange(self, message: Request, timeout_s: float | None = None) -> Reply:
        """Like `request`, but returns `Error` replies instead of raising."""
        return self.exchange_raw(encode(message), timeout_s)

    def exchange_raw(self, frame: bytes, timeout_s: float | None = None) -> Reply:
        """Send an already encoded frame and return the decoded reply."""
        self.sent = None
        self._send_frame(frame)
        return self.receive(timeout_s)

    def send(self, message: Request) -> None:
        """First half of `request`: send, so that several servers can work at once."""
        self.sent = message
        self._send_frame(encode(message))

    def _send_frame(self, frame: bytes) -> None:
        """`send_raw`, then show the frame to the tap (a frame that failed to go is not shown)."""
        self.send_raw(frame)
        if self.tap is not None:
            self.tap.request(frame)

    def receive(self, timeout_s: float | None = None) -> Reply:
        """Second half of `request`: the decoded reply to what `send` sent (the tap sees its
        frame before it is checked, so a malformed reply is recorded too)."""
        frame = self.receive_frame(timeout_s)
        self.answered = True
        if self.tap is not None:
            self.tap.reply(frame)
        try:
            return decode_reply(frame)  # type: ignore[return-value]
        except ProtocolError as exc:
            self.drop()
            rule = exc.message.removeprefix(f"{exc.field}: ") if exc.field else exc.message
            raise InvalidReply(
                exc.field or "frame", None, rule, f"invalid reply from {self.address}"
            ) from exc

    def receive_checked(self, timeout_s: float | None = None) -> Reply:
        """`receive`, raising `ServerError` for an `Error` reply (like `request`)."""
        reply = self.receive(timeout_s)
        if isinstance(reply, Error):
            raise ServerError(reply.code, reply.message)
        return reply

    def no_reply(self, wait_s: float) -> str:
        """Why a receive timed out: a server that has answered before is up and still working
        on the request (say what to raise); one that never has may be down or unreachable."""
        if not self.answered:
            return (
                f"no reply from {self.address} within {wait_s:.1f} s "
                "(is sim-server running and reachable?)"
            )
        sent = self.sent
        what = (
            "the reset"
            if isinstance(sent, Reset)
            else f"step {sent.seq}"
            if isinstance(sent, Step | MultiStep)
            else "the request"
        )
        deadline = "--reset-timeout" if isinstance(sent, Reset) else "--timeout"
        return (
            f"{self.address} is up (it has answered this session and its connection is alive) "
            f"but sent no reply to {what} within {wait_s:.1f} s: it may still be working on it "
            "(a large network, a long warm-up, an ego waiting to enter, the end of an episode); "
            f"give it longer: {deadline} SECONDS (RemoteEnv's reset_timeout_s / timeout_s)"
        )

    def hello(self, timeout_s: float | None = None, client: str = CLIENT_NAME) -> Welcome:
        """Handshake: announce our protocol version and receive the server's schemas."""
        reply = self.request(Hello(PROTOCOL_VERSION, client), timeout_s)
        if not isinstance(reply, Welcome):
            raise InvalidReply(
                "reply.type",
                reply.TYPE,
                "a hello is answered by welcome or error (§2.2)",
                f"invalid reply from {self.address}",
            )
        return reply

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
