"""The learner's end of the direct transport (`protocol.direct`): a plain TCP socket.

Same contract as the ZeroMQ `Connection`: one request in flight, a deadline on every receive,
a fresh connection after a lost reply (Lazy Pirate) under the same routing id, so a retried
step is answered from the server's cache. A closed connection raises `ServerLost` at once; a
frozen server is only seen through the deadline (there are no heartbeats on this transport).
"""

from __future__ import annotations

import os
import secrets
import select
import socket
import time

from agent_client.connection import Channel, MalformedReply, ServerLost, ServerTimeout
from protocol.direct import (
    DEFAULT_SPIN_US,
    FrameReader,
    FramingError,
    frame,
    preamble,
    spin_wait,
)
from protocol.transport import parse_endpoint

_RECEIVE_BYTES = 1 << 16


class DirectConnection(Channel):
    """A request/reply channel over ``direct://HOST:PORT``."""

    def __init__(self, address: str, timeout_s: float = 10.0, spin_us: float | None = None):
        endpoint = parse_endpoint(address)
        if endpoint.scheme != "direct":
            raise ValueError(f"{address}: DirectConnection takes direct://HOST:PORT")
        self.address = address
        self.timeout_s = timeout_s
        self.spin_us = DEFAULT_SPIN_US if spin_us is None else max(0.0, spin_us)
        self.routing_id = f"agent-client-{os.getpid()}-{secrets.token_hex(4)}".encode()
        self._host, self._port = endpoint.host, endpoint.port
        self._sock: socket.socket | None = None
        self._reader = FrameReader()
        self._pending: list[bytes] = []

    def send_raw(self, frame_bytes: bytes) -> None:
        sock = self._ensure_socket()
        try:
            sock.sendall(frame(frame_bytes))
        except OSError as exc:
            self.drop()
            raise ServerLost(f"connection to {self.address} lost while sending: {exc}") from exc

    def receive_frame(self, timeout_s: float | None = None) -> bytes:
        sock = self._sock
        if sock is None:
            raise RuntimeError("receive() without a request in flight")
        wait_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + wait_s
        fd = sock.fileno()

        def readable() -> bool:  # select, not a non-blocking recv: it takes no socket lock
            return bool(select.select((fd,), (), (), 0)[0])

        if not self._pending:
            spin_wait(readable, self.spin_us)
        while not self._pending:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select((fd,), (), (), remaining)[0]:
                self.drop()  # Lazy Pirate: the next request goes out on a fresh connection
                raise ServerTimeout(
                    f"no reply from {self.address} within {wait_s:.1f} s "
                    "(is sim-server running and reachable?)"
                )
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

    def _ensure_socket(self) -> socket.socket:
        if self._sock is None:
            try:
                sock = socket.create_connection((self._host, self._port), timeout=self.timeout_s)
            except OSError as exc:
                raise ServerTimeout(
                    f"cannot connect to {self.address}: {exc} (is sim-server running?)"
                ) from exc
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(self.timeout_s)
            try:
                sock.sendall(preamble(self.routing_id))
            except OSError as exc:
                sock.close()
                raise ServerLost(f"connection to {self.address} lost: {exc}") from exc
            self._sock, self._reader, self._pending = sock, FrameReader(), []
        return self._sock

    def drop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def close(self) -> None:
        self.drop()
