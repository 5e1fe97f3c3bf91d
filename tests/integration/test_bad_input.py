"""Malformed requests over a real socket: each gets its error code and the server keeps serving."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zmq

from agent_client.envs.remote_env import RemoteEnv
from agent_client.transport import ZmqChannel
from protocol.messages import Error, Hello, Observation, Reset, Step
from protocol.version import PROTOCOL_VERSION
from tests.conftest import RunningServer

pytestmark = pytest.mark.sumo

BAD_FRAMES = [
    (b"\xc1\xc1\xc1", "decode_error"),
    (msgpack.packb({"type": "hello", "protocol": [1, 0], "client": "x" * 100_000}), "frame_too_large"),
    (msgpack.packb({"type": "step", "seq": "one", "acceleration": 0.0}), "invalid_message"),
    (msgpack.packb({"type": "step", "seq": 1}), "invalid_message"),
    (msgpack.packb({"type": "step", "seq": 1, "acceleration": float("nan")}), "invalid_number"),
    (msgpack.packb({"type": "step", "seq": 1, "acceleration": float("-inf")}), "invalid_number"),
    (msgpack.packb({"type": "jump"}), "unknown_type"),
    (msgpack.packb({"type": "step", "seq": 1, "acceleration": 0.0}), "out_of_order"),
    (msgpack.packb({"type": "hello", "protocol": [99, 0]}), "version_mismatch"),
]  # fmt: skip


def test_every_bad_request_gets_its_own_error_and_the_server_goes_on(
    sumo_server: RunningServer,
) -> None:
    with ZmqChannel(sumo_server.address, timeout_s=10.0) as connection:
        connection.request(Hello(PROTOCOL_VERSION))
        codes = []
        for frame, expected in BAD_FRAMES:
            reply = connection.exchange_raw(frame)
            assert isinstance(reply, Error), (expected, reply)
            codes.append(reply.code)
            assert reply.code == expected, reply.message
        assert len(set(codes)) == 7  # seven kinds of fault, seven distinct codes
        connection.request(Hello(PROTOCOL_VERSION))
        assert isinstance(connection.request(Reset("cf", 1)), Observation)
        assert isinstance(connection.request(Step(1, 0.0)), Observation)
        connection.exchange(__import__("protocol").Close())
    assert sumo_server.process.poll() is None


def test_multipart_garbage_from_a_raw_socket_is_answered(sumo_server: RunningServer) -> None:
    context = zmq.Context()
    dealer = context.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(sumo_server.address)
    try:
        dealer.send_multipart([b"", b"one", b"two"])
        assert dealer.poll(10_000)
        frames = dealer.recv_multipart()
        reply = msgpack.unpackb(frames[-1], raw=False)
        assert reply["type"] == "error" and reply["code"] == "decode_error"
    finally:
        dealer.close(linger=0)
        context.term()
    env = RemoteEnv(sumo_server.address, "cf", reward=lambda p, o, d: 0.0)
    try:
        env.reset(seed=2)
        env.step({"acceleration": np.zeros(1), "lane_change": 0})
    finally:
        env.close()
