"""``sim-server --pool N``: one address, up to N sessions at once, a simulator process each.

libsumo runs one simulation per process, so the pool's front process runs no simulator: it binds
the public address (CURVE and heartbeats as a single server's) and starts N ordinary sim-server
processes on private ipc addresses in a directory only its user may enter, under the supervisor
of ``--workers`` (which restarts one that dies). Each client is routed to one of them:

- A client's ``hello`` goes to a free simulator (then to one whose client is gone or idle past
  the session timeout: that simulator decides, as it would on its own address). Where none is
  free, the client gets ``busy``, as from a single server that holds a session.
- Every client gets a connection of its own to its simulator, under an id derived from its own
  routing id: the simulator sees its client come, go and come back exactly as on its own address,
  so the session rules (ownership, a retried step, the session timeout) stay the simulator's. A
  client whose connection closes has its simulator's connection closed too (it is free at once).
- A simulator that exits fails the request in flight with ``simulator_error`` (the episode is
  over); the client's next ``reset`` is placed on a free simulator (waiting up to
  `PLACE_TIMEOUT_S` for one), the others' sessions go on. A client whose simulator another
  client took over gets ``busy``, as from a single server, until it says hello again.
- ``close`` frees the simulator.

The front only looks at a frame's type (`leading_type`) where it must: requests of a client with
a simulator are passed on without decoding.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from types import FrameType

import zmq

from protocol.codec import (
    DEFAULT_MAX_FRAME_BYTES,
    decode_reply,
    decode_request,
    encode,
    leading_type,
)
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import Bye, Error
from protocol.readiness import format_listening
from protocol.transport.security import ServerCredentials
from protocol.transport.zeromq import HEARTBEAT_TIMEOUT_MS
from sim_server.serve.lifecycle import StopFlag, stop_with_parent
from sim_server.serve.workers import Supervisor, Worker, without_options
from sim_server.serve.zeromq import POLL_INTERVAL_MS, RouterFront, source_fd
from sim_server.session import DEFAULT_SESSION_TIMEOUT_S

log = logging.getLogger("sim_server")

CHECK_INTERVAL_S = 0.1
"""How often the front looks for simulators that exited or came back."""
PLACE_TIMEOUT_S = 120.0
"""How long a client whose simulator exited waits for another one to come free."""
RETRY_INTERVAL_S = 1.0
"""How often a reset that waits for a simulator asks again those that refused it."""
ATTEMPT_TIMEOUT_S = 30.0
"""How long a simulator may take to answer a hello sent to place a client (one busy with a
long reset answers late) before the next one is tried."""


def pool_addresses(count: int) -> tuple[str, list[str]]:
    """A private directory (mode 0700) and `count` ipc addresses in it, one per simulator."""
    folder = tempfile.mkdtemp(prefix="av-bridge-pool-")
    return folder, [f"ipc://{folder}/simulator-{i}" for i in range(count)]


def link_id(peer: bytes) -> bytes:
    """The routing id of a client's connection to its simulator: the same for the same client
    (so that it comes back as itself), never starting with the zero byte ZeroMQ reserves."""
    return b"\x01" + hashlib.blake2b(peer, digest_size=16).digest()


@dataclass(eq=False)
class _Child:
    """One simulator process of the pool, as the front sees it."""

    index: int
    worker: Worker
    up: bool = False
    restarts_seen: int = 0
    holder: _Route | None = None
    """The client whose hello this simulator accepted (None: free)."""


@dataclass(eq=False)
class _Route:
    """One client: its hello, its simulator and its connection to it."""

    peer: bytes
    hello: bytes
    """The client's hello frame: said again for it where its simulator exited."""
    child: _Child | None = None
    link: zmq.Socket[bytes] | None = None
    fd: int | None = None
    connected: bool = True
    last_seen: float = 0.0
    in_flight: list[bytes] | None = None
    """The envelope of the request its simulator has not answered yet."""
    trying: _Child | None = None
    """The simulator its hello was sent to, while being placed."""
    tried: set[int] = field(default_factory=set)
    request: list[bytes] | None = None
    """While being placed: the request (envelope and frame) placing is for."""
    own_hello: bool = False
    """Placed by the front's own hello (its simulator exited): `request` is forwarded after."""
    waiting_since: float | None = None
    trying_since: float = 0.0
    request_kind: str | None = None
    """The type of `request` (a retry of the same type replaces it)."""
    retry_at: float = 0.0
    """While a reset waits for a simulator: when the refused ones are asked again."""
    displaced: bool = False
    """Its simulator was taken over by another client (after the session timeout, or once its
    connection had gone): it gets `busy`, as from a single server."""


class PoolServer(StopFlag):
    """The pool's front: binds the public address and routes each client to its simulator."""

    def __init__(
        self,
        supervisor: Supervisor,
        address: str,
        credentials: ServerCredentials | None = None,
        heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_MS / 1000,
        session_timeout_s: float = DEFAULT_SESSION_TIMEOUT_S,
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        folder: str | None = None,
    ) -> None:
        super().__init__()
        self.supervisor = supervisor
        self.session_timeout_s = session_timeout_s
        self.max_frame_bytes = max_frame_bytes
        self._folder = folder
        self._children = [_Child(i, w) for i, w in enumerate(supervisor.workers)]
        self._routes: dict[bytes, _Route] = {}
        self._by_link: dict[zmq.Socket[bytes], _Route] = {}
        self._closed_fds: set[int] = set()
        self._front = RouterFront(address, credentials, heartbeat_timeout_s)
        self.endpoint = self._front.endpoint
        self._context = self._front.context
        self._poller = zmq.Poller()
        self._poller.register(self._front.socket, zmq.POLLIN)
        self._poller.register(self._front.monitor, zmq.POLLIN)

    @property
    def sessions(self) -> int:
        """Simulators that hold a client's session now."""
        return sum(child.holder is not None for child in self._children)

    def serve(self) -> None:
        """Route requests until `stop`; always releases the sockets (not the simulators: the
        supervisor's)."""
        self._check_children(time.monotonic())  # the simulators ready now are up at once
        last_check = time.monotonic()
        try:
            while not self._stop.is_set():
                ready = dict(self._poller.poll(POLL_INTERVAL_MS))
                if self._front.socket in ready:  # data first, then news of a disconnection
                    self._read_front()
                for link in [s for s in ready if s in self._by_link]:
                    if link in self._by_link:  # not closed by an earlier reply in this round
                        self._read_link(link)
                if self._front.monitor in ready:
                    self._read_events()
                now = time.monotonic()
                if now - last_check >= CHECK_INTERVAL_S:
                    self._check_children(now)
                    last_check = now
        finally:
            self.close()

    # ----------------------------------------------------------------------- from clients

    def _read_front(self) -> None:
        head, envelope, body = self._front.receive()
        if len(body) != 1:
            refusal = Error(ErrorCode.DECODE_ERROR.value, f"expected one frame, got {len(body)}")
            self._answer(envelope, encode(refusal))
            return
        peer, frame = envelope[0], body[0]
        fd = source_fd(head)
        self._read_events()  # up to date: was this descriptor closed, or reused since?
        gone = fd is not None and fd in self._closed_fds
        route = self._routes.get(peer)
        if gone and (route is None or route.child is None):
            return  # sent by a client whose connection has closed since: nobody to answer
        if route is not None:
            if fd is not None and fd != route.fd:
                self._one_client_per_connection(route, fd)
            route.fd, route.connected, route.last_seen = fd, not gone, time.monotonic()
            if route.child is not None and route.trying is None:
                self._forward(route, envelope[1:], frame)  # the hot path: no decoding
                return
        elif fd is not None:
            self._one_client_per_connection(None, fd)
        kind = leading_type(frame) or _decoded_type(frame, self.max_frame_bytes)
        if route is not None and route.trying is not None:
            self._while_placing(route, envelope, frame, kind)
        elif kind == "hello":
            if route is None:
                route = self._routes[peer] = _Route(peer, frame, fd=fd, connected=not gone)
                route.last_seen = time.monotonic()
            route.hello, route.displaced = frame, False
            self._place(route, [*envelope, frame], own_hello=False)
        elif route is not None:
            self._without_simulator(route, envelope, frame, kind)
        else:
            self._answer(envelope, self._before_hello(frame, kind))

    def _one_client_per_connection(self, route: _Route | None, fd: int) -> None:
        """A connection carries one client: another route recorded on descriptor `fd` is of a
        connection that closed before this one reused the number (its news read already)."""
        for other in [r for r in self._routes.values() if r.fd == fd and r is not route]:
            self._disconnected(other)

    def _while_placing(
        self, route: _Route, envelope: list[bytes], frame: bytes, kind: str | None
    ) -> None:
        """A request while the client's hello (or reset) is being placed: a retry of it is
        answered in its place; anything else is told to wait."""
        assert route.request is not None
        if kind == route.request_kind:
            route.request = [*envelope, frame]
        else:
            why = f"{kind} while this client is being placed on a simulator: await the reply"
            self._answer(envelope, _refusal(ErrorCode.OUT_OF_ORDER, why))

    def _without_simulator(
        self, route: _Route, envelope: list[bytes], frame: bytes, kind: str | None
    ) -> None:
        """A client whose simulator exited or was taken over: its reset is placed afresh (not
        where it was taken over: `busy`, as a single server answers), its close ends it."""
        if kind == "close":
            self._answer(envelope, encode(Bye()))
            self._forget(route)
        elif route.displaced:
            self._answer(envelope, _refusal(ErrorCode.BUSY, _TAKEN))
        elif kind == "reset" and route.request is not None:
            route.request = [*envelope, frame]  # a retry while it waits: the same wait
        elif kind == "reset":
            self._place(route, [*envelope, frame], own_hello=True)
        else:
            self._answer(envelope, _refusal(ErrorCode.SIMULATOR_ERROR, _GONE))

    def _before_hello(self, frame: bytes, kind: str | None) -> bytes:
        """What a simulator would answer a client that has not said hello."""
        try:
            decode_request(frame, self.max_frame_bytes)
        except ProtocolError as exc:
            return encode(Error(exc.code.value, exc.message))
        return _refusal(ErrorCode.OUT_OF_ORDER, f"{kind} before hello: say hello first")

    def _forward(self, route: _Route, envelope: list[bytes], frame: bytes) -> None:
        assert route.child is not None
        if route.link is None:
            route.link = self._open_link(route, route.child)
        if _sent(route.link, [*envelope, frame]):
            route.in_flight = envelope
        else:
            self._answer([route.peer, *envelope], _refusal(ErrorCode.BUSY, _QUEUED))

    def _answer(self, envelope: list[bytes], reply: bytes) -> None:
        self._front.socket.send_multipart([*envelope, reply])

    # ----------------------------------------------------------------------- placing

    def _place(self, route: _Route, request: list[bytes], own_hello: bool) -> None:
        """Find `route` a simulator: its hello goes to the best candidate that it has not been
        refused by (`_try_next`)."""
        self._drop_link(route)
        if route.child is not None and route.child.holder is route:
            route.child.holder = None
        route.child = None
        route.request, route.own_hello, route.tried = request, own_hello, set()
        route.request_kind = leading_type(request[-1]) or _decoded_type(
            request[-1], self.max_frame_bytes
        )
        route.waiting_since = route.retry_at = time.monotonic()
        self._try_next(route)

    def _candidates(self, route: _Route) -> list[_Child]:
        """Simulators that may take `route`: free ones first, then those whose client is gone,
        then those whose client has been silent past the session timeout."""
        now = time.monotonic()

        def rank(child: _Child) -> int | None:
            holder = child.holder
            if holder is None:
                return 0
            if not holder.connected:
                return 1
            return 2 if now - holder.last_seen > self.session_timeout_s else None

        ranked = [
            (order, child)
            for child in self._children
            if child.up
            and child.index not in route.tried
            and child.holder is not route
            and (order := rank(child)) is not None
        ]
        return [child for _, child in sorted(ranked, key=lambda pair: (pair[0], pair[1].index))]

    def _try_next(self, route: _Route) -> None:
        assert route.request is not None
        for child in self._candidates(route):
            route.trying, route.trying_since = child, time.monotonic()
            route.tried.add(child.index)
            link = self._open_link(route, child)
            hello = [b"", route.hello] if route.own_hello else route.request[1:]
            if _sent(link, hello):
                return
            self._drop_link(route)
            route.trying = None
            continue
        route.trying = None
        if route.own_hello:
            return  # waits for a simulator to come free (`_check_children`), within a bound
        busy = (
            f"all {len(self._children)} simulators of this pool hold sessions; retry later or "
            "start a larger pool (sim-server --pool N)"
        )
        self._answer(route.request[:-1], _refusal(ErrorCode.BUSY, busy))
        self._forget(route)

    def _placed(self, route: _Route, reply: list[bytes]) -> None:
        """The answer to a hello sent while placing `route`."""
        child, request = route.trying, route.request
        assert child is not None and request is not None
        frame = reply[-1]
        kind = leading_type(frame)
        if kind == "error" and _error_code(frame) == ErrorCode.BUSY.value:
            self._drop_link(route)
            route.trying = None
            self._try_next(route)
            return
        route.trying, route.request, route.waiting_since = None, None, None
        if kind != "welcome":  # refused for a reason of the client's own: it reads why
            self._drop_link(route)
            self._answer(request[:-1], frame)  # the envelope of its latest try
            self._forget(route)
            return
        previous = child.holder
        if previous is not None and previous is not route:
            self._lose(previous, displaced=True)
        child.holder, route.child = route, child
        if route.own_hello:
            self._forward(route, request[1:-1], request[-1])
        else:
            self._answer(request[:-1], frame)
        if not route.connected:  # gone meanwhile: its simulator is free again at once
            self._drop_link(route)

    # ----------------------------------------------------------------------- from simulators

    def _read_link(self, link: zmq.Socket[bytes]) -> None:
        route = self._by_link[link]
        reply = link.recv_multipart()
        if route.trying is not None:
            self._placed(route, reply)
            return
        route.in_flight = None
        self._answer([route.peer, *reply[:-1]], reply[-1])
        if leading_type(reply[-1]) == "bye":
            self._forget(route)  # the session is over: the simulator is free
        elif not route.connected:
            self._drop_link(route)  # the client died after sending: its simulator is free

    def _read_events(self) -> None:
        for event, fd in self._front.events():
            if event == zmq.EVENT_ACCEPTED:
                self._closed_fds.discard(fd)
            elif event == zmq.EVENT_DISCONNECTED:
                self._closed_fds.add(fd)
                for route in [r for r in self._routes.values() if r.fd == fd]:
                    self._disconnected(route)

    def _disconnected(self, route: _Route) -> None:
        """The client's connection closed: its simulator's connection closes too (the
        simulator is free for another client at once; the same client may come back)."""
        route.connected = False
        self._drop_link(route)
        if route.child is None:
            self._forget(route)

    def _check_children(self, now: float) -> None:
        for child in self._children:
            worker = child.worker
            alive = worker.process is not None and worker.process.poll() is None
            if child.up and (not alive or worker.restarts != child.restarts_seen):
                log.warning("simulator %d exited; its client's episode is over", child.index)
                child.up = False
                self._fail(child)
            elif not child.up and alive and worker.ready:
                child.up, child.restarts_seen = True, worker.restarts
        for route in list(self._routes.values()):
            if route.request is None:
                continue
            if route.trying is not None:
                if now - route.trying_since > ATTEMPT_TIMEOUT_S:  # silent: the next one
                    log.warning("simulator %d did not answer a hello", route.trying.index)
                    self._drop_link(route)
                    route.trying = None
                    self._try_next(route)
                continue
            assert route.waiting_since is not None
            if now - route.waiting_since > PLACE_TIMEOUT_S:
                why = f"no simulator of the pool came free within {PLACE_TIMEOUT_S:g} s"
                self._answer(route.request[:-1], _refusal(ErrorCode.SIMULATOR_ERROR, why))
                route.request = None
            elif now >= route.retry_at:  # a simulator that refused may be free by now
                route.tried.clear()
                route.retry_at = now + RETRY_INTERVAL_S
                self._try_next(route)

    def _fail(self, child: _Child) -> None:
        """`child` exited: what was sent to it is answered for it."""
        for route in list(self._routes.values()):
            if route.trying is child:
                self._drop_link(route)
                route.trying = None
                self._try_next(route)
            elif route.child is child:
                if route.in_flight is not None:
                    why = "the simulator process serving this session exited; send reset"
                    self._answer([route.peer, *route.in_flight], _refusal(_FAILED, why))
                self._lose(route)
        child.holder = None

    def _lose(self, route: _Route, displaced: bool = False) -> None:
        """`route` no longer has its simulator: its next reset is placed afresh, or (taken over
        by another client) it is told `busy`."""
        if displaced and route.in_flight is not None:
            self._answer([route.peer, *route.in_flight], _refusal(ErrorCode.BUSY, _TAKEN))
        self._drop_link(route)
        route.child, route.in_flight, route.displaced = None, None, displaced
        if not route.connected:
            self._forget(route)

    # ----------------------------------------------------------------------- links

    def _open_link(self, route: _Route, child: _Child) -> zmq.Socket[bytes]:
        self._drop_link(route)
        link = self._context.socket(zmq.DEALER)
        link.setsockopt(zmq.LINGER, 0)
        link.setsockopt(zmq.ROUTING_ID, link_id(route.peer))
        link.connect(child.worker.address)
        route.link = link
        self._by_link[link] = route
        self._poller.register(link, zmq.POLLIN)
        return link

    def _drop_link(self, route: _Route) -> None:
        link, route.link = route.link, None
        if link is not None:
            self._poller.unregister(link)
            del self._by_link[link]
            link.close(linger=0)

    def _forget(self, route: _Route) -> None:
        self._drop_link(route)
        if route.child is not None and route.child.holder is route:
            route.child.holder = None
        route.child, route.request = None, None
        self._routes.pop(route.peer, None)

    def close(self) -> None:
        if self._front.closed:
            return
        for route in list(self._routes.values()):
            self._drop_link(route)
        self._front.close()
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)


_FAILED = ErrorCode.SIMULATOR_ERROR
_GONE = "this session's simulator process exited; send reset for a new episode"
_TAKEN = (
    "another client holds this simulator (it took over after the session timeout, or once "
    "this client's connection had gone); say hello for another one"
)
_QUEUED = "too many requests of this client are queued for its simulator; await the replies"


def _sent(link: zmq.Socket[bytes], frames: list[bytes]) -> bool:
    """Send without blocking: a client that floods its simulator must not stall the pool."""
    try:
        link.send_multipart(frames, flags=zmq.NOBLOCK)
    except zmq.Again:
        return False
    return True


def _refusal(code: ErrorCode, message: str) -> bytes:
    return encode(Error(code.value, message))


def _error_code(frame: bytes) -> str | None:
    try:
        reply = decode_reply(frame)
    except ProtocolError:
        return None
    return reply.code if isinstance(reply, Error) else None


def _decoded_type(frame: bytes, max_frame_bytes: int) -> str | None:
    """The type of a request whose first key is not ``type`` (a peer's own encoder)."""
    try:
        return decode_request(frame, max_frame_bytes).TYPE
    except ProtocolError:
        return None


def run_pool(
    argv: list[str],
    count: int,
    credentials: ServerCredentials | None,
    *,
    bind: str,
    heartbeat_timeout_s: float,
    session_timeout_s: float,
    max_frame_bytes: int,
    exit_with_parent: bool,
    env: dict[str, str],
) -> int:
    """The ``--pool`` mode of the CLI: `count` simulators behind the front on `bind`; `argv`
    is the command line it was given (the simulators get it without the address and keys, and
    `env`: without the keys' variables)."""
    folder, addresses = pool_addresses(count)
    private = ("--pool", "--bind", "--secret-key", "--authorized-keys", "--workers")
    supervisor = Supervisor(without_options(argv, private), addresses, env=env)
    server: PoolServer | None = None

    def on_signal(signum: int, frame: FrameType | None) -> None:
        supervisor.stop()
        if server is not None:
            server.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        supervisor.start()
        if supervisor.stopping:  # a signal came while the simulators started
            return 0
        try:
            server = PoolServer(
                supervisor, bind, credentials, heartbeat_timeout_s, session_timeout_s,
                max_frame_bytes, folder,
            )  # fmt: skip
        except Exception as exc:  # zmq.ZMQError and OS errors: report and exit cleanly
            print(f"sim-server: cannot bind {bind}: {exc}", file=sys.stderr)
            return 1
        if supervisor.stopping:  # a signal came while the front was built
            server.close()
            return 0
        if exit_with_parent:
            stop_with_parent(server)
        threading.Thread(target=supervisor.supervise, name="pool-supervisor", daemon=True).start()
        print(format_listening(server.endpoint), flush=True)
        log.info("a pool of %d simulators ready; restarting any that exits", count)
        server.serve()
    except RuntimeError as exc:
        print(f"sim-server: {exc}", file=sys.stderr)
        return 1
    finally:
        supervisor.stop()
        supervisor.shutdown()
        shutil.rmtree(folder, ignore_errors=True)
    log.info("stopped")
    return 0
