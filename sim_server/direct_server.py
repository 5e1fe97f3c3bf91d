"""The server loop of the direct transport (`protocol.direct`): plain TCP sockets, no ZeroMQ.

The same `Session` answers the same frames as behind the ZeroMQ `Server`; only the way frames
arrive differs. One listening socket and up to `MAX_CONNECTIONS` client connections are watched
with a selector; each connection starts with a preamble naming its client (its routing id), and a
client that connects again under the same id replaces its old connection (as ZeroMQ's
ROUTER_HANDOVER). A closed connection of the session's owner frees the simulator at once.
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading
from dataclasses import dataclass, field

from protocol.direct import DEFAULT_SPIN_US, FrameReader, FramingError, frame, spin_wait
from protocol.transport import Endpoint, parse_endpoint
from sim_server.server import POLL_INTERVAL_MS, Session

log = logging.getLogger("sim_server")

MAX_CONNECTIONS = 64
"""More simultaneous connections are closed at once (a flood cannot exhaust descriptors)."""
SEND_TIMEOUT_S = 10.0
"""A client that does not read its reply for this long is disconnected."""
_RECEIVE_BYTES = 1 << 16


@dataclass(eq=False)
class _Client:
    sock: socket.socket
    reader: FrameReader = field(default_factory=lambda: FrameReader(expect_preamble=True))

    @property
    def peer(self) -> bytes | None:
        return self.reader.routing_id


class DirectServer:
    """Binds a loopback TCP port and pumps frames through a `Session` until stopped."""

    def __init__(
        self,
        session: Session,
        address: str,
        spin_us: float = DEFAULT_SPIN_US,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        endpoint = parse_endpoint(address)
        if endpoint.scheme != "direct":
            raise ValueError(f"{address}: the direct server binds direct://HOST:PORT")
        if not endpoint.is_loopback:
            raise ValueError(
                f"{address}: the direct transport has no authentication and binds loopback "
                "addresses only; use tcp:// with --secret-key across machines"
            )
        self.session = session
        self.spin_us = spin_us
        self.max_connections = max_connections
        family = socket.AF_INET6 if ":" in endpoint.host else socket.AF_INET
        self._listener = socket.create_server((endpoint.host, endpoint.port), family=family)
        self._listener.setblocking(False)
        self.endpoint = Endpoint("direct", endpoint.host, self._listener.getsockname()[1])
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._clients: dict[int, _Client] = {}  # by file descriptor
        self._stop = threading.Event()

    def stop(self) -> None:
        """Ask the loop to return (safe from signal handlers and other threads)."""
        self._stop.set()

    @property
    def stopping(self) -> threading.Event:
        """Set once `stop` was called."""
        return self._stop

    def serve(self) -> None:
        """Serve requests until `stop`; always releases the sockets and the backend."""
        selector = self._selector
        timeout_s = POLL_INTERVAL_MS / 1000

        def anything() -> bool:
            return bool(selector.select(0))

        try:
            while not self._stop.is_set():
                spin_wait(anything, self.spin_us)
                for key, _ in selector.select(timeout_s):
                    if key.data is None:
                        self._accept()
                    else:
                        self._read(key.data)
        finally:
            self.close()

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except BlockingIOError:
            return
        if len(self._clients) >= self.max_connections:
            log.warning("more than %d connections: closing a new one", self.max_connections)
            sock.close()
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(SEND_TIMEOUT_S)  # reads happen only when the selector says readable
        client = _Client(sock)
        self._clients[sock.fileno()] = client
        self._selector.register(sock, selectors.EVENT_READ, client)

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(_RECEIVE_BYTES)
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        known = client.peer is not None
        try:
            frames = client.reader.feed(data)
        except FramingError as exc:
            log.info("closing a connection: %s", exc)
            self._drop(client)
            return
        if not known and client.peer is not None:
            self._hand_over(client)
        for request in frames:
            assert client.peer is not None
            reply = self.session.handle(client.peer, request)
            try:
                client.sock.sendall(frame(reply))
            except OSError:
                self._drop(client)
                return

    def _hand_over(self, client: _Client) -> None:
        """A client that came back under its routing id replaces its old connection."""
        for other in list(self._clients.values()):
            if other is not client and other.peer == client.peer:
                self._drop(other, handed_over=True)
        if client.peer == self.session.owner:
            self.session.owner_connected = True

    def _drop(self, client: _Client, handed_over: bool = False) -> None:
        fd = client.sock.fileno()
        if self._clients.pop(fd, None) is None:
            return
        self._selector.unregister(client.sock)
        client.sock.close()
        if not handed_over and client.peer is not None and client.peer == self.session.owner:
            self.session.owner_disconnected()

    def close(self) -> None:
        if self._listener.fileno() < 0:
            return
        for client in list(self._clients.values()):
            self._drop(client, handed_over=True)
        self._selector.close()
        self._listener.close()
        self.session.backend.close()
