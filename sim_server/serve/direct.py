"""The serving loop of the direct transport (`protocol.transport.direct`): plain sockets.

The same `Session` answers the same frames as behind the ZeroMQ `Server`; only the way frames
arrive differs. One listening socket and up to `MAX_CONNECTIONS` client connections are watched
with a selector, all non-blocking: a client that does not read its replies has them queued (up
to `MAX_PENDING_REPLY_BYTES`, for at most `SEND_TIMEOUT_S`) and is not read from meanwhile, so
no client can stall the loop. Each connection starts with a preamble naming its client (its
routing id); a client that connects again under the same id replaces its old connection (as
ZeroMQ's ROUTER_HANDOVER). A closed connection of the session's owner frees the simulator.
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import selectors
import socket
import time
from dataclasses import dataclass, field

from protocol.transport.direct import DEFAULT_SPIN_US, FrameReader, FramingError, frame, spin_wait
from protocol.transport.endpoint import Endpoint, parse_endpoint
from sim_server.serve.lifecycle import StopFlag
from sim_server.serve.zeromq import POLL_INTERVAL_MS
from sim_server.session import Session

log = logging.getLogger("sim_server")

MAX_CONNECTIONS = 64
"""At this many connections a new one evicts the longest-idle connection that is not the
session owner's (a flood of idle connections cannot lock the owner out)."""
MAX_REQUEST_BYTES = 1 << 20
"""A frame announced above this closes the connection (up to it, the session answers
``frame_too_large`` for frames above its own ``max_frame_bytes``)."""
MAX_PENDING_REPLY_BYTES = 1 << 20
"""Unread replies beyond this close the connection."""
SEND_TIMEOUT_S = 10.0
"""A client that leaves a reply unread for this long is disconnected."""
PREAMBLE_TIMEOUT_S = 5.0
"""A connection that has not named its client within this is closed."""
_RECEIVE_BYTES = 1 << 16
_ACCEPT_BACKOFF_S = 0.05


@dataclass(eq=False)
class _Client:
    sock: socket.socket
    opened: float
    reader: FrameReader = field(
        default_factory=lambda: FrameReader(expect_preamble=True, max_bytes=MAX_REQUEST_BYTES)
    )
    outgoing: bytearray = field(default_factory=bytearray)
    blocked_since: float | None = None
    """When a reply could not be written at once (None: nothing unsent)."""
    last_active: float = 0.0

    @property
    def peer(self) -> bytes | None:
        return self.reader.routing_id


class DirectServer(StopFlag):
    """Binds a loopback TCP port and pumps frames through a `Session` until stopped."""

    def __init__(
        self,
        session: Session,
        address: str,
        spin_us: float = DEFAULT_SPIN_US,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        super().__init__()
        endpoint = parse_endpoint(address)
        if endpoint.scheme != "direct":
            raise ValueError(f"{address}: the direct server binds direct://HOST:PORT")
        refusal = (
            f"{address}: the direct transport has no authentication and binds loopback "
            "addresses only; use tcp:// with --secret-key across machines"
        )
        if not endpoint.is_loopback:
            raise ValueError(refusal)
        family = socket.AF_INET6 if ":" in endpoint.host else socket.AF_INET
        self._listener = socket.create_server((endpoint.host, endpoint.port), family=family)
        bound_host, bound_port = self._listener.getsockname()[:2]
        if not ipaddress.ip_address(bound_host).is_loopback:  # e.g. a "localhost" that is not
            self._listener.close()
            raise ValueError(refusal)
        self._listener.setblocking(False)
        self.session = session
        self.spin_us = spin_us
        self.max_connections = max_connections
        self.endpoint = Endpoint("direct", endpoint.host, bound_port)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._clients: set[_Client] = set()
        self._accept_paused_until = 0.0

    def serve(self) -> None:
        """Serve requests until `stop`; always releases the sockets and the backend."""
        selector = self._selector
        timeout_s = POLL_INTERVAL_MS / 1000
        last_sweep = time.monotonic()

        def anything() -> bool:
            return bool(selector.select(0))

        try:
            while not self._stop.is_set():
                spin_wait(anything, self.spin_us)
                for key, events in selector.select(timeout_s):
                    if key.data is None:
                        self._accept()
                        continue
                    client: _Client = key.data
                    if events & selectors.EVENT_WRITE:
                        self._flush(client)
                    if events & selectors.EVENT_READ and client in self._clients:
                        self._read(client)
                now = time.monotonic()
                if now - last_sweep >= timeout_s:
                    self._sweep(now)
                    last_sweep = now
        finally:
            self.close()

    # ----------------------------------------------------------------------- connections

    def _accept(self) -> None:
        now = time.monotonic()
        if now < self._accept_paused_until:
            return
        try:
            sock, _ = self._listener.accept()
        except BlockingIOError:
            return
        except OSError as exc:  # out of descriptors, connection aborted...: serve on
            log.warning("accept failed: %s", exc)
            if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                self._accept_paused_until = now + _ACCEPT_BACKOFF_S
            return
        if len(self._clients) >= self.max_connections and not self._evict_one():
            sock.close()
            return
        try:
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            log.warning("cannot set up a new connection: %s", exc)
            sock.close()
            return
        client = _Client(sock, opened=now, last_active=now)
        self._clients.add(client)
        self._selector.register(sock, selectors.EVENT_READ, client)

    def _evict_one(self) -> bool:
        """Make room: close the longest-idle connection that is not the owner's."""
        others = [c for c in self._clients if c.peer is None or c.peer != self.session.owner]
        if not others:
            log.warning("%d connections, all the owner's: refusing a new one", len(self._clients))
            return False
        oldest = min(others, key=lambda c: c.last_active)
        log.info("%d connections: closing the longest idle one", len(self._clients))
        self._drop(oldest)
        return True

    def _sweep(self, now: float) -> None:
        """Close connections that never named their client, or leave replies unread."""
        for client in list(self._clients):
            if client.peer is None and now - client.opened > PREAMBLE_TIMEOUT_S:
                self._drop(client)
            elif client.blocked_since is not None and now - client.blocked_since > SEND_TIMEOUT_S:
                log.info("closing a connection that left its replies unread")
                self._drop(client)

    # ----------------------------------------------------------------------- frames

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(_RECEIVE_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        client.last_active = time.monotonic()
        known = client.peer is not None
        try:
            requests = client.reader.feed(data)
        except FramingError as exc:
            log.info("closing a connection: %s", exc)
            self._drop(client)
            return
        if not known and client.peer is not None:
            self._hand_over(client)
        for request in requests:
            assert client.peer is not None
            client.outgoing += frame(self.session.handle(client.peer, request))
            if len(client.outgoing) > MAX_PENDING_REPLY_BYTES:
                log.info(
                    "closing a connection with %d bytes of unread replies", MAX_PENDING_REPLY_BYTES
                )
                self._drop(client)
                return
        if requests:
            self._flush(client)

    def _flush(self, client: _Client) -> None:
        """Write what the socket takes now; wait for writability (not reading) for the rest."""
        try:
            sent = client.sock.send(client.outgoing)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError:
            self._drop(client)
            return
        del client.outgoing[:sent]
        if client.outgoing:
            if client.blocked_since is None:
                client.blocked_since = time.monotonic()
                self._selector.modify(client.sock, selectors.EVENT_WRITE, client)
        elif client.blocked_since is not None:
            client.blocked_since = None
            self._selector.modify(client.sock, selectors.EVENT_READ, client)

    def _hand_over(self, client: _Client) -> None:
        """A client that came back under its routing id replaces its old connection."""
        for other in list(self._clients):
            if other is not client and other.peer == client.peer:
                self._drop(other, handed_over=True)

    def _drop(self, client: _Client, handed_over: bool = False) -> None:
        if client not in self._clients:
            return
        self._clients.discard(client)
        self._selector.unregister(client.sock)
        client.sock.close()
        if not handed_over and client.peer is not None and client.peer == self.session.owner:
            self.session.owner_disconnected()

    def close(self) -> None:
        if self._listener.fileno() < 0:
            return
        for client in list(self._clients):
            self._drop(client, handed_over=True)
        self._selector.close()
        self._listener.close()
        self.session.backend.close()
