"""``agent-client check``: run the protocol conformance kit against a server (docs/conformance.md).

Exit status: 0 when every check passes (warnings allowed), 1 when one fails, 2 when the server
cannot be tested (unreachable, busy with another client, bad address or scenario).
"""

from __future__ import annotations

import argparse
import json
import sys

from agent_client.cli.common import Commands
from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from protocol.transport.endpoint import DEFAULT_ADDRESS


def add_parser(commands: Commands) -> None:
    """Register the ``check`` subcommand."""
    check = commands.add_parser(
        "check",
        help="run the protocol conformance checks against a server",
        description="Probe a bridge server (ours or one for another simulator) with raw frames "
        "and report, check by check, whether it follows docs/protocol.md. Exit 0: conforms, "
        "1: a check failed, 2: the server could not be tested.",
    )
    check.add_argument(
        "--server", default=DEFAULT_ADDRESS, help=f"server address (default {DEFAULT_ADDRESS})"
    )
    check.add_argument("--scenario", help="scenario to test (default: the first one offered)")
    check.add_argument(
        "--timeout",
        type=float,
        default=STEP_TIMEOUT_S,
        help=f"seconds to wait for each reply (default {STEP_TIMEOUT_S:g}; resets get "
        "--reset-timeout)",
    )
    check.add_argument(
        "--reset-timeout",
        type=float,
        default=RESET_TIMEOUT_S,
        help=f"seconds to wait for a reset reply (default {RESET_TIMEOUT_S:g})",
    )
    check.add_argument("--json", action="store_true", help="print one JSON object, no table")
    check.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the kit; print a table (or JSON) and return the exit status."""
    from agent_client.conformance.checks import ServerUnreachable, run_checks

    try:
        report = run_checks(args.server, args.scenario, args.timeout, args.reset_timeout)
    except (ServerUnreachable, ValueError) as exc:
        if args.json:
            print(json.dumps({"server": args.server, "ok": False, "error": str(exc)}))
        print(f"agent-client check: {exc}", file=sys.stderr)
        return 2
    print(report.to_json() if args.json else report.format_table(), flush=True)
    return report.exit_code
