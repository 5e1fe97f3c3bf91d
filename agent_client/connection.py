"""The learner's end of the wire: one request, one reply, always within a deadline.

Follows the ZeroMQ guide's Lazy Pirate client: a REQ socket with ``LINGER = 0``, a poll with a
timeout on every receive, and a fresh socket after a lost reply (a REQ socket that missed its
reply cannot send again).
"""

from __future__ import annotations

import time

import zmq

from protocol.codec import decode_reply, encode
from protocol.errors import ProtocolError
from protocol.messages import Error, Hello, Reply, Request, Welcome
from protocol.transport import connect_req, parse_endpoint
from protocol.version import PROTOCOL_VERSION

CLIENT_NAME = "agent_client"


class BridgeError(Exception):
    """Base class of the client's errors."""


class ServerTimeout(BridgeError):
    """The server did not answer within the deadline (dead, hung or unreachable)."""


class ServerError(BridgeError):
    """The server refused a request with an `Error` reply."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class MalformedReply(BridgeError):
    """The server sent something that is not a valid reply of this protocol."""


class Connection:
    """A request/reply channel to one server, with per-request timeouts."""

    def __init__(self, address: str, timeout_s: float = 10.0) -> None:
        parse_endpoint(address)  # fail early on a malformed address
        self.address = address
        self.timeout_s = timeout_s
        self._context = zmq.Context()
        self._socket: zmq.Socket[bytes] | None = None
        self._poller = zmq.Poller()

    def request(self, message: Request, timeout_s: float | None = None) -> Reply:
        """Send one request and return the reply; an `Error` reply raises `ServerError`."""
        reply = self.exchange(message, timeout_s)
        if isinstance(reply, Error):
            raise ServerError(reply.code, reply.message)
        return reply

    def exchange(self, message: Request, timeout_s: float | None = None) -> Reply:
        """Like `request`, but returns `Error` replies instead of raising."""
        return self.exchange_raw(encode(message), timeout_s)

    def exchange_raw(self, frame: bytes, timeout_s: float | None = None) -> Reply:
        """Send an already encoded frame (tests use it for malformed input)."""
        socket = self._ensure_socket()
        deadline = self.timeout_s if timeout_s is None else timeout_s
        socket.send(frame)
        if not self._poller.poll(int(deadline * 1000)):
            self._drop_socket()
            raise ServerTimeout(
                f"no reply from {self.address} within {deadline:.1f} s "
                "(is sim-server running and reachable?)"
            )
        frames = socket.recv_multipart()
        if len(frames) != 1:
            self._drop_socket()
            raise MalformedReply(f"reply from {self.address} has {len(frames)} frames, expected 1")
        try:
            return decode_reply(frames[0])  # type: ignore[return-value]
        except ProtocolError as exc:
            self._drop_socket()
            raise MalformedReply(f"invalid reply from {self.address}: {exc}") from exc

    def hello(self, timeout_s: float | None = None) -> Welcome:
        """Handshake: announce our protocol version and receive the server's schemas."""
        reply = self.request(Hello(PROTOCOL_VERSION, CLIENT_NAME), timeout_s)
        if not isinstance(reply, Welcome):
            raise MalformedReply(f"expected welcome, got {reply.TYPE}")
        return reply

    def _ensure_socket(self) -> zmq.Socket[bytes]:
        if self._socket is None:
            self._socket = connect_req(self._context, self.address)
            self._poller.register(self._socket, zmq.POLLIN)
        return self._socket

    def _drop_socket(self) -> None:
        if self._socket is not None:
            self._poller.unregister(self._socket)
            self._socket.close(linger=0)
            self._socket = None

    def close(self) -> None:
        """Close the socket and the context; never blocks."""
        self._drop_socket()
        self._context.term()

    def __enter__(self) -> Connection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_for_server(address: str, timeout_s: float = 30.0) -> Welcome:
    """Retry hello until the server answers (for scripts that just started one)."""
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        with Connection(address, timeout_s=max(0.1, min(1.0, remaining))) as connection:
            try:
                return connection.hello()
            except ServerTimeout:
                if time.monotonic() >= deadline:
                    raise
