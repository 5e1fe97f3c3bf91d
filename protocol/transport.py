"""ZeroMQ conventions shared by both peers: addresses, socket kinds and limits.

The server binds a ROUTER socket, the client connects a REQ socket (strict request/reply; one
request in flight). Both use ``LINGER = 0`` so that closing never blocks, and a hard cap on
incoming frames (`SOCKET_MAX_BYTES`) far above the protocol's own frame limit, so that an
oversized but finite frame still gets a `frame_too_large` error reply.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
from dataclasses import dataclass

import zmq

DEFAULT_ADDRESS = "tcp://127.0.0.1:5555"
SOCKET_MAX_BYTES = 16 * 1024 * 1024
"""Frames above this are dropped by ZeroMQ itself (the peer is disconnected)."""


@dataclass(frozen=True)
class Endpoint:
    """A parsed ``tcp://HOST:PORT`` or ``ipc://PATH`` address."""

    scheme: str
    host: str = ""
    port: int = 0
    path: str = ""

    def __str__(self) -> str:
        if self.scheme == "ipc":
            return f"ipc://{self.path}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tcp://{host}:{self.port}"

    @property
    def is_loopback(self) -> bool:
        """True for ipc and for tcp on a loopback address or ``localhost``."""
        if self.scheme == "ipc":
            return True
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


def parse_endpoint(address: str) -> Endpoint:
    """Parse and check an address; raises ValueError with the expected forms."""
    if address.startswith("ipc://"):
        path = address[len("ipc://") :]
        if not path:
            raise ValueError(f"{address!r}: ipc address needs a path, e.g. ipc:///tmp/bridge.sock")
        return Endpoint("ipc", path=path)
    if address.startswith("tcp://"):
        rest = address[len("tcp://") :]
        host, sep, port_text = rest.rpartition(":")
        host = host.strip("[]")
        if not sep or not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
            raise ValueError(f"{address!r}: expected tcp://HOST:PORT with PORT in 0..65535")
        return Endpoint("tcp", host=host, port=int(port_text))
    raise ValueError(f"{address!r}: expected tcp://HOST:PORT or ipc://PATH")


def bind_router(
    context: zmq.Context[zmq.Socket[bytes]], address: str
) -> tuple[zmq.Socket[bytes], Endpoint]:
    """Bind a ROUTER socket; port 0 asks the OS for a free port. Returns the bound endpoint."""
    endpoint = parse_endpoint(address)
    socket = context.socket(zmq.ROUTER)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.MAXMSGSIZE, SOCKET_MAX_BYTES)
    socket.setsockopt(zmq.ROUTER_MANDATORY, 0)
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


def connect_req(context: zmq.Context[zmq.Socket[bytes]], address: str) -> zmq.Socket[bytes]:
    """Connect a fresh REQ socket (one per attempt, as in the ZeroMQ guide's Lazy Pirate)."""
    endpoint = parse_endpoint(address)
    socket = context.socket(zmq.REQ)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.MAXMSGSIZE, SOCKET_MAX_BYTES)
    if endpoint.scheme == "tcp" and ":" in endpoint.host:
        socket.setsockopt(zmq.IPV6, 1)
    socket.connect(str(endpoint))
    return socket


def remove_ipc_file(endpoint: Endpoint) -> None:
    """ZeroMQ leaves ipc socket files behind; remove ours on shutdown."""
    if endpoint.scheme == "ipc":
        with contextlib.suppress(FileNotFoundError):
            os.unlink(endpoint.path)
