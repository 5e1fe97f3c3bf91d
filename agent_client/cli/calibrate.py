"""``agent-client calibrate-idm``: fit IDM to human trajectories recorded through the bridge.

Heavy imports (scipy) happen inside `run`, so that ``agent-client --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from agent_client.cli.common import Commands, add_connection_arguments
from agent_client.defaults import CALIBRATION_SEED, DEFAULT_SCENARIO


def add_parser(commands: Commands) -> None:
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
    calibrate.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from agent_client.envs.remote_env import RemoteEnv

    scenario = args.scenario or DEFAULT_SCENARIO
    seeds = list(range(args.seed, args.seed + args.episodes))
    env = RemoteEnv(args.server, scenario, timeout_s=args.timeout, **dict(args.option))
    try:
        segments = _record(env, seeds)
        welcome, step_length = env.welcome, env.step_length
    finally:
        env.close()
    assert step_length is not None  # RemoteEnv knows it once connected
    result = _fit(args, segments, step_length, welcome)
    _write(args, scenario, seeds, segments, step_length, welcome, result)
    return 0


def _record(env: Any, seeds: list[int]) -> list[Any]:
    """The scenario's human drivers, recorded with progress lines."""
    from agent_client.evaluation.calibration import record_segments

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

    return record_segments(env, seeds, on_episode=recorded)


def _fit(args: argparse.Namespace, segments: list[Any], step_length: float, welcome: Any) -> Any:
    from agent_client.evaluation.calibration import fit_idm

    print(
        f"fitting IDM on {len(segments)} segments ({sum(s.duration for s in segments):.0f} s): "
        f"differential evolution, {args.maxiter} generations x {args.popsize * 6}, then L-BFGS-B",
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
        acceleration_bounds=(welcome.action.acceleration_min, welcome.action.acceleration_max),
        on_generation=generation,
    )


def _write(
    args: argparse.Namespace,
    scenario: str,
    seeds: list[int],
    segments: list[Any],
    step_length: float,
    welcome: Any,
    result: Any,
) -> None:
    from agent_client import __version__
    from agent_client.evaluation.calibration import (
        FOLLOWING_GAP_M,
        FOLLOWING_HEADWAY_S,
        MIN_SEGMENT_S,
        calibration_document,
    )
    from protocol.version import PROTOCOL_VERSION, format_version

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
