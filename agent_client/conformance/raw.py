"""The kit's raw sockets: they see exactly what a server sends, envelope and extra replies too.

The client's own channels hide both: a REQ socket discards a reply that lacks the request's id,
and a second reply to one request. A ZeroMQ DEALER socket and a plain ``direct://`` socket
(with this transport's preamble and framing) do not, so the `transport` check can say what is
wrong with a server's envelope instead of timing out. Every receive has a deadline.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass

import zmq

from agent_client.conformance.probe import NoReply
from agent_client.transport.zeromq import POLL_SLICE_MS
from protocol.transport.direct import FrameReader, FramingError, frame, preamble
from protocol.transport.endpoint import new_routing_id, parse_endpoint
from protocol.transport.security import ClientCredentials, secure_client_socket

REQUEST_ID = b"\x80\x00\x2a\x17"
"""The request-id frame the DEALER puts before the empty delimiter, as a correlated REQ does."""


@dataclass(frozen=True)
class RawReply:
    """What came back for one request: its frames (ZeroMQ: the whole envelope) and whether
    anything more arrived within the short wait after it."""

    frames: list[bytes]
    extra: int
    """Messages (ZeroMQ) or bytes (direct://) that arrived after the reply."""


class RawPeer:
    """One raw connection to the server under a fresh routing id."""

    def __init__(self, address: str, timeout_s: float) -> None:
        self.address = address
        self.timeout_s = timeout_s
        self.direct = parse_endpoint(address).scheme == "direct"
        self.routing_id = new_routing_id("agent-client-check-raw")
        self._context: zmq.Context[zmq.Socket[bytes]] | None = None
        self._socket: zmq.Socket[bytes] | None = None
        self._sock: socket.socket | None = None
        self._reader = FrameReader()

    def exchange(self, parts: list[bytes], settle_s: float) -> RawReply:
        """Send one request (ZeroMQ: `parts` after the envelope; direct: one frame) and return
        its reply; raises `NoReply` after the deadline."""
        if self.direct:
            return self._exchange_direct(parts[0], settle_s)
        return self._exchange_zmq(parts, settle_s)

    def _exchange_zmq(self, parts: list[bytes], settle_s: float) -> RawReply:
        if self._socket is None:
            self._context = zmq.Context()
            sock = self._context.socket(zmq.DEALER)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.ROUTING_ID, self.routing_id)
            credentials = ClientCredentials.from_environment()
            if credentials is not None:
                secure_client_socket(sock, credentials)
            sock.connect(str(parse_endpoint(self.address)))
            self._socket = sock
        sock = self._socket
        sock.send_multipart([REQUEST_ID, b"", *parts])
        if not _poll(sock, self.timeout_s):
            raise NoReply(f"no reply from {self.address} within {self.timeout_s:g} s")
        frames = sock.recv_multipart()
        extra = 0
        deadline = time.monotonic() + settle_s
        while (left := deadline - time.monotonic()) > 0 and _poll(sock, left):
            sock.recv_multipart()
            extra += 1
        return RawReply(frames, extra)

    def _exchange_direct(self, payload: bytes, settle_s: float) -> RawReply:
        deadline = time.monotonic() + self.timeout_s
        if self._sock is None:
            endpoint = parse_endpoint(self.address)
            try:
                self._sock = socket.create_connection(
                    (endpoint.host, endpoint.port), timeout=self.timeout_s
                )
                self._sock.sendall(preamble(self.routing_id))
            except OSError as exc:
                raise NoReply(f"cannot connect to {self.address}: {exc}") from exc
        sock = self._sock
        try:
            sock.sendall(frame(payload))
            frames = self._read(sock, deadline, want=1)
            if not frames:
                raise NoReply(f"no reply from {self.address} within {self.timeout_s:g} s")
            extra = sum(len(f) for f in frames[1:]) + self._drain(sock, settle_s)
        except OSError as exc:
            raise NoReply(f"connection to {self.address} lost: {exc}") from exc
        except FramingError as exc:
            raise NoReply(f"{self.address} broke the direct:// framing: {exc}") from exc
        return RawReply(frames[:1], extra)

    def _read(self, sock: socket.socket, deadline: float, want: int) -> list[bytes]:
        frames: list[bytes] = []
        for data in _chunks(sock, deadline):
            frames += self._reader.feed(data)
            if len(frames) >= want:
                break
        return frames

    def _drain(self, sock: socket.socket, settle_s: float) -> int:
        """Bytes that arrive within `settle_s` when nothing was asked."""
        return sum(len(data) for data in _chunks(sock, time.monotonic() + settle_s))

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
        if self._context is not None:
            self._context.term()
        if self._sock is not None:
            self._sock.close()


def _chunks(sock: socket.socket, deadline: float) -> Iterator[bytes]:
    """What arrives on `sock` until `deadline` or until the peer closes."""
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            data = sock.recv(1 << 16)
        except TimeoutError:
            return
        if not data:
            return
        yield data


def _poll(sock: zmq.Socket[bytes], timeout_s: float) -> bool:
    """Whether `sock` became readable within `timeout_s`, waiting at most `POLL_SLICE_MS` at a
    time so that a Ctrl-C the kernel handed to one of libzmq's threads is seen soon."""
    deadline = time.monotonic() + timeout_s
    while True:
        left_ms = int(max(0.0, deadline - time.monotonic()) * 1000) + 1
        if sock.poll(min(left_ms, POLL_SLICE_MS)):
            return True
        if time.monotonic() >= deadline:
            return False
