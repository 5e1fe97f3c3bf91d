"""``agent-client calibrate-idm``: fit IDM to the scenario's own traffic, recorded over the bridge.

Heavy imports (scipy) happen inside `run`, so that ``agent-client --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from agent_client.cli.common import Commands, add_connection_arguments
from agent_client.defaults import CALIBRATION_EPISODES, CALIBRATION_SEED, DEFAULT_SCENARIO

UNITS = {"a": "m/s²", "b": "m/s²", "T": "s", "s0": "m", "v0": "m/s", "delta": ""}


def add_parser(commands: Commands) -> None:
    calibrate = commands.add_parser(
        "calibrate-idm",
        help="fit IDM to the scenario's own traffic, recorded through the bridge",
        description="Record every background vehicle of the scenario (reset option "
        "report_traffic) and fit IDM to their gaps the way SUMO integrates it: shared a, b, T, "
        "s0, delta and a desired speed per vehicle, with 90 % bootstrap intervals. The JSON "
        "written is usable as --policy idm:FILE. Details: docs/evaluation.md.",
    )
    add_connection_arguments(calibrate)
    calibrate.add_argument("--out", type=Path, required=True, help="JSON file to write")
    calibrate.add_argument(
        "--episodes",
        type=int,
        default=CALIBRATION_EPISODES,
        help=f"episodes to record (default {CALIBRATION_EPISODES})",
    )
    calibrate.add_argument(
        "--seed",
        type=int,
        default=CALIBRATION_SEED,
        help=f"seed of the first episode and of the optimiser (default {CALIBRATION_SEED})",
    )
    calibrate.add_argument(
        "--vehicle-type",
        default=None,
        help="vehicle type to calibrate (default: the most frequent among the followers)",
    )
    calibrate.add_argument(
        "--source",
        choices=("traffic", "ego"),
        default="traffic",
        help="traffic (default): every background vehicle; ego: only the ego driven by the "
        "simulator's own model (ego_driver=sumo), for a server that cannot report its traffic",
    )
    calibrate.add_argument(
        "--maxiter", type=int, default=40, help="generations of differential evolution (default 40)"
    )
    calibrate.add_argument(
        "--popsize", type=int, default=10, help="population per parameter (default 10)"
    )
    calibrate.add_argument(
        "--bootstrap",
        type=int,
        default=None,
        metavar="N",
        help="bootstrap replicates of the intervals (default 100; 0: no intervals)",
    )
    calibrate.add_argument(
        "--update",
        choices=("auto", "euler", "ballistic"),
        default="auto",
        help="the simulator's position update (default auto: read off the recorded odometers)",
    )
    calibrate.add_argument(
        "--stepping",
        type=float,
        default=None,
        metavar="S",
        help="the IDM's SUMO stepping (s per internal iteration; default SUMO's 0.25)",
    )
    calibrate.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from agent_client.envs.remote_env import RemoteEnv
    from agent_client.evaluation.calibration import choose_vehicle_type, recording_options

    scenario = args.scenario or DEFAULT_SCENARIO
    seeds = list(range(args.seed, args.seed + args.episodes))
    env = RemoteEnv(
        args.server,
        scenario,
        timeout_s=args.timeout,
        reset_timeout_s=args.reset_timeout,
        **dict(args.option),
    )
    try:
        recording_options(env, args.source)  # a scenario that cannot be recorded: say so now
        segments = _record(env, seeds, args.source)
        welcome, step_length = env.welcome, env.step_length
    finally:
        env.close()
    assert step_length is not None  # RemoteEnv knows it once connected
    vehicle_type = choose_vehicle_type(segments, args.vehicle_type)
    _print_types(segments, vehicle_type)
    chosen = [s for s in segments if s.vehicle_type == vehicle_type]
    result = _fit(args, chosen, step_length)
    _write(args, scenario, seeds, segments, vehicle_type, step_length, welcome, result)
    _print_result(result)
    print(f"wrote {args.out} (use it as --policy idm:{args.out})")
    return 0


def _record(env: Any, seeds: list[int], source: str) -> list[Any]:
    """The scenario's traffic (or ego), recorded with progress lines."""
    from agent_client.evaluation.calibration import record_segments

    done = 0

    def recorded(seed: int, segments: list[Any], steps: int) -> None:
        nonlocal done
        done += 1
        following = sum(s.duration for s in segments)
        followers = len({s.follower for s in segments})
        print(
            f"recorded {done}/{len(seeds)} seed {seed}: {steps} steps, {followers} follower(s), "
            f"{len(segments)} car-following segment(s), {following:.1f} s",
            flush=True,
        )

    return record_segments(env, seeds, on_episode=recorded, source=source)


def _print_types(segments: list[Any], vehicle_type: str) -> None:
    from agent_client.evaluation.calibration import types_seen

    seen = ", ".join(
        f"{name} ({summary.followers} followers, {summary.seconds:.0f} s)"
        for name, summary in types_seen(segments).items()
    )
    print(f"vehicle types among the followers: {seen}; calibrating {vehicle_type!r}", flush=True)


def _fit(args: argparse.Namespace, segments: list[Any], step_length: float) -> Any:
    from agent_client.evaluation.calibration import (
        BOOTSTRAP_REPLICATES,
        SUMO_IDM_STEPPING,
        detect_update,
        fit_idm,
        sumo_iterations,
    )

    stepping = args.stepping if args.stepping is not None else SUMO_IDM_STEPPING
    update = detect_update(segments, step_length) if args.update == "auto" else args.update
    followers = len({s.follower for s in segments})
    print(
        f"fitting IDM on {len(segments)} segments of {followers} followers "
        f"({sum(s.duration for s in segments):.0f} s) as SUMO steps it: {update} update, "
        f"{sumo_iterations(step_length, stepping)} iteration(s) per {step_length:g} s step; "
        f"differential evolution, {args.maxiter} generations x {args.popsize * 6}, "
        "then Levenberg-Marquardt",
        flush=True,
    )

    def generation(index: int, best: float) -> None:
        if index == 1 or index % 5 == 0 or index == args.maxiter:
            print(f"  generation {index}/{args.maxiter}: gap RMSE {best:.3f} m", flush=True)

    return fit_idm(
        segments,
        step_length,
        seed=args.seed,
        maxiter=args.maxiter,
        popsize=args.popsize,
        update=update,
        stepping=stepping,
        replicates=args.bootstrap if args.bootstrap is not None else BOOTSTRAP_REPLICATES,
        on_generation=generation,
        on_stage=lambda message: print(f"  {message}", flush=True),
    )


def _write(
    args: argparse.Namespace,
    scenario: str,
    seeds: list[int],
    segments: list[Any],
    vehicle_type: str,
    step_length: float,
    welcome: Any,
    result: Any,
) -> None:
    from dataclasses import asdict

    from agent_client import __version__
    from agent_client.evaluation.calibration import (
        FOLLOWING_GAP_M,
        FOLLOWING_HEADWAY_S,
        MIN_SEGMENT_S,
        calibration_document,
        types_seen,
    )
    from protocol.version import PROTOCOL_VERSION, format_version

    chosen = [s for s in segments if s.vehicle_type == vehicle_type]
    data = {
        "scenario": scenario,
        "episodes": len(seeds),
        "seeds": seeds,
        "options": dict(args.option),
        "step_length": step_length,
        "source": args.source,
        "vehicle_type": vehicle_type,
        "types_seen": {name: asdict(s) for name, s in types_seen(segments).items()},
        "following": {"max_headway_s": FOLLOWING_HEADWAY_S, "min_range_m": FOLLOWING_GAP_M},
        "min_segment_s": MIN_SEGMENT_S,
        "following_seconds": round(sum(s.duration for s in chosen), 1),
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


def _print_result(result: Any) -> None:
    """The parameters with their intervals and flags, one per line."""
    from agent_client.evaluation.calibration import (
        INTERVAL_LEVEL,
        UNDETERMINED_M,
        WIDE_INTERVAL,
        v0_summary,
    )

    print(
        f"IDM fitted in {result.seconds:.1f} s on {result.followers} followers: gap RMSE "
        f"{result.gap_rmse:.3f} m ({100 * result.gap_nrmse:.1f} % of the recorded gaps)"
    )
    level = round(100 * INTERVAL_LEVEL)
    at_bounds, wide, undetermined = (
        set(result.at_bounds),
        set(result.wide),
        set(result.undetermined),
    )
    for name, value in result.params.to_dict().items():
        interval = result.intervals.get(name)
        shown = f"{interval[0]:.3f}-{interval[1]:.3f}" if interval else "not computed"
        flags = [
            text
            for text, on in (
                ("UNDETERMINED", name in undetermined),
                ("AT A BOUND", name in at_bounds),
                ("WIDE", name in wide),
            )
            if on
        ]
        print(
            f"  {name:<5} {value:8.3f} {UNITS[name]:<4}  {level} % interval {shown}"
            + (f"  [{', '.join(flags)}]" if flags else "")
        )
    v0 = v0_summary(result)
    if v0["median"] is not None:
        others = v0["followers"] - v0["determined"]
        print(
            f"  v0 is the median of {v0['determined']} of {v0['followers']} followers' own v0"
            + (f" ({others} never drove near their desired speed)" if others else "")
            + f"; they spread {v0['p5']:.1f}-{v0['p95']:.1f} m/s (5-95 %)"
        )
    if undetermined:
        print(
            "undetermined (a 10 % change, the others compensating, moves the gaps by less than "
            f"{1000 * UNDETERMINED_M:g} mm; the traffic may sit in one steady state): "
            + ", ".join(sorted(undetermined))
        )
    if at_bounds:
        print(f"at a bound of the search box (poorly determined): {', '.join(sorted(at_bounds))}")
    if wide:
        print(
            f"wide {level} % interval (half-width above {100 * WIDE_INTERVAL:.0f} % of the value): "
            + ", ".join(sorted(wide))
        )
