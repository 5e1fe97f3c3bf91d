"""The direct transport: the same msgpack messages over a plain TCP socket, without ZeroMQ.

ZeroMQ moves every message through an I/O thread on each side: four thread hand-offs per round
trip, which on a small VM cost more than a SUMO step (docs/results.md, "Bridge performance").
``direct://HOST:PORT`` is the fast path for a learner and a simulator on one machine:

* the client opens a TCP connection and sends a preamble: ``AVB`` + the transport version byte
  + one length byte + its routing id (1-255 bytes, kept across reconnects, so the server knows a
  client that comes back on a fresh connection to retry its last step, as ZeroMQ's routing id);
* then each request and each reply is one frame: a 4-byte little-endian length and the msgpack
  payload. One request, one reply, in order.

Loopback only (no authentication or encryption: use ``tcp://`` with CURVE across machines), no
heartbeats (a dead peer is seen at once, a frozen one only by the other side's deadline). Both
ends may busy-wait a little for the reply before blocking (`spin_wait`): on a VM a blocked
process is woken tens of microseconds late.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Callable

from protocol.transport.zeromq import SOCKET_MAX_BYTES

SCHEME = "direct"
MAGIC = b"AVB"
TRANSPORT_VERSION = 1
LENGTH = struct.Struct("<I")
MAX_ROUTING_ID_BYTES = 255
DEFAULT_SPIN_US = 500
"""How long each end busy-waits for the peer before blocking (0: block at once)."""


class FramingError(Exception):
    """The byte stream is not this transport's: wrong preamble or a frame over the size cap."""


def preamble(routing_id: bytes) -> bytes:
    """The bytes a client sends first on every connection."""
    if not 1 <= len(routing_id) <= MAX_ROUTING_ID_BYTES:
        raise ValueError(f"routing id of {len(routing_id)} bytes: 1-{MAX_ROUTING_ID_BYTES} allowed")
    return MAGIC + bytes((TRANSPORT_VERSION, len(routing_id))) + routing_id


def frame(payload: bytes) -> bytes:
    """One frame: the length, then the payload."""
    return LENGTH.pack(len(payload)) + payload


class FrameReader:
    """Splits a byte stream into frames; with `expect_preamble`, reads the routing id first.

    Frames longer than `max_bytes` are a `FramingError` (the connection should be closed, as
    ZeroMQ's MAXMSGSIZE drops it), never a buffer that grows without bound.
    """

    def __init__(self, expect_preamble: bool = False, max_bytes: int = SOCKET_MAX_BYTES) -> None:
        self.routing_id: bytes | None = None if expect_preamble else b""
        self.max_bytes = max_bytes
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the frames now complete."""
        if not self._buffer and self.routing_id is not None and len(data) >= LENGTH.size:
            (size,) = LENGTH.unpack_from(data)  # the usual case: exactly one whole frame
            if len(data) == LENGTH.size + size and size <= self.max_bytes:
                return [data[LENGTH.size :]]
        self._buffer += data
        frames: list[bytes] = []
        if self.routing_id is None and not self._read_preamble():
            return frames
        buffer = self._buffer
        start = 0
        while len(buffer) - start >= LENGTH.size:
            (size,) = LENGTH.unpack_from(buffer, start)
            if size > self.max_bytes:
                raise FramingError(f"frame of {size} bytes exceeds {self.max_bytes}")
            end = start + LENGTH.size + size
            if len(buffer) < end:
                break
            frames.append(bytes(buffer[start + LENGTH.size : end]))
            start = end
        if start:
            del buffer[:start]
        return frames

    def _read_preamble(self) -> bool:
        buffer = self._buffer
        head = len(MAGIC) + 2
        if len(buffer) < head:
            if not MAGIC.startswith(bytes(buffer[: len(MAGIC)])):
                raise FramingError("not a direct-transport client (bad preamble)")
            return False
        if bytes(buffer[: len(MAGIC)]) != MAGIC or buffer[len(MAGIC)] != TRANSPORT_VERSION:
            raise FramingError("not a direct-transport client of version 1 (bad preamble)")
        size = buffer[len(MAGIC) + 1]
        if size == 0:
            raise FramingError("empty routing id")
        if len(buffer) < head + size:
            return False
        self.routing_id = bytes(buffer[head : head + size])
        del buffer[: head + size]
        return True

    @property
    def pending(self) -> int:
        """Bytes received but not yet part of a complete frame."""
        return len(self._buffer)


def spin_wait(ready: Callable[[], bool], spin_us: float) -> bool:
    """Busy-wait up to `spin_us` microseconds for `ready()`; True as soon as it is.

    Yields the CPU between checks: when the peer runs on the same core it gets it at once
    instead of after the scheduler's time slice (~1 ms).
    """
    if spin_us <= 0:
        return False
    clock, yield_cpu = time.perf_counter, os.sched_yield
    end = clock() + spin_us / 1e6
    while clock() < end:
        if ready():
            return True
        yield_cpu()
    return False
