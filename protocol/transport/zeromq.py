"""ZeroMQ conventions shared by both peers: addresses, socket kinds and limits.

The server binds a ROUTER socket, the client connects a REQ socket (strict request/reply; one
request in flight). Both use ``LINGER = 0`` so that closing never blocks, and a hard cap on
incoming frames (`SOCKET_MAX_BYTES`) far above the protocol's own frame limit, so that an
oversized but finite frame still gets a `frame_too_large` error reply.

Liveness: both sockets send ZMTP heartbeats (PING/PONG, answered by ZeroMQ's I/O thread, so a
learner busy in a long gradient update or a server in a long simulation step still answers).
A peer that stops answering for `HEARTBEAT_TIMEOUT_MS` is disconnected: a dead or frozen peer
is told apart from a slow one. A client keeps one routing id for all its sockets and the server
sets ``ROUTER_HANDOVER``, so a client that reconnects on a fresh socket is still the same client
to the server (which owns the simulation per routing id).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable

import zmq

from protocol.transport.endpoint import Endpoint, parse_endpoint
from protocol.transport.security import (
    ClientCredentials,
    ServerCredentials,
    secure_client_socket,
    secure_server_socket,
)

SOCKET_MAX_BYTES = 16 * 1024 * 1024
"""Frames above this are dropped by ZeroMQ itself (the peer is disconnected, no reply)."""
HEARTBEAT_INTERVAL_MS = 1000
"""How often each side pings the other when the connection is quiet."""
HEARTBEAT_TIMEOUT_MS = 5000
"""A connection without any traffic (not even a PONG) for this long is closed."""


def _set_heartbeats(socket: zmq.Socket[bytes], timeout_ms: int) -> None:
    interval_ms = max(100, min(HEARTBEAT_INTERVAL_MS, timeout_ms // 3))
    socket.setsockopt(zmq.HEARTBEAT_IVL, interval_ms)
    socket.setsockopt(zmq.HEARTBEAT_TIMEOUT, timeout_ms)
    socket.setsockopt(zmq.HEARTBEAT_TTL, timeout_ms)


def bind_router(
    context: zmq.Context[zmq.Socket[bytes]],
    address: str,
    credentials: ServerCredentials | None = None,
    heartbeat_timeout_ms: int = HEARTBEAT_TIMEOUT_MS,
) -> tuple[zmq.Socket[bytes], Endpoint]:
    """Bind a ROUTER socket; port 0 asks the OS for a free port. Returns the bound endpoint.

    With `credentials` the socket is a CURVE server (start the authenticator first); a client
    silent on the wire (not even a PONG) for `heartbeat_timeout_ms` is disconnected.
    """
    endpoint = parse_endpoint(address)
    socket = context.socket(zmq.ROUTER)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.MAXMSGSIZE, SOCKET_MAX_BYTES)
    socket.setsockopt(zmq.ROUTER_MANDATORY, 0)
    socket.setsockopt(zmq.ROUTER_HANDOVER, 1)
    _set_heartbeats(socket, heartbeat_timeout_ms)
    if credentials is not None:
        secure_server_socket(socket, credentials)
    if endpoint.scheme == "tcp" and endpoint.port == 0:
        host = f"[{endpoint.host}]" if ":" in endpoint.host else endpoint.host
        if ":" in endpoint.host:
            socket.setsockopt(zmq.IPV6, 1)
        socket.bind(f"tcp://{host}:*")
    else:
        if endpoint.scheme == "tcp" and ":" in endpoint.host:
            socket.setsockopt(zmq.IPV6, 1)
        socket.bind(str(endpoint))
    bound = parse_endpoint(socket.getsockopt_string(zmq.LAST_ENDPOINT))
    return socket, bound


def connect_req(
    context: zmq.Context[zmq.Socket[bytes]],
    address: str,
    routing_id: bytes | None = None,
    credentials: ClientCredentials | None = None,
    heartbeat_timeout_ms: int = HEARTBEAT_TIMEOUT_MS,
    before_connect: Callable[[zmq.Socket[bytes]], None] | None = None,
) -> zmq.Socket[bytes]:
    """Connect a fresh REQ socket (one per attempt, as in the ZeroMQ guide's Lazy Pirate).

    Pass the same `routing_id` for every socket of one client so the server recognises it
    after a reconnect; with `credentials` the socket is a CURVE client. `before_connect` runs
    on the socket just before it connects (attach a monitor there: on loopback a refused
    handshake can be over before a monitor attached after the connect sees it).
    """
    endpoint = parse_endpoint(address)
    socket = context.socket(zmq.REQ)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.MAXMSGSIZE, SOCKET_MAX_BYTES)
    # Correlate: replies carry the request's id, so a late reply to an abandoned request is
    # dropped instead of being read as the answer to the next one. Relaxed: after a timeout
    # the same socket may send again (a retry) without waiting for the lost reply.
    socket.setsockopt(zmq.REQ_CORRELATE, 1)
    socket.setsockopt(zmq.REQ_RELAXED, 1)
    _set_heartbeats(socket, heartbeat_timeout_ms)
    if routing_id is not None:
        socket.setsockopt(zmq.ROUTING_ID, routing_id)
    if credentials is not None:
        secure_client_socket(socket, credentials)
    if endpoint.scheme == "tcp" and ":" in endpoint.host:
        socket.setsockopt(zmq.IPV6, 1)
    if before_connect is not None:
        before_connect(socket)
    socket.connect(str(endpoint))
    return socket


def remove_ipc_file(endpoint: Endpoint) -> None:
    """ZeroMQ leaves ipc socket files behind; remove ours on shutdown."""
    if endpoint.scheme == "ipc":
        with contextlib.suppress(FileNotFoundError):
            os.unlink(endpoint.path)
