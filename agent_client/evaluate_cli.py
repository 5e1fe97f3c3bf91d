"""``agent-client calibrate-idm`` and ``agent-client evaluate``: command-line fronts.

Heavy imports (scipy, torch, matplotlib) happen inside the run functions, so that
``agent-client --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path
from typing import Any

CALIBRATION_SEED = 300_000
"""First seed of the recorded human episodes (disjoint from training and evaluation seeds)."""
EVALUATION_SEED = 200_000
"""First seed of the evaluation episodes: disjoint from training seeds (0...) and from the
training's greedy evaluations (100000...), which chose ``policy.pt``."""


def add_evaluate_parsers(commands: Any, add_connection_arguments: Any) -> None:
    """Add the ``calibrate-idm`` and ``evaluate`` sub-commands."""
    calibrate = commands.add_parser(
        "calibrate-idm",
        help="fit IDM to human trajectories recorded through the bridge",
        description="Record the scenario's human drivers (reset option ego_driver=sumo) and fit "
        "IDM's six parameters to their gaps. The JSON written is usable as --policy idm:FILE. "
        "Details: docs/evaluation.md.",
    )
    add_connection_arguments(calibrate)
    calibrate.add_argument("--out", type=Path, required=True, help="JSON file to write")
    calibrate.add_argument(
        "--episodes", type=int, default=20, help="human episodes to record (default 20)"
    )
    calibrate.add_argument(
        "--seed",
        type=int,
        default=CALIBRATION_SEED,
        help=f"seed of the first episode and of the optimiser (default {CALIBRATION_SEED})",
    )
    calibrate.add_argument(
        "--maxiter", type=int, default=40, help="generations of differential evolution (default 40)"
    )
    calibrate.add_argument(
        "--popsize", type=int, default=10, help="population per parameter (default 10)"
    )
    calibrate.set_defaults(run=run_calibrate)

    evaluate = commands.add_parser(
        "evaluate",
        help="compare a policy with a baseline on the same seeds; write a report",
        description="Drive a policy and a baseline over the same seeds and write report.md, "
        "metrics.json and the figures of the paper's §4.4-4.5. Details: docs/evaluation.md.",
    )
    add_connection_arguments(evaluate)
    evaluate.add_argument(
        "--policy", required=True, help="runs/NAME/policy.pt, idm or idm:PARAMS.json"
    )
    evaluate.add_argument(
        "--baseline", default="idm", help="idm (default), idm:PARAMS.json or a policy file"
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
    evaluate.set_defaults(run=run_evaluate)


# --------------------------------------------------------------------------- calibrate-idm


def run_calibrate(args: argparse.Namespace) -> int:
    from agent_client import __version__
    from agent_client.calibration import (
        FOLLOWING_GAP_M,
        FOLLOWING_HEADWAY_S,
        MIN_SEGMENT_S,
        calibration_document,
        fit_idm,
        record_segments,
    )
    from agent_client.remote_env import RemoteEnv
    from protocol.version import PROTOCOL_VERSION, format_version

    scenario = args.scenario or "cf"
    seeds = list(range(args.seed, args.seed + args.episodes))
    env = RemoteEnv(args.server, scenario, timeout_s=args.timeout, **dict(args.option))
    done = 0

    def recorded(seed: int, segments: list[Any], steps: int) -> None:
        nonlocal done
        done += 1
        following = sum(s.duration for s in segments)
        print(
            f"recorded {done}/{len(seeds)} seed {seed}: {steps} steps, {len(segments)} "
            f"car-following segment(s), {following:.1f} s",
            flush=True,
        )

    try:
        segments = record_segments(env, seeds, on_episode=recorded)
        welcome = env.welcome
        step_length = env.step_length
    finally:
        env.close()
    bounds = (welcome.action.acceleration_min, welcome.action.acceleration_max)
    print(
        f"fitting IDM on {len(segments)} segments ({sum(s.duration for s in segments):.0f} s): "
        f"differential evolution, {args.maxiter} generations x {args.popsize * 6}, then L-BFGS-B",
        flush=True,
    )

    def generation(index: int, best: float) -> None:
        if index == 1 or index % 5 == 0 or index == args.maxiter:
            print(f"  generation {index}/{args.maxiter}: gap RMSE {best:.3f} m", flush=True)

    result = fit_idm(
        segments,
        step_length,
        seed=args.seed,
        maxiter=args.maxiter,
        popsize=args.popsize,
        acceleration_bounds=bounds,
        on_generation=generation,
    )
    data = {
        "scenario": scenario,
        "episodes": len(seeds),
        "seeds": seeds,
        "options": dict(args.option),
        "step_length": step_length,
        "following": {"max_headway_s": FOLLOWING_HEADWAY_S, "min_range_m": FOLLOWING_GAP_M},
        "min_segment_s": MIN_SEGMENT_S,
        "following_seconds": round(sum(s.duration for s in segments), 1),
    }
    versions = {
        "server": welcome.server,
        "backend": f"{welcome.backend} {welcome.backend_version}",
        "agent_client": __version__,
        "protocol": format_version(PROTOCOL_VERSION),
    }
    document = calibration_document(result, data, versions)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    params = ", ".join(f"{k}={v:.3f}" for k, v in result.params.to_dict().items() if v is not None)
    print(
        f"IDM fitted in {result.seconds:.1f} s: {params} | gap RMSE {result.gap_rmse:.3f} m "
        f"({100 * result.gap_nrmse:.1f} % of the recorded gaps)"
    )
    if result.at_bounds:
        print(f"at a bound of the search box (poorly determined): {', '.join(result.at_bounds)}")
    print(f"wrote {args.out} (use it as --policy idm:{args.out})")
    return 0


# --------------------------------------------------------------------------- evaluate


def evaluation_command(args: argparse.Namespace, scenario: str, out: Path) -> str:
    """The command line that reruns this evaluation."""
    parts = ["agent-client", "evaluate", "--server", args.server, "--scenario", scenario]
    for name, value in args.option:
        parts += [
            "--option",
            f"{name}={json.dumps(value) if not isinstance(value, str) else value}",
        ]
    parts += ["--policy", args.policy, "--baseline", args.baseline]
    parts += ["--episodes", str(args.episodes), "--seed", str(args.seed), "--out", str(out)]
    if args.run_folder is not None:
        parts += ["--run", str(args.run_folder), "--table2-bins", str(args.table2_bins)]
    if args.cf_policy is not None:
        parts += ["--cf-policy", args.cf_policy]
    return shlex.join(parts)


def default_out(policy: str) -> Path:
    """``runs/NAME/eval`` next to a policy file; ``runs/eval-idm`` for IDM specs."""
    if policy == "idm" or policy.startswith("idm:"):
        return Path("runs") / "eval-idm"
    return Path(policy).parent / "eval"


def run_evaluate(args: argparse.Namespace) -> int:
    from agent_client import __version__
    from agent_client.cli import load_driver
    from agent_client.evaluation import DriverRun, EpisodeRecord, Evaluation, evaluate_driver
    from agent_client.metrics import format_summary
    from agent_client.policy import training_settings
    from agent_client.remote_env import RemoteEnv
    from agent_client.report import write_report
    from agent_client.run_log import EPISODE_CSV, read_rows
    from protocol.version import PROTOCOL_VERSION, format_version

    trained_scenario, trained_options = training_settings(args.policy)
    scenario = args.scenario or trained_scenario or "cf"
    defaults = trained_options if scenario == trained_scenario else {}
    options = {**defaults, **dict(args.option)}
    if defaults:
        print(f"the policy was trained with {defaults}: evaluating with them (--option overrides)")
    args.option = sorted(options.items())  # the rerun command names them explicitly
    out = args.out if args.out is not None else default_out(args.policy)
    seeds = list(range(args.seed, args.seed + args.episodes))
    specs = {"policy": args.policy, "baseline": args.baseline}
    if args.cf_policy is not None:
        specs["cf_policy"] = args.cf_policy
    drivers = {role: load_driver(spec) for role, spec in specs.items()}
    training_rows = None
    if args.run_folder is not None:
        training_rows = read_rows(args.run_folder / EPISODE_CSV)
    env = RemoteEnv(args.server, scenario, timeout_s=args.timeout, **options)
    runs: dict[str, DriverRun] = {}
    try:
        for role, driver in drivers.items():
            count = 0

            def progress(record: EpisodeRecord, role: str = role) -> None:
                nonlocal count
                count += 1
                print(f"[{role} {count}/{len(seeds)}] {format_summary(record.summary)}", flush=True)

            runs[role] = DriverRun(specs[role], evaluate_driver(env, driver, seeds, progress))
        welcome = env.welcome
        options = dict(env.options)
    finally:
        env.close()
    evaluation = Evaluation(
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
        training_rows=training_rows,
        run_folder=str(args.run_folder) if args.run_folder is not None else None,
        table2_bins=args.table2_bins,
    )
    path = write_report(out, evaluation)
    metrics = json.loads((out / "metrics.json").read_text())
    policy, baseline = metrics["drivers"]["policy"], metrics["drivers"]["baseline"]
    ratio = metrics["comparison"]["speed_ratio_policy_to_baseline"]
    ratio_text = f"{ratio:.3f}x" if ratio is not None else "n/a"
    print(
        f"policy {policy['average_speed']:.2f} m/s vs baseline {baseline['average_speed']:.2f} "
        f"m/s ({ratio_text}) | collisions/episode {policy['collisions_per_episode']:.2f} vs "
        f"{baseline['collisions_per_episode']:.2f}"
    )
    print(f"report: {path} (metrics.json and figures in {out})")
    return 0
