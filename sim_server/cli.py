"""``sim-server``: run a simulator behind the bridge protocol.

Prints ``listening on ADDRESS`` on stdout once it accepts requests; logs go to stderr. A command
line that cannot be served is refused with one line on stderr naming the bad value, and exit
status 2. ``sim-server keygen --out DIR`` writes CURVE key pairs for an authenticated server.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn
from xml.etree import ElementTree

from protocol.codec import DEFAULT_MAX_FRAME_BYTES
from protocol.readiness import format_listening
from protocol.transport.direct import DEFAULT_SPIN_US
from protocol.transport.endpoint import DEFAULT_ADDRESS, Endpoint, parse_endpoint
from protocol.transport.security import ServerCredentials, generate_keys, load_key_pair
from protocol.transport.zeromq import HEARTBEAT_TIMEOUT_MS
from sim_server import __version__
from sim_server.backends.base import Backend
from sim_server.backends.sumo.gui import DEFAULT_DELAY_MS, DEFAULT_SPAN_M, GuiView
from sim_server.errors import UsageError
from sim_server.serve.direct import DirectServer
from sim_server.serve.lifecycle import stop_with_parent
from sim_server.serve.zeromq import Server
from sim_server.session import DEFAULT_SESSION_TIMEOUT_S, Session

SECRET_KEY_ENV = "SIM_SERVER_SECRET_KEY"
AUTHORIZED_KEYS_ENV = "SIM_SERVER_AUTHORIZED_KEYS"

BACKENDS = ("sumo", "sumo-traci", "fake", "highway", "replay")
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
USAGE_STATUS = 2
"""Exit status of a refused command line (as argparse's own)."""

_PROVIDERS = {
    "highway_env": ("highway-env", "highway"),
    "libsumo": ("libsumo", "server"),
    "traci": ("traci", "server"),
    "sumo": ("eclipse-sumo", "server"),
}
"""Module a backend imports -> (the package that provides it, the extra of this project that
installs it)."""


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line (``--help`` lists the options), and
    which takes no abbreviated option: ``--workers`` and ``--pool`` hand their command line on
    to the servers they start, without the options that are theirs, named in full."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **{"allow_abbrev": False, **kwargs})

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_STATUS, f"{self.prog}: error: {message}\n")


# --------------------------------------------------------------------------- the parsers


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="sim-server",
        description="Serve a traffic simulator to a learner over the bridge protocol.",
    )
    parser.add_argument(
        "--bind",
        default=DEFAULT_ADDRESS,
        help="address to listen on: tcp://HOST:PORT (port 0 picks a free port) or ipc://PATH "
        "(ZeroMQ), or direct://127.0.0.1:PORT (plain socket, loopback only, fastest) "
        f"(default {DEFAULT_ADDRESS})",
    )
    _add_simulator_arguments(parser.add_argument_group("simulator"))
    _add_connection_arguments(parser.add_argument_group("connections"))
    _add_security_arguments(parser.add_argument_group("authentication (CURVE, tcp:// and ipc://)"))
    _add_process_arguments(parser.add_argument_group("processes"))
    parser.add_argument(
        "--log-level",
        default="INFO",
        type=str.upper,
        choices=LOG_LEVELS,
        help="DEBUG, INFO, WARNING, ERROR or CRITICAL (default INFO)",
    )
    parser.add_argument("--version", action="version", version=f"sim-server {__version__}")
    return parser


def _add_simulator_arguments(group: argparse._ArgumentGroup) -> None:
    group.add_argument(
        "--backend",
        choices=BACKENDS,
        default="sumo",
        help="simulator: sumo (libsumo, in-process), sumo-traci (SUMO over its TraCI socket), "
        "highway (highway-env), fake (kinematic toy for tests) or replay (a recording, "
        "--recording)",
    )
    group.add_argument(
        "--recording",
        type=Path,
        metavar="DIR",
        help="with --backend replay: the folder `agent-client drive/evaluate --record` wrote "
        "(docs/recording.md)",
    )
    group.add_argument(
        "--gui",
        action="store_true",
        help="with --backend sumo-traci: run sumo-gui instead of sumo, to watch the ego "
        "(needs a display); the view follows the ego, painted red",
    )
    group.add_argument(
        "--gui-delay",
        type=float,
        metavar="MS",
        help="with --gui: wall-clock ms per simulation step of an episode (default "
        f"{DEFAULT_DELAY_MS:g}: real time at 0.1 s steps; 0 as fast as it goes)",
    )
    group.add_argument(
        "--gui-span",
        type=float,
        metavar="M",
        help=f"with --gui: metres of road across the window, around the ego (default "
        f"{DEFAULT_SPAN_M:g})",
    )
    group.add_argument(
        "--screenshots",
        type=Path,
        metavar="DIR",
        help="with --gui: save each episode's steps as PNGs in DIR/episode-NNNN/ and, once it "
        "is over, DIR/episode-NNNN.gif",
    )
    group.add_argument(
        "--screenshot-every",
        type=int,
        metavar="N",
        help="with --screenshots: every N-th step only (default 1)",
    )
    group.add_argument(
        "--traci-port",
        type=int,
        help="with --backend sumo-traci: attach to a SUMO that another tool started with "
        "--remote-port PORT on this machine, instead of starting one",
    )
    group.add_argument(
        "--sumocfg",
        type=Path,
        help="offer your own SUMO scenario (.sumocfg) in addition to the built-in ones",
    )
    group.add_argument(
        "--ego-route",
        help="with --sumocfg: the route id (in your route files) the ego drives, or random (a "
        "trip over the network drawn per seed)",
    )
    group.add_argument(
        "--net",
        type=Path,
        metavar="FILE",
        help="offer your own SUMO network (.net.xml[.gz]) as a scenario: seeded traffic and "
        "an ego trip drawn per reset (docs/maps.md)",
    )
    group.add_argument(
        "--osm",
        type=Path,
        metavar="FILE",
        help="offer an OpenStreetMap export (.osm[.xml|.gz]) as a scenario: netconvert builds "
        "its network once (cached), then as --net (docs/maps.md)",
    )
    group.add_argument(
        "--scenario-name",
        help="name clients use for --sumocfg, --net or --osm (default: the file's name "
        "without its extensions)",
    )
    group.add_argument(
        "--cache-dir", type=Path, help="where built scenario files go (default ~/.cache/av-bridge)"
    )


def _add_connection_arguments(group: argparse._ArgumentGroup) -> None:
    group.add_argument(
        "--session-timeout",
        type=float,
        default=DEFAULT_SESSION_TIMEOUT_S,
        help="seconds of silence after which another client may take over one that is still "
        "connected (default %(default)g; a disconnected or frozen client is released at once)",
    )
    group.add_argument(
        "--heartbeat-timeout",
        type=float,
        default=HEARTBEAT_TIMEOUT_MS / 1000,
        help="seconds without any sign of life (ZeroMQ heartbeats are answered even during a "
        "long gradient update) after which a client counts as gone (default %(default)g)",
    )
    group.add_argument(
        "--max-frame-bytes",
        type=int,
        default=DEFAULT_MAX_FRAME_BYTES,
        help=f"largest request accepted (default {DEFAULT_MAX_FRAME_BYTES})",
    )
    group.add_argument(
        "--spin-us",
        type=float,
        help="direct:// only: microseconds to busy-wait for the next request before blocking "
        f"(default {DEFAULT_SPIN_US}; 0 never spins: less CPU, higher latency)",
    )


def _add_security_arguments(group: argparse._ArgumentGroup) -> None:
    group.add_argument(
        "--secret-key",
        type=Path,
        default=os.environ.get(SECRET_KEY_ENV) or None,
        help="the server's secret key file (server.key_secret from `sim-server keygen`); "
        f"turns on authentication and encryption (env {SECRET_KEY_ENV})",
    )
    group.add_argument(
        "--authorized-keys",
        type=Path,
        default=os.environ.get(AUTHORIZED_KEYS_ENV) or None,
        help="directory of the client public keys (*.key) allowed in "
        f"(default: the directory of --secret-key; env {AUTHORIZED_KEYS_ENV})",
    )
    group.add_argument(
        "--insecure",
        action="store_true",
        help="allow binding a non-loopback address without authentication",
    )


def _add_process_arguments(group: argparse._ArgumentGroup) -> None:
    group.add_argument(
        "--pool",
        type=int,
        default=1,
        help="serve up to N clients at once on the one --bind address, each on a simulator "
        "process of its own (started and restarted by this one; a client that finds all N "
        "busy is told so); over tcp:// and ipc:// (default 1: this process simulates)",
    )
    group.add_argument(
        "--workers",
        type=int,
        default=1,
        help="run N servers (one simulation each) on consecutive ports from --bind (port 0: free "
        "ports), print one readiness line per worker, restart any that dies (default 1; "
        "--pool serves as many on one address)",
    )
    group.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop when the process that started this server exits, even by SIGKILL (the "
        "--workers supervisor starts its workers so: none outlives it)",
    )
    group.add_argument(
        "--idle-priority",
        action="store_true",
        help="run in the kernel's idle scheduling class (Linux SCHED_IDLE; its workers too): "
        "the server gets only CPU time nothing else wants, for evaluation servers beside "
        "training (docs/learner.md)",
    )


def build_keygen_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="sim-server keygen",
        description="Write CURVE key pairs: server.key(_secret) and client.key(_secret). Give the "
        "server server.key_secret (and the directory of client .key files), give each learner "
        "server.key and client.key_secret.",
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for the key files")
    return parser


def keygen(argv: list[str]) -> int:
    args = build_keygen_parser().parse_args(argv)
    try:
        written = generate_keys(args.out)
    except (FileExistsError, OSError) as exc:
        print(f"sim-server keygen: {exc}", file=sys.stderr)
        return 1
    for path in written:
        print(path)
    return 0


# --------------------------------------------------------------------------- usage checks


def check_usage(args: argparse.Namespace) -> tuple[Endpoint, ServerCredentials | None]:
    """The address to bind and the CURVE credentials; `UsageError` if the command line cannot
    be served as given."""
    endpoint = _endpoint(args)
    credentials = load_credentials(args)
    _check_exposure(endpoint, credentials, args)
    _check_simulator(args)
    _check_numbers(args)
    return endpoint, credentials


def _endpoint(args: argparse.Namespace) -> Endpoint:
    try:
        endpoint = parse_endpoint(args.bind)
    except ValueError as exc:
        raise UsageError(f"--bind {exc}") from exc
    if endpoint.scheme != "direct" and args.spin_us is not None:
        raise UsageError(f"--spin-us applies to direct:// addresses only, not --bind {args.bind}")
    return endpoint


def load_credentials(args: argparse.Namespace) -> ServerCredentials | None:
    """CURVE credentials from --secret-key / --authorized-keys, or None."""
    if args.secret_key is None:
        if args.authorized_keys is not None:
            raise UsageError(f"--authorized-keys {args.authorized_keys} needs --secret-key")
        return None
    try:
        keys = load_key_pair(args.secret_key)
    except ValueError as exc:
        raise UsageError(f"--secret-key: {exc}") from exc
    authorized = args.authorized_keys or args.secret_key.parent
    if not authorized.is_dir() or not any(authorized.glob("*.key")):
        raise UsageError(f"--authorized-keys {authorized}: no directory of client *.key files")
    return ServerCredentials(keys, authorized)


def _check_exposure(
    endpoint: Endpoint, credentials: ServerCredentials | None, args: argparse.Namespace
) -> None:
    """Only loopback addresses without authentication (unless --insecure); direct:// never
    leaves the machine."""
    if endpoint.scheme == "direct":
        if credentials is not None:
            raise UsageError("--secret-key: direct:// has no CURVE: use tcp:// with --secret-key")
        if not endpoint.is_loopback:
            raise UsageError(
                f"--bind {args.bind}: direct:// binds loopback addresses only (no "
                "authentication); use tcp:// with --secret-key across machines"
            )
    if not endpoint.is_loopback and credentials is None and not args.insecure:
        raise UsageError(
            f"--bind {args.bind} is reachable from other machines: turn on authentication with "
            "--secret-key (keys from `sim-server keygen`), bind a loopback address, or pass "
            "--insecure on a trusted network"
        )


def _check_simulator(args: argparse.Namespace) -> None:
    """The simulator options fit --backend."""
    _check_recording(args)
    for given, name in ((args.gui, "--gui"), (args.traci_port is not None, "--traci-port")):
        if given and args.backend != "sumo-traci":
            raise UsageError(f"{name} needs --backend sumo-traci, not --backend {args.backend}")
    if args.traci_port is not None and not 1 <= args.traci_port <= 65535:
        raise UsageError(f"--traci-port {args.traci_port}: expected a port in 1..65535")
    _check_gui(args)
    _check_map(args)


def _check_map(args: argparse.Namespace) -> None:
    """At most one of --sumocfg, --net and --osm, an existing file, a SUMO backend; the
    options that go with them."""
    given = [
        (f"--{flag}", path) for flag in ("sumocfg", "net", "osm") if (path := getattr(args, flag))
    ]
    if args.ego_route is not None and args.sumocfg is None:
        raise UsageError(
            f"--ego-route {args.ego_route}: applies to --sumocfg only (on --net and --osm the "
            "ego's trip is drawn per seed, or set with --option ego_from=EDGE --option ego_to=EDGE)"
        )
    if not given:
        if args.scenario_name is not None:
            raise UsageError(
                f"--scenario-name {args.scenario_name}: applies to --sumocfg, --net or --osm only"
            )
        return
    if len(given) > 1:
        raise UsageError(f"{given[0][0]} and {given[1][0]}: give one map per server")
    flag, path = given[0]
    if not args.backend.startswith("sumo"):
        raise UsageError(f"{flag} needs a SUMO backend (sumo, sumo-traci), not {args.backend}")
    if not path.is_file():
        raise UsageError(f"{flag} {path}: no such file")
    if flag == "--sumocfg" and not args.ego_route:
        raise UsageError(
            "--sumocfg needs --ego-route (a route id defined in your route files, or random)"
        )


def _check_gui(args: argparse.Namespace) -> None:
    """The view's options come with --gui and are in range; the --screenshots folder is made
    here, so that a path that cannot be one fails before anything starts."""
    given = (
        ("--gui-delay", args.gui_delay),
        ("--gui-span", args.gui_span),
        ("--screenshots", args.screenshots),
        ("--screenshot-every", args.screenshot_every),
    )
    for name, value in given:
        if value is not None and not args.gui:
            raise UsageError(f"{name} needs --gui (with --backend sumo-traci)")
    if args.screenshot_every is not None and args.screenshots is None:
        raise UsageError(f"--screenshot-every {args.screenshot_every}: needs --screenshots DIR")
    if args.gui_delay is not None and not 0 <= args.gui_delay < math.inf:
        raise UsageError(f"--gui-delay {args.gui_delay:g}: must be >= 0 ms")
    if args.gui_span is not None and not 0 < args.gui_span < math.inf:
        raise UsageError(f"--gui-span {args.gui_span:g}: must be > 0 m")
    if args.screenshot_every is not None and args.screenshot_every < 1:
        raise UsageError(f"--screenshot-every {args.screenshot_every}: must be at least 1")
    if args.screenshots is not None:
        try:
            args.screenshots.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UsageError(f"--screenshots {args.screenshots}: {exc.strerror or exc}") from exc


def _gui_view(args: argparse.Namespace) -> GuiView:
    """The sumo-gui view the GUI options describe (defaults for those not given)."""
    return GuiView(
        delay_ms=DEFAULT_DELAY_MS if args.gui_delay is None else args.gui_delay,
        span_m=DEFAULT_SPAN_M if args.gui_span is None else args.gui_span,
        screenshots=None if args.screenshots is None else args.screenshots.resolve(),
        screenshot_every=1 if args.screenshot_every is None else args.screenshot_every,
    )


def _check_recording(args: argparse.Namespace) -> None:
    """--backend replay and --recording go together, and the folder exists."""
    if args.recording is None:
        if args.backend == "replay":
            raise UsageError("--backend replay needs --recording DIR (a recording folder)")
        return
    if args.backend != "replay":
        raise UsageError(f"--recording needs --backend replay, not --backend {args.backend}")
    if not args.recording.is_dir():
        raise UsageError(f"--recording {args.recording}: no such folder")


def _check_numbers(args: argparse.Namespace) -> None:
    if args.workers < 1:
        raise UsageError(f"--workers {args.workers}: must be at least 1")
    if args.pool < 1:
        raise UsageError(f"--pool {args.pool}: must be at least 1")
    if args.pool > 1 and args.workers > 1:
        raise UsageError("--pool and --workers: choose one (a pool serves N on one address)")
    if args.pool > 1 and (args.traci_port is not None or args.gui):
        raise UsageError(
            f"--pool {args.pool}: each simulator of a pool runs SUMO of its own; --traci-port "
            "and --gui attach one"
        )
    if args.pool > 1 and args.bind.startswith("direct://"):
        raise UsageError(
            f"--pool {args.pool}: a pool serves over tcp:// or ipc:// (ZeroMQ); over direct:// "
            "run --workers N (one address each)"
        )
    if args.max_frame_bytes < 1:
        raise UsageError(f"--max-frame-bytes {args.max_frame_bytes}: must be at least 1")
    if not args.heartbeat_timeout > 0:
        raise UsageError(f"--heartbeat-timeout {args.heartbeat_timeout:g}: must be > 0 s")
    if not args.session_timeout >= 0:
        raise UsageError(f"--session-timeout {args.session_timeout:g}: must be >= 0 s")


# --------------------------------------------------------------------------- the backend


def make_backend(args: argparse.Namespace) -> Backend:
    """The backend --backend names; `UsageError` if it cannot be started as asked."""
    try:
        return _backend(args)
    except ModuleNotFoundError as exc:
        provider = _PROVIDERS.get((exc.name or "").partition(".")[0])
        if provider is None:
            raise
        package, extra = provider
        raise UsageError(
            f"--backend {args.backend} needs {package}, which is not installed: "
            f"pip install -e '.[{extra}]'"
        ) from exc
    except (ValueError, FileNotFoundError) as exc:  # SumoBackend's refusals, no sumo binary
        raise UsageError(f"--backend {args.backend}: {exc}") from exc


def _backend(args: argparse.Namespace) -> Backend:
    if args.backend == "fake":
        from sim_server.backends.fake import FakeBackend

        return FakeBackend()
    if args.backend == "highway":
        from sim_server.backends.highway import HighwayBackend

        return HighwayBackend()
    if args.backend == "replay":
        from protocol.recording import RecordingError
        from sim_server.backends.replay import ReplayBackend

        try:
            return ReplayBackend(args.recording)
        except RecordingError as exc:  # its message starts with the file or folder at fault
            raise UsageError(f"--recording {exc}") from exc
    from sim_server.backends.sumo.backend import SumoBackend

    custom = user_scenarios(args)
    if args.backend == "sumo-traci":
        return SumoBackend(
            cache_dir=args.cache_dir,
            custom=custom,
            traci=True,
            gui=args.gui,
            traci_port=args.traci_port,
            view=_gui_view(args) if args.gui else None,
        )
    return SumoBackend(cache_dir=args.cache_dir, custom=custom)


def user_scenarios(args: argparse.Namespace) -> tuple[Any, ...]:
    """The user's own scenario (--sumocfg, --net, --osm), built where it needs building (an OSM
    export's network, once, into the cache); `UsageError` if it cannot be."""
    from sim_server.backends.sumo.maps import MapNetwork, MapScenario, build_osm, map_name
    from sim_server.backends.sumo.scenarios import CustomScenario, default_cache_dir

    if args.sumocfg is not None:
        name = args.scenario_name or args.sumocfg.stem
        return (CustomScenario(name, args.sumocfg.resolve(), args.ego_route),)
    path, flag = (args.osm, "--osm") if args.osm is not None else (args.net, "--net")
    if path is None:
        return ()
    cache = args.cache_dir or default_cache_dir()
    log = logging.getLogger("sim_server")
    try:
        net_file = build_osm(path, cache, log.info) if flag == "--osm" else path
        network = MapNetwork.of(net_file, cache)
    except (OSError, RuntimeError, ValueError, ElementTree.ParseError) as exc:
        raise UsageError(f"{flag} {path}: {exc}") from exc
    name = args.scenario_name or map_name(path)
    graph = network.graph
    description = (
        f"your map {path.name}: {len(graph.roads)} roads, {graph.lane_km(list(graph.roads)):.0f} "
        f"lane-km, {graph.traffic_lights} signalised junctions; seeded traffic and ego trips"
    )
    return (MapScenario(name, description, network),)


# --------------------------------------------------------------------------- running


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["keygen"]:
        return keygen(argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=args.log_level, format="%(asctime)s sim-server %(levelname)s %(message)s"
    )
    try:
        endpoint, credentials = check_usage(args)
        if args.idle_priority:
            set_idle_priority()
        if args.backend.startswith("sumo") and (args.osm is not None or args.net is not None):
            user_scenarios(args)  # built (and cached) once, before any worker starts
        if args.workers > 1:
            return _run_workers(argv, args)
        if args.pool > 1:
            return _run_pool(argv, args, credentials)
        backend = make_backend(args)
    except UsageError as exc:
        message = " ".join(str(exc).splitlines())
        print(f"sim-server: error: {message}", file=sys.stderr)
        return USAGE_STATUS
    return serve(args, endpoint, credentials, backend)


def _run_workers(argv: list[str], args: argparse.Namespace) -> int:
    from sim_server.serve.workers import run_workers, worker_addresses

    try:
        addresses = worker_addresses(args.bind, args.workers)
    except ValueError as exc:
        raise UsageError(f"--workers {args.workers}: {exc}") from exc
    return run_workers(argv, addresses)


def _run_pool(
    argv: list[str], args: argparse.Namespace, credentials: ServerCredentials | None
) -> int:
    from sim_server.serve.pool import run_pool

    private = (SECRET_KEY_ENV, AUTHORIZED_KEYS_ENV)  # the simulators serve the front over ipc
    return run_pool(
        argv, args.pool, credentials, bind=args.bind, heartbeat_timeout_s=args.heartbeat_timeout,
        session_timeout_s=args.session_timeout, max_frame_bytes=args.max_frame_bytes,
        exit_with_parent=args.exit_with_parent,
        env={k: v for k, v in os.environ.items() if k not in private},
    )  # fmt: skip


def serve(
    args: argparse.Namespace,
    endpoint: Endpoint,
    credentials: ServerCredentials | None,
    backend: Backend,
) -> int:
    """Bind, print the readiness line and serve until SIGTERM or SIGINT; 1 if it cannot bind."""
    session = Session(backend, args.max_frame_bytes, args.session_timeout)
    try:
        server: Server | DirectServer = (
            DirectServer(session, args.bind, _spin_us(args))
            if endpoint.scheme == "direct"
            else Server(session, args.bind, credentials, args.heartbeat_timeout)
        )
    except Exception as exc:  # zmq.ZMQError and OS errors: report and exit cleanly
        backend.close()
        print(f"sim-server: cannot bind {args.bind}: {exc}", file=sys.stderr)
        return 1

    def on_signal(signum: int, frame: FrameType | None) -> None:
        server.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    if args.exit_with_parent:
        stop_with_parent(server)
    print(format_listening(server.endpoint), flush=True)
    log = logging.getLogger("sim_server")
    log.info(
        "backend %s %s, scenarios: %s; %s",
        backend.name,
        backend.version,
        ", ".join(s.name for s in backend.scenarios()),
        f"CURVE on, client keys from {credentials.authorized_keys}"
        if credentials is not None
        else "no authentication",
    )
    server.serve()
    log.info("stopped")
    return 0


def set_idle_priority() -> None:
    """Move this process (and what it starts later) to the idle scheduling class; `UsageError`
    where the platform has none."""
    if not hasattr(os, "SCHED_IDLE"):
        raise UsageError("--idle-priority needs Linux's SCHED_IDLE scheduling class")
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def _spin_us(args: argparse.Namespace) -> float:
    return DEFAULT_SPIN_US if args.spin_us is None else max(0.0, args.spin_us)


if __name__ == "__main__":
    sys.exit(main())
