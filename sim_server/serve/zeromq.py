"""The ZeroMQ serving loop: one ROUTER socket in front of one `Session`.

The loop moves frames between the socket and the session, tells the session when its client's
connection is gone (killed, or silent past ZeroMQ's heartbeat timeout) and watches for shutdown.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import zmq
from zmq.utils.monitor import parse_monitor_message

from protocol.codec import encode
from protocol.errors import ErrorCode
from protocol.messages import Error
from protocol.transport.security import ServerCredentials, start_authenticator
from protocol.transport.zeromq import HEARTBEAT_TIMEOUT_MS, bind_router, remove_ipc_file
from sim_server.serve.lifecycle import StopFlag
from sim_server.session import Session

log = logging.getLogger("sim_server")

POLL_INTERVAL_MS = 100


class RouterFront:
    """A server's bound ROUTER socket with its context, its CURVE authenticator and the monitor
    of its connections (accepted, closed): the single `Server`'s and a pool's front."""

    def __init__(
        self,
        address: str,
        credentials: ServerCredentials | None = None,
        heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
    ) -> None:
        self.context = zmq.Context()
        self._authenticator = (
            start_authenticator(self.context, credentials) if credentials is not None else None
        )
        try:
            self.socket, self.endpoint = bind_router(
                self.context, address, credentials, int(heartbeat_timeout_s * 1000)
            )
        except Exception:
            self._release_context()
            raise
        self.monitor = self.socket.get_monitor_socket(zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED)

    def receive(self) -> tuple[zmq.Frame, list[bytes], list[bytes]]:
        """The next request: its first frame (for `source_fd`), its envelope (the routing id and
        every frame up to the empty delimiter: a correlated REQ client's request id among them)
        and its body. Only the first frame is received as a zmq.Frame."""
        socket = self.socket
        head = socket.recv(copy=False)
        parts = [head.bytes]
        while socket.rcvmore:
            parts.append(socket.recv())
        try:
            split = parts.index(b"", 1) + 1
        except ValueError:
            split = 1
        return head, parts[:split], parts[split:]

    def events(self) -> Iterator[tuple[int, int]]:
        """The monitor's events that have come, as (event, descriptor), without waiting."""
        while self.monitor.poll(0):
            event = parse_monitor_message(self.monitor.recv_multipart())
            yield event["event"], event["value"]

    @property
    def closed(self) -> bool:
        return bool(self.socket.closed)

    def close(self) -> None:
        if self.socket.closed:
            return
        self.socket.disable_monitor()
        self.monitor.close(linger=0)
        self.socket.close(linger=0)
        self._release_context()
        remove_ipc_file(self.endpoint)

    def _release_context(self) -> None:
        if self._authenticator is not None:
            self._authenticator.stop()
        self.context.term()


class Server(StopFlag):
    """Binds the socket and pumps frames through a `Session` until stopped."""

    def __init__(
        self,
        session: Session,
        address: str,
        credentials: ServerCredentials | None = None,
        heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
    ) -> None:
        super().__init__()
        self.session = session
        self.address = address
        self._front = RouterFront(address, credentials, heartbeat_timeout_s)
        self.endpoint = self._front.endpoint
        self._owner_fd: int | None = None
        self._closed_fds: set[int] = set()
        """Connections reported closed (and not reused since): a request read from one of them
        was sent before its client died and must not mark the client connected again."""

    def serve(self) -> None:
        """Serve requests until `stop`; always releases the socket and the backend."""
        socket, monitor = self._front.socket, self._front.monitor
        watched = [(socket, zmq.POLLIN), (monitor, zmq.POLLIN)]
        try:
            while not self._stop.is_set():
                ready = {s for s, _ in zmq.zmq_poll(watched, POLL_INTERVAL_MS)}
                if socket in ready:  # data first: a request a client sent before it died...
                    self._answer()
                if monitor in ready:  # ...comes before the news of its disconnection
                    self._read_events()
        finally:
            self.close()

    def _read_events(self) -> None:
        for event, fd in self._front.events():
            if event == zmq.EVENT_ACCEPTED:
                self._closed_fds.discard(fd)  # the descriptor now names a new connection
            elif event == zmq.EVENT_DISCONNECTED:
                self._closed_fds.add(fd)
                if fd == self._owner_fd:
                    self._owner_fd = None
                    self.session.owner_disconnected()

    def _answer(self) -> None:
        # A REQ peer sends [routing id, request id, b"", payload]; keep the envelope, answer the
        # payload.
        head, envelope, body = self._front.receive()
        if len(body) != 1:
            reply = encode(
                Error(ErrorCode.DECODE_ERROR.value, f"expected one frame, got {len(body)}")
            )
        else:
            peer = envelope[0]
            reply = self.session.handle(peer, body[0])
            if self.session.owner == peer:
                fd = source_fd(head)
                self._read_events()  # up to date: was this descriptor closed, or reused since?
                if fd is not None and fd in self._closed_fds:
                    self.session.owner_disconnected()  # its connection is already gone
                else:
                    self._owner_fd = fd
        self._send(envelope, reply)

    def _send(self, envelope: list[bytes], reply: bytes) -> None:
        """The reply behind the request's whole envelope."""
        self._front.socket.send_multipart([*envelope, reply])

    def close(self) -> None:
        if self._front.closed:
            return
        self._front.close()
        self.session.backend.close()


def source_fd(frame: zmq.Frame) -> int | None:
    """The file descriptor of the connection a frame came in on (None if unavailable)."""
    try:
        return int(frame.get(zmq.SRCFD))
    except (zmq.ZMQError, AttributeError, TypeError, ValueError):
        return None
