"""``agent-client``: the learner side of the bridge (drive, train)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from agent_client import __version__
from agent_client.connection import BridgeError
from agent_client.features import FeatureMismatch
from protocol.messages import OptionValue
from protocol.security import CLIENT_SECRET_ENV, SERVER_KEY_ENV, ClientCredentials
from protocol.transport import DEFAULT_ADDRESS


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
        "--timeout", type=float, default=10.0, help="seconds to wait for a step reply (default 10)"
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
        raise ValueError("--server-key and --secret-key go together")
    ClientCredentials.from_files(args.server_key, args.secret_key)  # fail early on bad files
    os.environ[SERVER_KEY_ENV] = str(args.server_key.resolve())
    os.environ[CLIENT_SECRET_ENV] = str(args.secret_key.resolve())


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="agent-client", description="Learner side of the SUMO/DRL co-simulation bridge."
    )
    parser.add_argument("--version", action="version", version=f"agent-client {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)

    drive = commands.add_parser(
        "drive", help="drive episodes with a driver (idm or a trained policy) and summarise them"
    )
    add_connection_arguments(drive)
    drive.add_argument(
        "--policy",
        default="idm",
        help="idm, idm:PARAMS.json, or a trained policy file (runs/NAME/policy.pt)",
    )
    drive.add_argument("--episodes", type=int, default=5, help="number of episodes (default 5)")
    drive.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    drive.add_argument("--json", action="store_true", help="print one JSON object per episode")
    drive.add_argument(
        "--reward", default="safe", help="reward reported per episode (default safe)"
    )
    drive.set_defaults(run=run_drive)

    from agent_client.train_cli import add_train_parser

    add_train_parser(commands, add_connection_arguments)

    from agent_client.evaluate_cli import add_evaluate_parsers

    add_evaluate_parsers(commands, add_connection_arguments)

    from agent_client.conformance_cli import add_check_parser

    add_check_parser(commands)
    for subcommand in commands.choices.values():
        add_key_arguments(subcommand)
    return parser


def load_driver(spec: str):  # type: ignore[no-untyped-def]
    """A driver from ``idm``, ``idm:FILE.json`` or a policy file."""
    from agent_client.idm import IDMDriver, IDMParams

    if spec == "idm":
        return IDMDriver()
    if spec.startswith("idm:"):
        params = json.loads(Path(spec[4:]).read_text())
        params = params.get("params", params)
        return IDMDriver(IDMParams(**params))
    from agent_client.policy import load_policy_driver

    return load_policy_driver(Path(spec))


def run_drive(args: argparse.Namespace) -> int:
    from agent_client.drive import aggregate, drive
    from agent_client.metrics import format_summary
    from agent_client.policy import training_settings
    from agent_client.remote_env import RemoteEnv

    driver = load_driver(args.policy)
    trained_scenario, trained_options = training_settings(args.policy)
    args.scenario = args.scenario or trained_scenario or "cf"
    if args.scenario != trained_scenario:
        trained_options = {}
    env = RemoteEnv(
        args.server,
        args.scenario,
        reward=args.reward,
        timeout_s=args.timeout,
        **{**trained_options, **dict(args.option)},
    )
    try:
        summaries = []
        for summary in drive(env, driver, args.episodes, args.seed):
            summaries.append(summary)
            if args.json:
                print(json.dumps(summary.to_dict()), flush=True)
            else:
                print(format_summary(summary), flush=True)
    finally:
        env.close()
    if not args.json:
        totals = aggregate(summaries)
        print(
            f"{args.policy} on {args.scenario}: {len(summaries)} episodes | "
            f"avg speed {totals['average_speed']:.2f} m/s (sd {totals['average_speed_sd']:.2f}), "
            f"{totals['speed_ratio_to_ceiling']:.3f}x the leader-at-entry ceiling | "
            f"collisions/episode {totals['collisions_per_episode']:.2f} | "
            f"jerk>5.6 {100 * totals['jerk_share_above_limit']:.2f}% | "
            f"headway<1s {100 * totals['headway_share_below_1s']:.2f}%"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        use_keys(args)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        return int(args.run(args))
    except (BridgeError, FeatureMismatch) as exc:
        print(f"agent-client: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
