"""The learner's end of the wire: one request, one reply, always within a deadline.

Follows the ZeroMQ guide's Lazy Pirate client: a REQ socket with ``LINGER = 0`` and a poll with a
timeout on every receive. The socket is relaxed and correlated, so after a timeout the same
request may simply be sent again (the server answers a retried step from its cache, and the late
reply to the first attempt is dropped by ZeroMQ). A broken or untrustworthy connection gets a
fresh socket; every socket of one `ZmqChannel` carries the same routing id, so the server still
knows the client after such a reconnect.

A message that does not carry the request's id (a late reply to an abandoned attempt, a second
reply, or a server that drops the REQ envelope's request-id frame) is discarded by the REQ
socket: the receive never blocks on it, and a timeout says how many were discarded.

While it waits, the connection also watches its socket's events: ZeroMQ's heartbeats close a
connection whose peer stopped answering, so a dead or frozen server raises `ServerLost` within
seconds even when a step may legitimately take much longer (`ServerTimeout`); a refused CURVE
handshake raises `AuthenticationFailed` at once.
"""

from __future__ import annotations

import time

import zmq
from zmq.utils.monitor import parse_monitor_message

from agent_client.defaults import STEP_TIMEOUT_S
from agent_client.errors import AuthenticationFailed, MalformedReply, ServerLost, ServerTimeout
from agent_client.transport.channel import Channel
from protocol.transport.endpoint import new_routing_id, parse_endpoint
from protocol.transport.security import ClientCredentials
from protocol.transport.zeromq import HEARTBEAT_TIMEOUT_MS, connect_req

POLL_SLICE_MS = 200
"""The longest single wait for a reply: a Ctrl-C that the kernel hands to one of libzmq's I/O
threads does not wake the main thread's poll, which sees it only when the poll returns (a
whole `--timeout` later, unsliced: a loaded machine made that likely)."""

_UP = zmq.EVENT_HANDSHAKE_SUCCEEDED
_LOST = zmq.EVENT_DISCONNECTED
_REFUSED = zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
"""A refused handshake: wrong keys, or CURVE on one side only."""
_FAILED = zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
"""A handshake that broke off: a CURVE server meeting a plain client, but also a connection cut
mid-handshake (a server being restarted): refused after `FAILED_HANDSHAKES_REFUSED` in a row."""
FAILED_HANDSHAKES_REFUSED = 3
"""ZeroMQ retries every 100 ms, so a refusal is reported within about half a second."""


class ZmqChannel(Channel):
    """The ZeroMQ channel: a REQ socket (Lazy Pirate), heartbeats, CURVE when keys are given."""

    def __init__(
        self,
        address: str,
        timeout_s: float = STEP_TIMEOUT_S,
        credentials: ClientCredentials | None = None,
        heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
        routing_id: bytes | None = None,
    ) -> None:
        """`credentials` default to $AV_BRIDGE_SERVER_KEY / $AV_BRIDGE_SECRET_KEY when set; a
        server silent on the wire (no heartbeat answered) for `heartbeat_timeout_s` is lost."""
        parse_endpoint(address)  # fail early on a malformed address
        self.address = address
        self.timeout_s = timeout_s
        self.credentials = credentials or ClientCredentials.from_environment()
        self.heartbeat_timeout_ms = int(heartbeat_timeout_s * 1000)
        self.routing_id = routing_id or new_routing_id()
        self._context = zmq.Context()
        self._socket: zmq.Socket[bytes] | None = None
        self._monitor: zmq.Socket[bytes] | None = None
        self._session_up = False
        """A handshake succeeded on the current connection (requests reach the server)."""
        self._failed_handshakes = 0
        self.discarded = 0
        """Messages the REQ socket discarded as answering no request in flight (they lack the
        request's id): late or repeated replies, or a server that drops the request-id frame."""

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
        discarded = 0
        while True:
            remaining_ms = int(max(0.0, deadline - time.monotonic()) * 1000)
            ready = {s for s, _ in zmq.zmq_poll(watched, min(remaining_ms, POLL_SLICE_MS))}
            if socket in ready:
                try:  # never a blocking recv: the REQ socket discards uncorrelated replies
                    frames = socket.recv_multipart(zmq.NOBLOCK)
                    break
                except zmq.Again:  # readable, but nothing it keeps: it lacked the request id
                    discarded += 1
                    self.discarded += 1
                    continue
            if monitor in ready:
                self._check_events(waiting=True)
                continue
            if time.monotonic() < deadline:
                continue
            raise ServerTimeout(self._no_reply(wait_s, discarded))
        if len(frames) != 1:
            self._drop_socket()
            raise MalformedReply(f"reply from {self.address} has {len(frames)} frames, expected 1")
        return frames[0]

    def drop(self) -> None:
        self._drop_socket()

    def _no_reply(self, wait_s: float, discarded: int) -> str:
        """Why a receive timed out (`Channel.no_reply`), naming the messages the REQ socket
        discarded meanwhile: then the server answers, but not this request."""
        if not discarded:
            return self.no_reply(wait_s)
        return (
            f"no reply from {self.address} within {wait_s:.1f} s: {discarded} message(s) "
            "arrived without this request's id and were discarded (does the server echo the "
            "whole envelope, request-id frame included? docs/protocol.md §7.1)"
        )

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

            def watch(socket: zmq.Socket[bytes]) -> None:  # before the handshake can happen
                self._monitor = socket.get_monitor_socket(_UP | _LOST | _REFUSED | _FAILED)

            self._socket = connect_req(
                self._context,
                self.address,
                self.routing_id,
                self.credentials,
                self.heartbeat_timeout_ms,
                before_connect=watch,
            )
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
