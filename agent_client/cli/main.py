"""The ``agent-client`` program: one sub-command per module, errors as one line.

Exit status: 0 done, 1 a conformance check failed (``check``), 2 a usage error (one line that
names the bad value and the valid ones) or a failure of the server or the wire, 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading

from agent_client import __version__
from agent_client.cli import calibrate, check, drive, evaluate, export, report, train
from agent_client.cli.common import add_key_arguments, use_keys
from agent_client.errors import BridgeError

COMMANDS = (drive, train, calibrate, evaluate, report, check, export)
INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as a shell reports it."""
EXIT_GRACE_S = 2.0
"""Seconds the interpreter's own shutdown may take after Ctrl-C before the process leaves
anyway: closing what a command held (sockets to a server that never answers, child processes)
must not keep a user who pressed Ctrl-C waiting, however loaded the machine."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="agent-client", description="Learner side of the SUMO/DRL co-simulation bridge."
    )
    parser.add_argument("--version", action="version", version=f"agent-client {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(commands)
    for subcommand in commands.choices.values():
        add_key_arguments(subcommand)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        use_keys(args)
        return int(args.run(args))
    except BridgeError as exc:  # UsageError included: the message names the bad value
        print(f"agent-client: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        leave_soon(INTERRUPTED)
        return INTERRUPTED


def leave_soon(status: int) -> None:
    """Exit with `status` after `EXIT_GRACE_S` if the normal shutdown has not ended by then."""
    sys.stdout.flush()
    sys.stderr.flush()
    timer = threading.Timer(EXIT_GRACE_S, os._exit, (status,))
    timer.daemon = True
    timer.start()


if __name__ == "__main__":
    sys.exit(main())
