"""The learner's end of the direct transport (`protocol.transport.direct`): a plain TCP socket.

Same contract as the ZeroMQ `ZmqChannel`: one request in flight, a deadline on every receive,
a fresh connection after a lost reply (Lazy Pirate) under the same routing id, so a retried
step is answered from the server's cache. As with ZeroMQ, a server that is not up yet is waited
for until the request's deadline (connection attempts every `CONNECT_RETRY_S`). A closed
connection raises `ServerLost` at once; a frozen server is only seen through the deadline (there
are no heartbeats on this transport). The stream has no request ids, so bytes that arrive when no
request is in flight (a server that answered twice, or a reply nobody asked for) are refused as
`MalformedReply` before the next request goes out, never read as its answer.
"""

from __future__ import annotations

import select
import socket
import time

from agent_client.defaults import STEP_TIMEOUT_S
from agent_client.errors import MalformedReply, ServerLost, ServerTimeout
from agent_client.transport.channel import Channel
from protocol.transport.direct import (
    DEFAULT_SPIN_US,
    FrameReader,
    FramingError,
    frame,
    preamble,
    spin_wait,
)
from protocol.transport.endpoint import new_routing_id, parse_endpoint, require_loopback_for_direct

CONNECT_RETRY_S = 0.1
"""Pause between connection attempts to a server that is not (yet) listening."""
_RECEIVE_BYTES = 1 << 16


class DirectChannel(Channel):
    """A request/reply channel over ``direct://HOST:PORT`` (a loopback address)."""

    def __init__(
        self,
        address: str,
        timeout_s: float = STEP_TIMEOUT_S,
        spin_us: float | None = None,
        routing_id: bytes | None = None,
    ) -> None:
        endpoint = parse_endpoint(address)
        if endpoint.scheme != "direct":
            raise ValueError(f"{address}: DirectChannel takes direct://HOST:PORT")
        require_loopback_for_direct(endpoint)
        self.address = address
        self.timeout_s = timeout_s
        self.spin_us = DEFAULT_SPIN_US if spin_us is None else max(0.0, spin_us)
        self.routing_id = routing_id or new_routing_id()
        self._host, self._port = endpoint.host, endpoint.port
        self._sock: socket.socket | None = None
        self._poller: select.poll | None = None
        self._reader = FrameReader()
        self._pending: list[bytes] = []
        self._unsent: bytes | None = None
        """A request waiting for the server to accept a connection."""

    def send_raw(self, frame_bytes: bytes) -> None:
        self._pending = []
        self._refuse_unasked()
        if self._sock is None and not self._try_connect(self.timeout_s):
            self._unsent = frame_bytes  # sent once a connection comes up (receive waits for it)
            return
        self._send(frame_bytes)

    def _refuse_unasked(self) -> None:
        """Bytes waiting on an idle connection answer no request: drop it and say so.

        A connection the server closed meanwhile is left as it is: the request's send or
        receive then reports it (`ServerLost`, at once)."""
        poller = self._poller
        if poller is None or not poller.poll(0):
            return
        assert self._sock is not None
        try:
            data = self._sock.recv(_RECEIVE_BYTES, socket.MSG_PEEK)
        except OSError:
            return
        if data:
            self.drop()
            raise MalformedReply(
                f"{self.address} sent {len(data)} bytes while no request was in flight: one "
                "request gets exactly one reply (docs/protocol.md §1.2; did it answer twice?)"
            )

    def _send(self, frame_bytes: bytes) -> None:
        assert self._sock is not None
        try:
            self._sock.sendall(frame(frame_bytes))
        except OSError as exc:
            self.drop()
            raise ServerLost(f"connection to {self.address} lost while sending: {exc}") from exc

    def receive_frame(self, timeout_s: float | None = None) -> bytes:
        wait_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + wait_s
        if self._sock is None and self._unsent is None:
            raise RuntimeError("receive() without a request in flight")
        while self._sock is None:  # the server was not listening when the request was sent
            if time.monotonic() >= deadline:
                self._unsent = None
                raise ServerTimeout(
                    f"cannot connect to {self.address} within {wait_s:.1f} s "
                    "(is sim-server running?)"
                )
            time.sleep(min(CONNECT_RETRY_S, max(0.0, deadline - time.monotonic())))
            if self._try_connect(deadline - time.monotonic()):
                unsent, self._unsent = self._unsent, None
                assert unsent is not None
                self._send(unsent)
        sock, poller = self._sock, self._poller
        assert poller is not None

        def readable() -> bool:  # poll, not a non-blocking recv: it takes no socket lock
            return bool(poller.poll(0))

        if not self._pending:
            spin_wait(readable, self.spin_us)
        while not self._pending:
            remaining_ms = max(0.0, deadline - time.monotonic()) * 1000
            if not poller.poll(remaining_ms):
                self.drop()  # Lazy Pirate: the next request goes out on a fresh connection
                raise ServerTimeout(self.no_reply(wait_s))
            try:
                data = sock.recv(_RECEIVE_BYTES)
            except OSError as exc:
                self.drop()
                raise ServerLost(f"connection to {self.address} lost: {exc}") from exc
            if not data:
                self.drop()
                raise ServerLost(
                    f"connection to {self.address} closed while waiting for a reply "
                    "(the server died or restarted)"
                )
            try:
                self._pending += self._reader.feed(data)
            except FramingError as exc:
                self.drop()
                raise MalformedReply(f"invalid reply from {self.address}: {exc}") from exc
        if len(self._pending) > 1:
            self.drop()
            raise MalformedReply(f"{self.address} sent {len(self._pending)} replies to one request")
        return self._pending.pop()

    def _try_connect(self, timeout_s: float) -> bool:
        """Open a connection and send the preamble within `timeout_s`; False if nobody listens
        (yet)."""
        try:
            sock = socket.create_connection(
                (self._host, self._port), timeout=max(0.01, min(timeout_s, self.timeout_s))
            )
        except OSError:
            return False
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.sendall(preamble(self.routing_id))
        except OSError:
            sock.close()
            return False
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        self._sock, self._poller, self._reader, self._pending = sock, poller, FrameReader(), []
        return True

    def drop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock, self._poller = None, None
        self._unsent = None

    def close(self) -> None:
        self.drop()
