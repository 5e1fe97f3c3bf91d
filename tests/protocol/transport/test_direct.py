"""Framing of the direct transport: preamble, length-prefixed frames, size cap, spinning."""

from __future__ import annotations

import itertools
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.transport.direct import (
    LENGTH,
    FrameReader,
    FramingError,
    frame,
    preamble,
    spin_wait,
)
from protocol.transport.endpoint import Endpoint, parse_endpoint


def test_direct_addresses_parse_and_print() -> None:
    endpoint = parse_endpoint("direct://127.0.0.1:5556")
    assert endpoint == Endpoint("direct", "127.0.0.1", 5556)
    assert str(endpoint) == "direct://127.0.0.1:5556"
    assert endpoint.is_loopback
    assert not parse_endpoint("direct://10.0.0.2:1").is_loopback
    with pytest.raises(ValueError, match="direct://HOST:PORT"):
        parse_endpoint("direct://nohost")


@given(
    routing_id=st.binary(min_size=1, max_size=255),
    payloads=st.lists(st.binary(max_size=300), max_size=8),
    cuts=st.lists(st.integers(min_value=0, max_value=4000), max_size=12),
)
def test_any_chunking_yields_the_routing_id_and_the_frames(
    routing_id: bytes, payloads: list[bytes], cuts: list[int]
) -> None:
    stream = preamble(routing_id) + b"".join(frame(p) for p in payloads)
    bounds = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    reader = FrameReader(expect_preamble=True)
    got = []
    for start, end in itertools.pairwise(bounds):
        got += reader.feed(stream[start:end])
    assert reader.routing_id == routing_id
    assert got == payloads
    assert reader.pending == 0


def test_a_frame_over_the_cap_is_refused_without_waiting_for_its_bytes() -> None:
    reader = FrameReader(max_bytes=1000)
    with pytest.raises(FramingError, match="exceeds 1000"):
        reader.feed(LENGTH.pack(1001) + b"x" * 10)
    assert FrameReader(max_bytes=1000).feed(frame(b"y" * 1000)) == [b"y" * 1000]


@pytest.mark.parametrize(
    "stream",
    [b"GET / HTTP/1.1\r\n", b"AVB\x02\x01x", b"AVB\x01\x00", b"\x00\x00\x00\x01"],
    ids=["http", "version-2", "empty-id", "no-preamble"],
)
def test_a_stream_without_a_valid_preamble_is_refused(stream: bytes) -> None:
    with pytest.raises(FramingError):
        FrameReader(expect_preamble=True).feed(stream)


def test_a_partial_preamble_waits_for_more() -> None:
    reader = FrameReader(expect_preamble=True)
    assert reader.feed(b"AV") == []
    assert reader.routing_id is None
    assert reader.feed(b"B\x01\x02ab" + frame(b"m")) == [b"m"]
    assert reader.routing_id == b"ab"


def test_routing_ids_are_bounded() -> None:
    with pytest.raises(ValueError, match="1-255"):
        preamble(b"")
    with pytest.raises(ValueError, match="1-255"):
        preamble(b"x" * 256)


def test_spin_wait_returns_when_ready_and_gives_up_in_time() -> None:
    calls = []

    def third_time() -> bool:
        calls.append(1)
        return len(calls) == 3

    assert spin_wait(third_time, 1e6)
    assert len(calls) == 3
    started = time.perf_counter()
    assert not spin_wait(lambda: False, 2000)
    assert 0.002 <= time.perf_counter() - started < 1.0
    assert not spin_wait(lambda: True, 0)  # 0: no spinning at all
