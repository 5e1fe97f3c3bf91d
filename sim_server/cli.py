"""``sim-server``: run a simulator behind the bridge protocol.

Prints ``listening on ADDRESS`` on stdout once it accepts requests; logs go to stderr.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from types import FrameType

from protocol.codec import DEFAULT_MAX_FRAME_BYTES
from protocol.transport import DEFAULT_ADDRESS, parse_endpoint
from sim_server import __version__
from sim_server.backend import Backend
from sim_server.server import Server, Session, format_listening

BACKENDS = ("sumo", "fake")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sim-server",
        description="Serve a traffic simulator to a learner over the bridge protocol (ZeroMQ).",
    )
    parser.add_argument(
        "--bind",
        default=DEFAULT_ADDRESS,
        help="address to listen on: tcp://HOST:PORT (port 0 picks a free port) or ipc://PATH "
        f"(default {DEFAULT_ADDRESS})",
    )
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="sumo",
        help="simulator: sumo (libsumo, in-process) or fake (kinematic toy for tests)",
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
        default=60.0,
        help="seconds of silence after which another client may take over (default 60)",
    )
    parser.add_argument(
        "--max-frame-bytes",
        type=int,
        default=DEFAULT_MAX_FRAME_BYTES,
        help=f"largest request accepted (default {DEFAULT_MAX_FRAME_BYTES})",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="allow binding a non-loopback address without authentication",
    )
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING (default INFO)")
    parser.add_argument("--version", action="version", version=f"sim-server {__version__}")
    return parser


def make_backend(args: argparse.Namespace) -> Backend:
    if args.backend == "fake":
        from sim_server.fake_backend import FakeBackend

        return FakeBackend()
    from sim_server.scenarios import CustomScenario
    from sim_server.sumo_backend import SumoBackend

    custom: tuple[CustomScenario, ...] = ()
    if args.sumocfg is not None:
        name = args.scenario_name or args.sumocfg.stem
        custom = (CustomScenario(name, args.sumocfg.resolve(), args.ego_route),)
    return SumoBackend(cache_dir=args.cache_dir, custom=custom)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s sim-server %(levelname)s %(message)s"
    )
    try:
        endpoint = parse_endpoint(args.bind)
    except ValueError as exc:
        parser.error(str(exc))
    if not endpoint.is_loopback and not args.insecure:
        parser.error(
            f"{args.bind} is reachable from other machines and this server has no "
            "authentication: bind a loopback address, or pass --insecure on a trusted network"
        )
    if args.sumocfg is not None:
        if not args.sumocfg.is_file():
            parser.error(f"--sumocfg {args.sumocfg}: no such file")
        if not args.ego_route:
            parser.error("--sumocfg needs --ego-route (a route id defined in your route files)")

    backend = make_backend(args)
    session = Session(backend, args.max_frame_bytes, args.session_timeout)
    try:
        server = Server(session, args.bind)
    except Exception as exc:  # zmq.ZMQError and OS errors: report and exit cleanly
        backend.close()
        print(f"sim-server: cannot bind {args.bind}: {exc}", file=sys.stderr)
        return 1

    def on_signal(signum: int, frame: FrameType | None) -> None:
        server.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    print(format_listening(server.endpoint), flush=True)
    logging.getLogger("sim_server").info(
        "backend %s %s, scenarios: %s",
        backend.name,
        backend.version,
        ", ".join(s.name for s in backend.scenarios()),
    )
    server.serve()
    logging.getLogger("sim_server").info("stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
