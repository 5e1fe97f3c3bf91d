"""The learner's end of the wire: one request, one reply, always within a deadline.

Follows the ZeroMQ guide's Lazy Pirate client: a REQ socket with ``LINGER = 0`` and a poll with a
timeout on every receive. The socket is relaxed and correlated, so after a timeout the same
request may simply be sent again (the server answers a retried step from its cache, and the late
reply to the first attempt is dropped by ZeroMQ). A broken or untrustworthy connection gets a
fresh socket; every socket of one `Connection` carries the same routing id, so the server still
knows the client after such a reconnect.

While it waits, the connection also watches its socket's events: ZeroMQ's heartbeats close a
connection whose peer stopped answering, so a dead or frozen server raises `ServerLost` within
seconds even when a step may legitimately take much longer (`ServerTimeout`); a refused CURVE
handshake raises `AuthenticationFailed` at once.
"""

from __future__ import annotations

import os
import secrets
import time
from abc import ABC, abstractmethod
from typing import Self

import zmq
from zmq.utils.monitor import parse_monitor_message

from protocol.codec import decode_reply, encode
from protocol.errors import ProtocolError
from protocol.messages import Error, Hello, Reply, Request, Welcome
from protocol.security import ClientCredentials
from protocol.transport import HEARTBEAT_TIMEOUT_MS, connect_req, parse_endpoint
from protocol.version import PROTOCOL_VERSION

CLIENT_NAME = "agent_client"

_UP = zmq.EVENT_HANDSHAKE_SUCCEEDED
_LOST = zmq.EVENT_DISCONNECTED
_REFUSED = zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
"""A refused handshake: wrong keys, or CURVE on one side only."""
_FAILED = zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
"""A handshake that broke off: a CURVE server meeting a plain client, but also a connection cut
mid-handshake (a server being restarted): refused after `FAILED_HANDSHAKES_REFUSED` in a row."""
FAILED_HANDSHAKES_REFUSED = 3
"""ZeroMQ retries every 100 ms, so a refusal is reported within about half a second."""


class BridgeError(Exception):
    """Base class of the client's errors."""


class ServerUnavailable(BridgeError):
    """The server cannot be reached or stopped answering; a retry policy may reconnect."""


class ServerTimeout(ServerUnavailable):
    """The server did not answer within the deadline (dead, hung or unreachable)."""


class ServerLost(ServerUnavailable):
    """The connection broke while a request was in flight (the server died or froze)."""


class AuthenticationFailed(BridgeError):
    """The server refused the CURVE handshake (wrong keys, or keys where none are expected)."""


class ServerError(BridgeError):
    """The server refused a request with an `Error` reply."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class MalformedReply(BridgeError):
    """The server sent something that is not a valid reply of this protocol."""


class Channel(ABC):
    """A request/reply channel to one server, with per-request deadlines (either transport).

    Subclasses move frames (`send_raw`, `receive_frame`); everything typed is here.
    """

    address: str
    timeout_s: float
    routing_id: bytes

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
        self.send_raw(frame)
        return self.receive(timeout_s)

    def send(self, message: Request) -> None:
        """First half of `request`: send, so that several servers can work at once."""
        self.send_raw(encode(message))

    def receive(self, timeout_s: float | None = None) -> Reply:
        """Second half of `request`: the decoded reply to what `send` sent."""
        frame = self.receive_frame(timeout_s)
        try:
            return decode_reply(frame)  # type: ignore[return-value]
        except ProtocolError as exc:
            self.drop()
            raise MalformedReply(f"invalid reply from {self.address}: {exc}") from exc

    def receive_checked(self, timeout_s: float | None = None) -> Reply:
        """`receive`, raising `ServerError` for an `Error` reply (like `request`)."""
        reply = self.receive(timeout_s)
        if isinstance(reply, Error):
            raise ServerError(reply.code, reply.message)
        return reply

    def hello(self, timeout_s: float | None = None) -> Welcome:
        """Handshake: announce our protocol version and receive the server's schemas."""
        reply = self.request(Hello(PROTOCOL_VERSION, CLIENT_NAME), timeout_s)
        if not isinstance(reply, Welcome):
            raise MalformedReply(f"expected welcome, got {reply.TYPE}")
        return reply

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def connect(
    address: str,
    timeout_s: float = 10.0,
    credentials: ClientCredentials | None = None,
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
    spin_us: float | None = None,
) -> Channel:
    """A channel to `address`: ZeroMQ for ``tcp://`` and ``ipc://``, a plain socket for
    ``direct://`` (`spin_us`: how long to busy-wait for a reply; direct only)."""
    if parse_endpoint(address).scheme == "direct":
        from agent_client.direct_connection import DirectConnection

        if credentials is not None:
            raise ValueError("direct:// has no CURVE authentication: use tcp:// with keys")
        return DirectConnection(address, timeout_s, spin_us=spin_us)
    return Connection(address, timeout_s, credentials, heartbeat_timeout_s)


class Connection(Channel):
    """The ZeroMQ channel: a REQ socket (Lazy Pirate), heartbeats, CURVE when keys are given."""

    def __init__(
        self,
        address: str,
        timeout_s: float = 10.0,
        credentials: ClientCredentials | None = None,
        heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
    ) -> None:
        """`credentials` default to $AV_BRIDGE_SERVER_KEY / $AV_BRIDGE_SECRET_KEY when set; a
        server silent on the wire (no heartbeat answered) for `heartbeat_timeout_s` is lost."""
        parse_endpoint(address)  # fail early on a malformed address
        self.address = address
        self.timeout_s = timeout_s
        self.credentials = credentials or ClientCredentials.from_environment()
        self.heartbeat_timeout_ms = int(heartbeat_timeout_s * 1000)
        self.routing_id = f"agent-client-{os.getpid()}-{secrets.token_hex(4)}".encode()
        self._context = zmq.Context()
        self._socket: zmq.Socket[bytes] | None = None
        self._monitor: zmq.Socket[bytes] | None = None
        self._session_up = False
        """A handshake succeeded on the current connection (requests reach the server)."""
        self._failed_handshakes = 0

    def send_raw(self, frame: bytes) -> None:
        socket = self._ensure_socket()
        self._check_events(waiting=False)
        socket.send(frame)

    def receive_frame(self, timeout_s: float | None = None) -> bytes:
        socket = self._socket
        if socket is None:
            raise RuntimeError("receive() without a request in flight")
        wait_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + wait_s
        monitor = self._monitor
        assert monitor is not None
        watched: list[tuple[zmq.Socket[bytes], int]] = [(socket, zmq.POLLIN), (monitor, zmq.POLLIN)]
        while True:
            remaining_ms = int(max(0.0, deadline - time.monotonic()) * 1000)
            ready = {s for s, _ in zmq.zmq_poll(watched, remaining_ms)}
            if socket in ready:
                break
            if monitor in ready:
                self._check_events(waiting=True)
                continue
            raise ServerTimeout(
                f"no reply from {self.address} within {wait_s:.1f} s "
                "(is sim-server running and reachable?)"
            )
        frames = socket.recv_multipart()
        if len(frames) != 1:
            self._drop_socket()
            raise MalformedReply(f"reply from {self.address} has {len(frames)} frames, expected 1")
        return frames[0]

    def drop(self) -> None:
        self._drop_socket()

    def _check_events(self, waiting: bool) -> None:
        """Read the socket's pending events; raise if the connection broke or was refused.

        While `waiting` for a reply any disconnection lost the request; between requests only a
        connection that is still down counts (ZeroMQ reconnects by itself).
        """
        assert self._monitor is not None
        refused = lost = False
        while self._monitor.poll(0):
            event = parse_monitor_message(self._monitor.recv_multipart())["event"]
            if event & _UP:
                self._session_up, self._failed_handshakes = True, 0
                lost = waiting and lost
            if event & _LOST and self._session_up:  # before a handshake no request was sent
                self._session_up = False
                lost = True
            if event & _FAILED:
                self._failed_handshakes += 1
            refused = (
                refused
                or bool(event & _REFUSED)
                or self._failed_handshakes >= FAILED_HANDSHAKES_REFUSED
            )
        if refused:
            self._drop_socket()
            raise AuthenticationFailed(
                f"{self.address} refused the CURVE handshake: check --server-key and "
                "--secret-key (and that the server authorises this client's public key)"
            )
        if lost:
            self._drop_socket()
            raise ServerLost(
                f"connection to {self.address} lost "
                + ("while waiting for a reply " if waiting else "")
                + "(the server died, froze or restarted)"
            )

    def _ensure_socket(self) -> zmq.Socket[bytes]:
        if self._socket is None:
            self._socket = connect_req(
                self._context,
                self.address,
                self.routing_id,
                self.credentials,
                self.heartbeat_timeout_ms,
            )
            self._monitor = self._socket.get_monitor_socket(_UP | _LOST | _REFUSED | _FAILED)
            self._session_up, self._failed_handshakes = False, 0
        return self._socket

    def _drop_socket(self) -> None:
        if self._socket is not None:
            self._socket.disable_monitor()
            self._socket.close(linger=0)
            self._socket = None
        if self._monitor is not None:
            self._monitor.close(linger=0)
            self._monitor = None

    def close(self) -> None:
        """Close the socket and the context; never blocks."""
        self._drop_socket()
        self._context.term()


def wait_for_server(address: str, timeout_s: float = 30.0) -> Welcome:
    """Retry hello until the server answers (for scripts that just started one)."""
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        with connect(address, timeout_s=max(0.1, min(1.0, remaining))) as connection:
            try:
                return connection.hello()
            except ServerUnavailable:
                if time.monotonic() >= deadline:
                    raise
