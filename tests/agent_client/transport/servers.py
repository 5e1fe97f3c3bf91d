"""Misbehaving servers for the client's transports, in a thread, on a free loopback port.

ZeroMQ: the toy servers of the conformance tests (our real serving loop with one rule broken).
direct://: `DirectToy`, a plain-socket server in front of our `Session` (fake backend) whose
`behaviour` breaks the transport: answers twice, late, with another request's reply, never, with
half a frame, or announcing a frame far over the cap.
"""

from __future__ import annotations

import socket
import threading
import time

from protocol.codec import decode_request
from protocol.errors import ProtocolError
from protocol.messages import Reset, Step
from protocol.transport.direct import LENGTH, FrameReader, frame
from sim_server.backends.fake import FakeBackend
from sim_server.session import Session

LATE_S = 1.0
"""How late `late` answers step 3."""


class DirectToy:
    """A direct:// server with one `behaviour`: "twice" (the second reply 50 ms later),
    "twice_at_once", "late", "another_seq", "silent", "partial", "huge" (or "" for a correct
    one)."""

    def __init__(self, behaviour: str = "") -> None:
        self.behaviour = behaviour
        self.session = Session(FakeBackend())
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.05)
        self.address = f"direct://127.0.0.1:{self._listener.getsockname()[1]}"
        self.received = threading.Event()
        """Set once a request arrived (a test's readiness signal)."""
        self._stop = threading.Event()
        self._previous: bytes | None = None
        self._threads: list[threading.Thread] = []
        self._accepting = threading.Thread(target=self._accept, daemon=True)

    def __enter__(self) -> DirectToy:
        self._accepting.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._accepting.join(timeout=5)
        for thread in self._threads:
            thread.join(timeout=5)
        self._listener.close()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            thread = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            self._threads.append(thread)
            thread.start()

    def _serve(self, conn: socket.socket) -> None:
        reader = FrameReader(expect_preamble=True)
        conn.settimeout(0.05)
        with conn:
            while not self._stop.is_set():
                try:
                    data = conn.recv(1 << 16)
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not data:
                    return
                for request in reader.feed(data):
                    assert reader.routing_id is not None
                    self.received.set()
                    if not self._answer(conn, reader.routing_id, request):
                        return

    def _answer(self, conn: socket.socket, peer: bytes, request: bytes) -> bool:
        """Answer one request as the behaviour says; False to stop serving this connection."""
        reply = self.session.handle(peer, request)
        try:
            message = decode_request(request)
        except ProtocolError:
            message = None
        behaviour = self.behaviour
        if behaviour == "silent":
            return True
        if behaviour == "partial":
            conn.sendall(LENGTH.pack(len(reply))[:2])
            return True
        if behaviour == "huge":
            conn.sendall(LENGTH.pack(2**31) + reply)
            return True
        if behaviour == "late" and isinstance(message, Step) and message.seq == 3:
            self._stop.wait(LATE_S)
        if behaviour == "another_seq" and isinstance(message, Step) and message.seq > 1:
            reply, self._previous = self._previous or reply, reply
        elif isinstance(message, Step | Reset):
            self._previous = reply
        try:
            conn.sendall(frame(reply) * (2 if behaviour == "twice_at_once" else 1))
            if behaviour == "twice":
                time.sleep(0.05)  # the second reply comes on its own
                conn.sendall(frame(reply))
        except OSError:
            return False
        return True


def wait_until(condition: threading.Event, timeout_s: float = 10.0) -> None:
    """Wait for a readiness signal, or fail the test."""
    if not condition.wait(timeout_s):
        raise AssertionError(f"no readiness signal within {timeout_s} s")


def elapsed_since(start: float) -> float:
    return time.monotonic() - start
