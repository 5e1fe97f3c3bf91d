"""``agent-client evaluate``: compare a policy with a baseline on the same seeds; write a report.

Heavy imports (torch, matplotlib) happen inside `run`, so that ``agent-client --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path
from typing import Any

from agent_client.cli.common import (
    Commands,
    add_connection_arguments,
    add_record_argument,
    check_record_folder,
    existing_folder,
    open_recorder,
)
from agent_client.defaults import DEFAULT_SCENARIO, EVALUATION_SEED


def add_parser(commands: Commands) -> None:
    evaluate = commands.add_parser(
        "evaluate",
        help="compare a policy with a baseline on the same seeds; write a report",
        description="Drive a policy and a baseline over the same seeds and write report.md, "
        "metrics.json and the figures of the paper's §4.4-4.5. Details: docs/evaluation.md.",
    )
    add_connection_arguments(evaluate)
    evaluate.add_argument(
        "--policy",
        required=True,
        help="runs/NAME/policy.pt, idm, idm+mobil, sumo or idm:PARAMS.json",
    )
    evaluate.add_argument(
        "--baseline",
        default="idm",
        help="idm (default), idm+mobil (lane changes: on roads with a lane end or an exit), "
        "idm:PARAMS.json, sumo or a policy file",
    )
    evaluate.add_argument(
        "--reference",
        help="a second baseline on the same seeds, e.g. sumo (the simulator's own driver)",
    )
    evaluate.add_argument("--episodes", type=int, default=10, help="episodes per driver (10)")
    evaluate.add_argument(
        "--seed",
        type=int,
        default=EVALUATION_SEED,
        help=f"seed of the first episode (default {EVALUATION_SEED})",
    )
    evaluate.add_argument(
        "--out", type=Path, help="report folder (default: next to the policy, eval/)"
    )
    evaluate.add_argument(
        "--run",
        type=Path,
        dest="run_folder",
        metavar="RUN",
        help="training run folder: Table 2 from its episodes.csv (cflc)",
    )
    evaluate.add_argument(
        "--cf-policy", help="a car-following-only policy to compare with (cflc, Fig. 13)"
    )
    evaluate.add_argument(
        "--table2-bins", type=int, default=10, help="ranges of training episodes (default 10)"
    )
    evaluate.add_argument(
        "--trajectory-seeds",
        type=int,
        nargs="+",
        metavar="SEED",
        help="evaluated seeds whose episodes the report draws (time-space diagrams, time "
        "series); default: the first seed and the policy's most critical episode",
    )
    add_record_argument(evaluate)
    evaluate.set_defaults(run=run)


def evaluation_command(args: argparse.Namespace, scenario: str, out: Path) -> str:
    """The command line that reruns this evaluation."""
    parts = ["agent-client", "evaluate", "--server", args.server, "--scenario", scenario]
    for name, value in args.option:
        parts += [
            "--option",
            f"{name}={json.dumps(value) if not isinstance(value, str) else value}",
        ]
    parts += ["--policy", args.policy, "--baseline", args.baseline]
    if args.reference is not None:
        parts += ["--reference", args.reference]
    parts += ["--episodes", str(args.episodes), "--seed", str(args.seed), "--out", str(out)]
    if args.run_folder is not None:
        parts += ["--run", str(args.run_folder), "--table2-bins", str(args.table2_bins)]
    if args.cf_policy is not None:
        parts += ["--cf-policy", args.cf_policy]
    if args.trajectory_seeds is not None:
        parts += ["--trajectory-seeds", *map(str, args.trajectory_seeds)]
    return shlex.join(parts)


def default_out(policy: str) -> Path:
    """``runs/NAME/eval`` next to a policy file; ``runs/eval-MODEL`` for the model drivers
    (``runs/eval-idm``, ``runs/eval-idm+mobil``, ``runs/eval-sumo``) and
    ``runs/eval-pretrained-NAME`` for a shipped policy."""
    from agent_client.drivers.spec import is_model

    if is_model(policy):
        return Path("runs") / f"eval-{policy.split(':')[0]}"
    if policy.startswith("pretrained:"):  # not into the package's folder
        return Path("runs") / f"eval-{policy.replace(':', '-')}"
    return Path(policy).parent / "eval"


def run(args: argparse.Namespace) -> int:
    from agent_client.drivers.spec import load_driver, trained_on, training_settings
    from agent_client.envs.remote_env import RemoteEnv
    from agent_client.errors import UsageError
    from agent_client.evaluation.report import check_trajectory_seeds, write_report
    from agent_client.training.run_log import EPISODE_CSV, read_rows

    trained_scenario, trained_options = training_settings(args.policy)
    if args.scenario is None and isinstance(trained_scenario, list):
        raise UsageError(
            f"{args.policy} was trained on {', '.join(trained_scenario)}: evaluate it on one "
            "at a time (--scenario NAME), each with its own report"
        )
    scenario = args.scenario or trained_scenario or DEFAULT_SCENARIO
    assert isinstance(scenario, str)
    defaults = trained_options if trained_on(trained_scenario, scenario) else {}
    options = {**defaults, **dict(args.option)}
    if defaults:
        print(f"the policy was trained with {defaults}: evaluating with them (--option overrides)")
    args.option = sorted(options.items())  # the rerun command names them explicitly
    out = args.out if args.out is not None else default_out(args.policy)
    seeds = list(range(args.seed, args.seed + args.episodes))
    if args.trajectory_seeds is not None:
        check_trajectory_seeds(args.trajectory_seeds, seeds)
    specs = {"policy": args.policy, "baseline": args.baseline}
    if args.reference is not None:
        specs["reference"] = args.reference
    if args.cf_policy is not None:
        specs["cf_policy"] = args.cf_policy
    check_record_folder(args.record)
    drivers = {role: load_driver(spec) for role, spec in specs.items()}
    training_rows = None
    if args.run_folder is not None:
        training_rows = read_rows(existing_folder(args.run_folder, "--run") / EPISODE_CSV)
    wire = open_recorder(args, scenario=scenario, options=options, seeds=seeds, drivers=specs)
    try:
        env = RemoteEnv(
            args.server,
            scenario,
            timeout_s=args.timeout,
            reset_timeout_s=args.reset_timeout,
            recorder=wire,
            **options,
        )
        try:
            runs = _drive_all(env, drivers, specs, seeds)
            welcome, options = env.welcome, dict(env.options)
        finally:
            env.close()
    finally:
        if wire is not None:
            wire.close()
    evaluation = _evaluation(args, scenario, seeds, options, welcome, runs, out, training_rows)
    path = write_report(out, evaluation, args.trajectory_seeds)
    _print_comparison(json.loads((out / "metrics.json").read_text()))
    print(f"report: {path} (metrics.json and figures in {out})")
    return 0


def _drive_all(
    env: Any, drivers: dict[str, Any], specs: dict[str, str], seeds: list[int]
) -> dict[str, Any]:
    """Every driver over the same seeds, with a progress line per episode."""
    from agent_client.evaluation.evaluate import DriverRun, EpisodeRecord, evaluate_driver
    from agent_client.evaluation.metrics import format_summary

    runs: dict[str, DriverRun] = {}
    for role, driver in drivers.items():
        count = 0

        def progress(record: EpisodeRecord, role: str = role) -> None:
            nonlocal count
            count += 1
            print(f"[{role} {count}/{len(seeds)}] {format_summary(record.summary)}", flush=True)

        runs[role] = DriverRun(specs[role], evaluate_driver(env, driver, seeds, progress))
    return runs


def _evaluation(
    args: argparse.Namespace,
    scenario: str,
    seeds: list[int],
    options: dict[str, Any],
    welcome: Any,
    runs: dict[str, Any],
    out: Path,
    training_rows: list[dict[str, str]] | None,
) -> Any:
    from agent_client import __version__
    from agent_client.evaluation.evaluate import Evaluation
    from protocol.version import PROTOCOL_VERSION, format_version

    return Evaluation(
        scenario=scenario,
        seeds=seeds,
        options=options,
        versions={
            "server": welcome.server,
            "backend": welcome.backend,
            "backend version": welcome.backend_version,
            "agent_client version": __version__,
            "protocol version (client / server)": f"{format_version(PROTOCOL_VERSION)} / "
            f"{format_version(welcome.protocol)}",
        },
        command=evaluation_command(args, scenario, out),
        policy=runs["policy"],
        baseline=runs["baseline"],
        cf_policy=runs.get("cf_policy"),
        reference=runs.get("reference"),
        training_rows=training_rows,
        run_folder=str(args.run_folder) if args.run_folder is not None else None,
        table2_bins=args.table2_bins,
    )


def _print_comparison(metrics: dict[str, Any]) -> None:
    policy, baseline = metrics["drivers"]["policy"], metrics["drivers"]["baseline"]
    ratio = metrics["comparison"]["speed_ratio_policy_to_baseline"]
    ratio_text = f"{ratio:.3f}x" if ratio is not None else "n/a"
    print(
        f"policy {policy['average_speed']:.2f} m/s vs baseline {baseline['average_speed']:.2f} "
        f"m/s ({ratio_text}) | collisions/episode {policy['collisions_per_episode']:.2f} vs "
        f"{baseline['collisions_per_episode']:.2f}"
    )
    routes = {r: d["route"] for r, d in metrics["drivers"].items() if d.get("route")}
    if routes:
        print(
            "reached the end of the route: "
            + ", ".join(
                f"{role} {100 * route['arrival_share']:.0f}%" for role, route in routes.items()
            )
        )
