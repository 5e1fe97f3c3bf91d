"""``sim-server``: run a simulator behind the bridge protocol.

Prints ``listening on ADDRESS`` on stdout once it accepts requests; logs go to stderr.
``sim-server keygen --out DIR`` writes CURVE key pairs for an authenticated server.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from protocol.codec import DEFAULT_MAX_FRAME_BYTES
from protocol.direct import DEFAULT_SPIN_US
from protocol.security import KeyPair, ServerCredentials, generate_keys, load_key_pair
from protocol.transport import DEFAULT_ADDRESS, HEARTBEAT_TIMEOUT_MS, parse_endpoint
from sim_server import __version__
from sim_server.backend import Backend
from sim_server.direct_server import DirectServer
from sim_server.server import (
    DEFAULT_SESSION_TIMEOUT_S,
    Server,
    Session,
    StopFlag,
    format_listening,
)

SECRET_KEY_ENV = "SIM_SERVER_SECRET_KEY"
AUTHORIZED_KEYS_ENV = "SIM_SERVER_AUTHORIZED_KEYS"

BACKENDS = ("sumo", "sumo-traci", "fake", "highway")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="sumo",
        help="simulator: sumo (libsumo, in-process), sumo-traci (SUMO over its TraCI socket), "
        "highway (highway-env) or fake (kinematic toy for tests)",
    )
    parser.add_argument(
        "--gui",
        action="store_true",
        help="with --backend sumo-traci: run sumo-gui instead of sumo, to watch the ego "
        "(needs a display)",
    )
    parser.add_argument(
        "--traci-port",
        type=int,
        help="with --backend sumo-traci: attach to a SUMO that another tool started with "
        "--remote-port PORT on this machine, instead of starting one",
    )
    parser.add_argument(
        "--sumocfg",
        type=Path,
        help="offer your own SUMO scenario (.sumocfg) in addition to the built-in ones",
    )
    parser.add_argument("--ego-route", help="route id (in your route files) the ego drives")
    parser.add_argument(
        "--scenario-name", help="name clients use for --sumocfg (default: the file's stem)"
    )
    parser.add_argument(
        "--cache-dir", type=Path, help="where built scenario files go (default ~/.cache/av-bridge)"
    )
    parser.add_argument(
        "--session-timeout",
        type=float,
        default=DEFAULT_SESSION_TIMEOUT_S,
        help="seconds of silence after which another client may take over one that is still "
        "connected (default %(default)g; a disconnected or frozen client is released at once)",
    )
    parser.add_argument(
        "--heartbeat-timeout",
        type=float,
        default=HEARTBEAT_TIMEOUT_MS / 1000,
        help="seconds without any sign of life (ZeroMQ heartbeats are answered even during a "
        "long gradient update) after which a client counts as gone (default %(default)g)",
    )
    parser.add_argument(
        "--max-frame-bytes",
        type=int,
        default=DEFAULT_MAX_FRAME_BYTES,
        help=f"largest request accepted (default {DEFAULT_MAX_FRAME_BYTES})",
    )
    parser.add_argument(
        "--secret-key",
        type=Path,
        default=os.environ.get(SECRET_KEY_ENV) or None,
        help="CURVE: the server's secret key file (server.key_secret from `sim-server keygen`); "
        f"turns on authentication and encryption (env {SECRET_KEY_ENV})",
    )
    parser.add_argument(
        "--authorized-keys",
        type=Path,
        default=os.environ.get(AUTHORIZED_KEYS_ENV) or None,
        help="CURVE: directory of the client public keys (*.key) allowed in "
        f"(default: the directory of --secret-key; env {AUTHORIZED_KEYS_ENV})",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="allow binding a non-loopback address without authentication",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="run N servers (one simulation each) on consecutive ports from --bind (port 0: free "
        "ports), print one readiness line per worker, restart any that dies (default 1)",
    )
    parser.add_argument(
        "--spin-us",
        type=float,
        help="direct:// only: microseconds to busy-wait for the next request before blocking "
        f"(default {DEFAULT_SPIN_US}; 0 never spins: less CPU, higher latency)",
    )
    parser.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop when the process that started this server exits, even by SIGKILL (the "
        "--workers supervisor starts its workers so: none outlives it)",
    )
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING (default INFO)")
    parser.add_argument("--version", action="version", version=f"sim-server {__version__}")
    return parser


def make_backend(args: argparse.Namespace) -> Backend:
    if args.backend != "sumo-traci" and (args.gui or args.traci_port is not None):
        raise SystemExit("sim-server: --gui and --traci-port need --backend sumo-traci")
    if args.backend == "fake":
        from sim_server.fake_backend import FakeBackend

        return FakeBackend()
    if args.backend == "highway":
        from sim_server.highway_backend import HighwayBackend

        return HighwayBackend()
    from sim_server.scenarios import CustomScenario
    from sim_server.sumo_backend import SumoBackend

    custom: tuple[CustomScenario, ...] = ()
    if args.sumocfg is not None:
        name = args.scenario_name or args.sumocfg.stem
        custom = (CustomScenario(name, args.sumocfg.resolve(), args.ego_route),)
    if args.backend == "sumo-traci":
        try:
            return SumoBackend(
                cache_dir=args.cache_dir,
                custom=custom,
                traci=True,
                gui=args.gui,
                traci_port=args.traci_port,
            )
        except (ValueError, FileNotFoundError) as exc:
            raise SystemExit(f"sim-server: {exc}") from exc
    return SumoBackend(cache_dir=args.cache_dir, custom=custom)


def build_keygen_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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


def load_credentials(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> ServerCredentials | None:
    """CURVE credentials from --secret-key / --authorized-keys, or None; usage errors exit."""
    if args.secret_key is None:
        if args.authorized_keys is not None:
            parser.error("--authorized-keys needs --secret-key")
        return None
    try:
        keys: KeyPair = load_key_pair(args.secret_key)
    except ValueError as exc:
        parser.error(f"--secret-key: {exc}")
    authorized = args.authorized_keys or args.secret_key.parent
    if not authorized.is_dir() or not any(authorized.glob("*.key")):
        parser.error(f"--authorized-keys {authorized}: no directory of client *.key files")
    return ServerCredentials(keys, authorized)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["keygen"]:
        return keygen(argv[1:])
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s sim-server %(levelname)s %(message)s"
    )
    try:
        endpoint = parse_endpoint(args.bind)
    except ValueError as exc:
        parser.error(str(exc))
    credentials = load_credentials(parser, args)
    if endpoint.scheme == "direct":
        if credentials is not None:
            parser.error("direct:// has no CURVE: use tcp:// with --secret-key")
        if not endpoint.is_loopback:
            parser.error(
                f"{args.bind}: direct:// binds loopback addresses only (no authentication); "
                "use tcp:// with --secret-key across machines"
            )
    elif args.spin_us is not None:
        parser.error("--spin-us applies to direct:// addresses only")
    if not endpoint.is_loopback and credentials is None and not args.insecure:
        parser.error(
            f"{args.bind} is reachable from other machines: turn on authentication with "
            "--secret-key (keys from `sim-server keygen`), bind a loopback address, or pass "
            "--insecure on a trusted network"
        )
    if args.sumocfg is not None:
        if not args.backend.startswith("sumo"):
            parser.error(f"--sumocfg needs a SUMO backend, not --backend {args.backend}")
        if not args.sumocfg.is_file():
            parser.error(f"--sumocfg {args.sumocfg}: no such file")
        if not args.ego_route:
            parser.error("--sumocfg needs --ego-route (a route id defined in your route files)")

    if args.workers < 1:
        parser.error("--workers must be at least 1")
    if args.workers > 1:
        from sim_server.workers import run_workers

        return run_workers(argv, args.bind, args.workers)

    backend = make_backend(args)
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
    logging.getLogger("sim_server").info(
        "backend %s %s, scenarios: %s; %s",
        backend.name,
        backend.version,
        ", ".join(s.name for s in backend.scenarios()),
        f"CURVE on, client keys from {credentials.authorized_keys}"
        if credentials is not None
        else "no authentication",
    )
    server.serve()
    logging.getLogger("sim_server").info("stopped")
    return 0


def _spin_us(args: argparse.Namespace) -> float:
    return DEFAULT_SPIN_US if args.spin_us is None else max(0.0, args.spin_us)


def stop_with_parent(server: StopFlag, check_interval_s: float = 0.5) -> None:
    """Stop `server` once this process's parent is gone (the process is re-parented)."""
    parent = os.getppid()

    def watch() -> None:
        while not server.stopping.wait(check_interval_s):
            if os.getppid() != parent:
                logging.getLogger("sim_server").warning("parent %d is gone; stopping", parent)
                server.stop()
                return

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


if __name__ == "__main__":
    sys.exit(main())
