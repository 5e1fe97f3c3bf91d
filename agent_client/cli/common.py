"""What every command shares: the server and scenario options, CURVE keys, option parsing."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.errors import UsageError
from protocol.messages import OptionValue
from protocol.transport.endpoint import DEFAULT_ADDRESS
from protocol.transport.security import CLIENT_SECRET_ENV, SERVER_KEY_ENV, ClientCredentials

if TYPE_CHECKING:
    from agent_client.transport.recording import WireRecorder

Commands = Any
"""The sub-parsers action of argparse (its type is private)."""


def parse_option(text: str) -> tuple[str, OptionValue]:
    """Parse ``NAME=VALUE``; VALUE is read as JSON when it parses (numbers, true), else a string."""
    name, sep, raw = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if not isinstance(value, bool | int | float | str) and value is not None:
        raise argparse.ArgumentTypeError(f"option {name}: value must be a number, bool or string")
    return name, value


def add_connection_arguments(parser: argparse.ArgumentParser, several: bool = False) -> None:
    """--server (repeatable with `several`), --scenario, --option, --timeout and
    --reset-timeout."""
    if several:
        parser.add_argument(
            "--server",
            action="append",
            help="server address; repeat it to step several simulators at once "
            f"(default {DEFAULT_ADDRESS})",
        )
    else:
        parser.add_argument(
            "--server", default=DEFAULT_ADDRESS, help=f"server address (default {DEFAULT_ADDRESS})"
        )
    if several:
        parser.add_argument(
            "--scenario",
            action="append",
            help="scenario name (default cf); repeat it to train one policy on several, each "
            "episode drawing one",
        )
    else:
        parser.add_argument("--scenario", help="scenario name (default cf)")
    parser.add_argument(
        "--option",
        action="append",
        type=parse_option,
        default=[],
        metavar="NAME=VALUE",
        help="scenario option, repeatable (e.g. --option flow=1200 --option decision_interval=1.0)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=STEP_TIMEOUT_S,
        help=f"seconds to wait for a step reply (default {STEP_TIMEOUT_S:g})",
    )
    parser.add_argument(
        "--reset-timeout",
        type=float,
        default=RESET_TIMEOUT_S,
        help="seconds to wait for a reset reply: it builds the network, warms up and inserts "
        f"the ego (default {RESET_TIMEOUT_S:g})",
    )


def add_key_arguments(parser: argparse.ArgumentParser) -> None:
    """CURVE keys of an authenticated server (see `sim-server keygen`)."""
    parser.add_argument(
        "--server-key",
        type=Path,
        default=os.environ.get(SERVER_KEY_ENV) or None,
        help=f"the server's public key file (server.key); env {SERVER_KEY_ENV}",
    )
    parser.add_argument(
        "--secret-key",
        type=Path,
        default=os.environ.get(CLIENT_SECRET_ENV) or None,
        help=f"this learner's secret key file (client.key_secret); env {CLIENT_SECRET_ENV}",
    )


def use_keys(args: argparse.Namespace) -> None:
    """Check the key files and make them the default of every connection of this process."""
    if args.server_key is None and args.secret_key is None:
        return
    if args.server_key is None or args.secret_key is None:
        raise UsageError("--server-key and --secret-key go together")
    try:
        ClientCredentials.from_files(args.server_key, args.secret_key)  # fail early on bad files
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    os.environ[SERVER_KEY_ENV] = str(args.server_key.resolve())
    os.environ[CLIENT_SECRET_ENV] = str(args.secret_key.resolve())


def check_reward(name: str) -> None:
    """A reward name the learner knows, or a `UsageError` listing them."""
    from agent_client.rl.rewards import make_reward

    make_reward(name)


def existing_folder(path: Path, flag: str) -> Path:
    """`path` if it is a folder, else a `UsageError` naming the flag."""
    if not path.is_dir():
        raise UsageError(f"{flag} {path}: no such folder")
    return path


def add_record_argument(parser: argparse.ArgumentParser) -> None:
    """--record DIR: keep the whole wire stream of the command's episodes (docs/recording.md)."""
    parser.add_argument(
        "--record",
        type=Path,
        metavar="DIR",
        help="record every frame sent and received into the new or empty folder DIR "
        "(docs/recording.md); `sim-server --backend replay --recording DIR` serves it back",
    )


def check_record_folder(path: Path | None) -> None:
    """Refuse a --record folder that cannot take a new recording, naming it (`UsageError`)."""
    if path is None:
        return
    if path.exists() and not path.is_dir():
        raise UsageError(f"--record {path}: not a folder")
    if path.is_dir() and any(path.iterdir()):
        raise UsageError(f"--record {path}: the folder is not empty; give a new or empty folder")
    # a new folder is made with its missing parents: the nearest existing one must take it
    where = path if path.is_dir() else next(p for p in path.absolute().parents if p.exists())
    if not where.is_dir() or not os.access(where, os.W_OK | os.X_OK):
        raise UsageError(f"--record {path}: cannot write in {where}")


def open_recorder(args: argparse.Namespace, **about: Any) -> WireRecorder | None:
    """The `WireRecorder` of --record (None without it), its manifest saying what the command
    records (`about`: scenario, options, seeds, drivers) and who records it."""
    if args.record is None:
        return None
    from agent_client import __version__
    from agent_client.transport.recording import WireRecorder

    return WireRecorder(
        args.record,
        command=args.command,
        client=f"agent_client {__version__}",
        server=args.server,
        **about,
    )
