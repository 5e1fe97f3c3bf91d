"""How fast does the learner reach the targets on `cf` (or `cflc`, or several scenarios at once)?
Prints a table, writes JSON.

For each reward and training seed: start a real SUMO server on a free loopback port, train from
scratch with the scenario's recommended configuration (`agent-client train`'s; plus any --config and
--set), evaluate greedily every `eval_every` episodes on `eval_episodes` held-out seeds (in the
background, on two idle-priority `direct://` servers of their own, unless --eval-servers 0; --set
eval_while_training=false makes training wait for them), and stop at three passing evaluations in a
row (zero collisions, <= 2.6 % jerk samples above 5.6 m/s^3, <= 5 % of leader steps under 1 s
headway, speed >= IDM and >= 98 % of the leader-at-entry ceiling) or at the time budget.

    python benchmarks/learning.py --rewards safe ra3 --seeds 0 1 2 --minutes 15
    python benchmarks/learning.py --rewards safe --seeds 0 1 2 --minutes 3 --config configs/cf.toml
    python benchmarks/learning.py --scenario merge exit lanedrop cflc --rewards safe --minutes 15

With --without-evaluations each converged seed is trained again to the episode where it
converged, without evaluations: the same training (evaluations on servers of their own do not
change it), so the difference in wall time is what the evaluations cost the run, whatever the
profile attributes to them.

Every run is timed alike: a short run first, not reported, loads the compiled update, which
only the first run of a process would otherwise pay for (~4 s). This is a measurement, not a
test: it takes minutes per run and prints what it measured.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.errors import UsageError
from agent_client.training.config import (
    TrainConfig,
    apply_overrides,
    load_config_file,
    parse_assignment,
    recommended,
)
from agent_client.training.progress import Profile
from agent_client.training.trainer import QuietReporter, Trainer
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line


def start_servers(
    count: int, scheme: str = "tcp", idle_priority: bool = False
) -> tuple[subprocess.Popen[str], list[str]]:
    """`count` SUMO servers on free loopback ports, under one `--workers` supervisor."""
    command = [sys.executable, "-m", "sim_server.cli", "--bind", f"{scheme}://127.0.0.1:0",
               "--workers", str(count), "--log-level", "WARNING"]  # fmt: skip
    if idle_priority:
        command.append("--idle-priority")
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        return server, [wait_for_line(server, LISTENING, 120.0) for _ in range(count)]
    except NotReady:
        server.kill()
        raise


class Deadline(QuietReporter):
    """Stops a run at its time budget (checked after every episode)."""

    def __init__(self, trainer_ref: list[Trainer], minutes: float, verbose: bool) -> None:
        self.trainer_ref = trainer_ref
        self.end = time.monotonic() + 60 * minutes
        self.verbose = verbose

    def message(self, text: str) -> None:
        if self.verbose:
            print(f"    {text}", flush=True)

    def episode(self, row: dict[str, Any]) -> None:
        if time.monotonic() > self.end and self.trainer_ref:
            self.trainer_ref[0].request_stop()


def run_one(
    config: TrainConfig, out: Path, minutes: float, verbose: bool, servers: int, eval_servers: int
) -> dict[str, Any]:
    supervisors = []
    train_supervisor, train_addresses = start_servers(servers)
    supervisors.append(train_supervisor)
    eval_addresses: list[str] = []
    if eval_servers:  # on this machine: the plain-socket transport, cheaper per step
        background = config.eval_while_training  # then they get only what training leaves
        eval_supervisor, eval_addresses = start_servers(eval_servers, "direct", background)
        supervisors.append(eval_supervisor)
    holder: list[Trainer] = []
    try:
        trainer = Trainer(
            config, train_addresses, out, reporter=Deadline(holder, minutes, verbose),
            eval_servers=eval_addresses,
        )  # fmt: skip
        holder.append(trainer)
        try:
            progress = trainer.run()
        finally:
            trainer.close()
    finally:
        for supervisor in supervisors:
            stop_process(supervisor)
    evaluations = progress.evaluations
    last = evaluations[-1] if evaluations else {}
    return {
        "reward": config.reward,
        "seed": config.seed,
        "converged": progress.converged_episode is not None,
        "episodes_to_converge": progress.converged_episode,
        "minutes_to_converge": (
            None if progress.converged_time is None else progress.converged_time / 60
        ),
        "steps_to_converge": progress.converged_step,
        "episodes_run": progress.episode,
        "minutes_run": progress.wall_time / 60,
        "steps_run": progress.global_step,
        "updates_run": progress.updates,
        "servers": servers,
        "eval_servers": eval_servers,
        "eval_while_training": config.eval_while_training,
        "evaluation_share": trainer.profile.evaluation_share(),
        "sampling": trainer.sampling,
        "evaluation_share_parts": evaluation_parts(trainer.profile, evaluations),
        "evaluation_episodes_run": sum(int(e["episodes"]) for e in evaluations),
        "evaluation_episodes_saved": sum(int(e.get("episodes_saved", 0)) for e in evaluations),
        "profile": trainer.profile.to_dict(),
        "last_evaluation": last,
        "evaluations": evaluations,
    }


def load_compiled_update(config: TrainConfig, out: Path, servers: int, verbose: bool) -> None:
    """A short run, not reported, before the timed ones: the first update of a process loads
    the compiled update from the disk cache (~4 s, docs/learner-design.md), which the first timed
    run would pay and the runs after it (and its rerun without evaluations) would not."""
    warm = apply_overrides(
        config,
        {"episodes": 6, "eval_every": 0, "stop_when_converged": False,
         "learner": {"learning_starts": 300}},
    )  # fmt: skip
    started = time.perf_counter()
    result = run_one(warm, out / "load-compiled-update", 5.0, verbose, servers, 0)
    print(f"== loaded the compiled update: {result['updates_run']} updates in "
          f"{time.perf_counter() - started:.1f} s (not timed)", flush=True)  # fmt: skip


def rerun_without_evaluations(
    config: TrainConfig, result: dict[str, Any], folder: Path, servers: int, verbose: bool
) -> dict[str, Any]:
    """Train `result`'s seed again to the episode where it converged, without evaluations; the
    evaluations' cost is the difference in wall time. Only where the training is the same (the
    same env steps and updates at that episode: evaluations on servers of their own leave it
    alone); else the cost is None."""
    episodes = result["episodes_to_converge"]
    # the same sampling (auto would choose it by whether evaluations need the servers)
    changes = {"eval_every": 0, "episodes": episodes, "sampling": result["sampling"]}
    bare = apply_overrides(config, changes)
    again = run_one(bare, folder.with_name(folder.name + "-without-evaluations"), 60.0, verbose,
                    servers, 0)  # fmt: skip
    # Both stop after the iteration in which that episode ended (the evaluated run as it converges)
    ran = ("steps_run", "updates_run")
    same = all(again[key] == result[key] for key in ran)
    seconds, bare_seconds = 60 * result["minutes_to_converge"], 60 * again["minutes_run"]
    extra = seconds - bare_seconds if same else None
    verdict = (
        f"the evaluations cost {extra:.1f} s of {seconds:.1f} ({100 * extra / seconds:.0f} %)"
        if extra is not None
        else "NOT the same training: no cost computed"
    )
    print(f"   without evaluations: {bare_seconds:.1f} s to episode {episodes} "
          f"({again['steps_run']} env steps); {verdict}", flush=True)  # fmt: skip
    return {
        "seconds": bare_seconds,
        "steps": again["steps_run"],
        "updates": again["updates_run"],
        "same_training": same,
        "evaluation_cost_seconds": extra,
        "evaluation_cost_share": None if extra is None else extra / seconds,
        "profile": again["profile"],
    }


def evaluation_parts(profile: Profile, evaluations: list[dict[str, Any]]) -> dict[str, float]:
    """The evaluations' share of the loop's time, split: the IDM baseline, the passing
    evaluations (which convergence needs in full: no schedule or screen may shorten them), the
    failed ones, and the rest (an evaluation given up, or still running at the end)."""
    total = profile.total or 1.0
    passes = sum(e["seconds"] for e in evaluations if e["passed_in_a_row"] > 0)
    failed = sum(e["seconds"] for e in evaluations if e["passed_in_a_row"] == 0)
    other = profile.evaluation_seconds - profile.baseline_evaluation - passes - failed
    return {
        "baseline": profile.baseline_evaluation / total,
        "passes": passes / total,
        "failed": failed / total,
        "other": max(other, 0.0) / total,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scenario", nargs="+", default=["cf"], help="one scenario, or several: one policy"
    )
    parser.add_argument("--rewards", nargs="+", default=["safe", "ra3"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--minutes", type=float, default=15.0, help="time budget per run")
    parser.add_argument("--episodes", type=int, default=1000, help="episode cap per run")
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--eval-every", type=int, default=10)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--servers", type=int, default=2, help="training servers (default 2)")
    parser.add_argument(
        "--eval-servers",
        type=int,
        default=2,
        help="direct:// evaluation servers of their own, evaluating in the background at idle "
        "priority (default 2, as scripts/main.sh; --set eval_while_training=false: training "
        "waits while they evaluate; 0: inline on the training servers, as `agent-client train` "
        "does without --eval-server)",
    )
    parser.add_argument(
        "--config", type=Path, help="TOML (or JSON) file of settings, before --set (configs/)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "benchmark")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument(
        "--without-evaluations",
        action="store_true",
        help="train each converged seed again to its converged episode without evaluations, and "
        "report what the evaluations cost (the difference in wall time)",
    )
    args = parser.parse_args()
    if args.without_evaluations and not args.eval_servers:
        print(
            "error: --without-evaluations needs --eval-servers: inline evaluations on the "
            "training servers change the training, so a run without them is not the same run",
            file=sys.stderr,
        )
        return 2

    try:
        config_file = load_config_file(args.config) if args.config is not None else None
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    def run_config(reward: str, seed: int) -> TrainConfig:
        scenario = args.scenario[0] if len(args.scenario) == 1 else args.scenario
        config = apply_overrides(
            recommended(scenario),  # what `agent-client train --scenario ...` starts from
            {
                "reward": reward,
                "seed": seed,
                "episodes": args.episodes,
                "eval_every": args.eval_every,
                "eval_episodes": args.eval_episodes,
                "stop_when_converged": True,
            },
        )
        if config_file is not None:
            config = apply_overrides(config, config_file)
        for assignment in args.set:
            config = apply_overrides(config, parse_assignment(assignment))
        return config

    try:
        configs = {(r, seed): run_config(r, seed) for r in args.rewards for seed in args.seeds}
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    results = []
    load_compiled_update(next(iter(configs.values())), args.out, args.servers, args.verbose)
    for reward in args.rewards:
        for seed in args.seeds:
            config = configs[reward, seed]
            print(f"== {config.label} reward={reward} seed={seed}", flush=True)
            folder = args.out / f"{config.label}-{reward}-{seed}"
            result = run_one(
                config, folder, args.minutes, args.verbose, args.servers, args.eval_servers
            )
            if args.without_evaluations and result["converged"]:
                result["without_evaluations"] = rerun_without_evaluations(
                    config, result, folder, args.servers, args.verbose
                )
            results.append(result)
            print(f"   {summary_line(result)}", flush=True)

    print()
    print(table(results))
    machine = f"{platform.node()} {platform.machine()}, {platform.python_version()}"
    label = "+".join(args.scenario)
    payload = {"scenario": label, "machine": machine, "config": config_file,
               "settings": args.set, "results": results}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"learning-{label}.json").write_text(json.dumps(payload, indent=2))
    print(f"\nwrote {args.out / f'learning-{label}.json'}")
    return 0


def summary_line(result: dict[str, Any]) -> str:
    last = result["last_evaluation"]
    state = (
        f"converged at episode {result['episodes_to_converge']} "
        f"({result['minutes_to_converge']:.1f} min, {result['steps_to_converge']} steps)"
        if result["converged"]
        else f"not converged in {result['episodes_run']} episodes ({result['minutes_run']:.1f} min)"
    )
    if not last:
        return state
    return (
        f"{state}; last evaluation: {last['collisions_per_episode']:.2f} collisions/ep, "
        f"jerk>5.6 {100 * last['jerk_share_above_limit']:.2f}%, "
        f"headway<1s {100 * last['headway_share_below_1s']:.2f}%, "
        f"speed {last['speed_ratio_to_idm']:.3f}x IDM, "
        f"{last['speed_ratio_to_ceiling']:.3f}x ceiling"
    )


def table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| reward | seed | converged at (min / episode / env steps) | collisions/ep | jerk>5.6 "
        "| headway<1s | speed / IDM | speed / ceiling "
        "| evaluations' share (IDM baseline + passes + failed) "
        "| evaluations (episodes run / saved by screening) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in results:
        last = r["last_evaluation"] or {}
        converged = (
            f"{r['minutes_to_converge']:.1f} / {r['episodes_to_converge']} / "
            f"{r['steps_to_converge']:,}"
            if r["converged"]
            else f"no ({r['episodes_run']} ep, {r['minutes_run']:.1f} min)"
        )
        lines.append(
            f"| {r['reward']} | {r['seed']} | {converged} "
            f"| {last.get('collisions_per_episode', float('nan')):.2f} "
            f"| {100 * last.get('jerk_share_above_limit', float('nan')):.2f}% "
            f"| {100 * last.get('headway_share_below_1s', float('nan')):.2f}% "
            f"| {last.get('speed_ratio_to_idm', float('nan')):.3f} "
            f"| {last.get('speed_ratio_to_ceiling', float('nan')):.3f} "
            f"| {100 * r['evaluation_share']:.0f}% ({share_parts(r)}) "
            f"| {len(r['evaluations'])} ({r['evaluation_episodes_run']} / "
            f"{r['evaluation_episodes_saved']}) |"
        )
    return "\n".join(lines)


def share_parts(result: dict[str, Any]) -> str:
    parts = result["evaluation_share_parts"]
    text = " + ".join(f"{100 * parts[name]:.0f}" for name in ("baseline", "passes", "failed"))
    other = parts.get("other", 0.0)
    return f"{text} + {100 * other:.0f} other" if other >= 0.005 else text


if __name__ == "__main__":
    sys.exit(main())
