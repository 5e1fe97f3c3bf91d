"""``agent-client drive``: drive episodes with IDM or a trained policy and summarise them."""

from __future__ import annotations

import argparse
import json
import math

from agent_client.cli.common import (
    Commands,
    add_connection_arguments,
    add_record_argument,
    check_record_folder,
    check_reward,
    open_recorder,
)
from agent_client.defaults import DEFAULT_SCENARIO


def add_parser(commands: Commands) -> None:
    drive = commands.add_parser(
        "drive",
        help="drive episodes with a driver (idm, idm+mobil, sumo or a trained policy) and "
        "summarise them",
    )
    add_connection_arguments(drive)
    drive.add_argument(
        "--policy",
        default="idm",
        help="idm, idm+mobil (with lane changes: a route's merge or exit), sumo (the "
        "simulator's own driver), idm:PARAMS.json, or a trained policy file "
        "(runs/NAME/policy.pt)",
    )
    drive.add_argument("--episodes", type=int, default=5, help="number of episodes (default 5)")
    drive.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    drive.add_argument("--json", action="store_true", help="print one JSON object per episode")
    drive.add_argument(
        "--reward", default="safe", help="reward reported per episode (default safe)"
    )
    add_record_argument(drive)
    drive.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from agent_client.drivers.episode import drive
    from agent_client.drivers.spec import load_driver, trained_on, training_settings
    from agent_client.envs.remote_env import RemoteEnv
    from agent_client.evaluation.metrics import aggregate, episode_summary, format_summary

    check_reward(args.reward)
    check_record_folder(args.record)
    driver = load_driver(args.policy)
    trained_scenario, trained_options = training_settings(args.policy)
    scenario = args.scenario or trained_scenario or DEFAULT_SCENARIO  # several: drawn by seed
    if not (scenario == trained_scenario or trained_on(trained_scenario, str(scenario))):
        trained_options = {}
    options = {**trained_options, **dict(args.option)}
    seeds = list(range(args.seed, args.seed + args.episodes))
    wire = open_recorder(
        args, scenario=scenario, options=options, seeds=seeds, drivers={"policy": args.policy}
    )
    summaries = []
    try:
        env = RemoteEnv(
            args.server,
            scenario,
            reward=args.reward,
            timeout_s=args.timeout,
            reset_timeout_s=args.reset_timeout,
            recorder=wire,
            **options,
        )
        try:
            for episode in drive(env, driver, args.episodes, args.seed):
                summary = episode_summary(episode)
                summaries.append(summary)
                print(
                    json.dumps(summary.to_dict()) if args.json else format_summary(summary),
                    flush=True,
                )
        finally:
            env.close()
    finally:
        if wire is not None:
            wire.close()
    if not args.json:
        totals = aggregate(summaries)
        ratio = totals["speed_ratio_to_ceiling"]
        ceiling = (
            f"{ratio:.3f}x the leader-at-entry ceiling" if math.isfinite(ratio) else "no ceiling"
        )
        print(
            f"{args.policy} on {scenario}: {len(summaries)} episodes | "
            f"avg speed {totals['average_speed']:.2f} m/s (sd {totals['average_speed_sd']:.2f}), "
            f"{ceiling} | "
            f"collisions/episode {totals['collisions_per_episode']:.2f} | "
            f"red lights/episode {totals['red_lights_per_episode']:.2f} | "
            f"arrived {100 * totals['arrival_share']:.0f}% | "
            f"jerk>5.6 {100 * totals['jerk_share_above_limit']:.2f}% | "
            f"headway<1s {100 * totals['headway_share_below_1s']:.2f}%"
        )
    return 0
