"""``agent-client train``: command-line front of `agent_client.training.trainer`."""

from __future__ import annotations

import argparse
import contextlib
import json
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agent_client.cli.common import Commands, add_connection_arguments, existing_folder
from agent_client.defaults import DEFAULT_SCENARIO
from agent_client.errors import UsageError
from agent_client.rl.rewards import REWARDS
from protocol.transport.endpoint import DEFAULT_ADDRESS

if TYPE_CHECKING:
    from agent_client.training.config import TrainConfig
    from agent_client.training.trainer import Trainer


def add_parser(commands: Commands) -> None:
    train = commands.add_parser(
        "train",
        help="train a TD3 (or DDPG) driver through the bridge",
        description="Train a driver through the bridge. Settings: the scenario's recommended "
        "ones < --config FILE < flags < --set KEY=VALUE. Every setting and its default: "
        "docs/learner.md.",
    )
    add_connection_arguments(train, several=True)
    train.add_argument("--out", type=Path, help="run folder (default runs/SCENARIO-REWARD-SEED)")
    train.add_argument(
        "--reward",
        help=f"one of {', '.join(REWARDS)} (default safe; wave and wave_own read the traffic: "
        "--option report_traffic=true)",
    )
    train.add_argument("--episodes", type=int, help="training episodes (default 300)")
    train.add_argument(
        "--minutes", type=float, help="stop after this many minutes (checkpointed; default: none)"
    )
    train.add_argument(
        "--algo", choices=("ddpg", "td3"), help="learner (default td3: DDPG with its three fixes)"
    )
    train.add_argument("--seed", type=int, help="seed (default 0)")
    train.add_argument(
        "--pretrain-idm", action="store_true", default=None, help="behaviour-clone IDM first"
    )
    train.add_argument("--decision-interval", type=float, help="s per decision (default 0.1)")
    train.add_argument(
        "--egos",
        type=int,
        metavar="N",
        help="egos per simulation, all driven by the one shared policy and all learned from "
        "(protocol 1.4; the ring, cf, cflc); evaluations stay one-ego (default 1)",
    )
    train.add_argument("--config", type=Path, help="TOML (or JSON) file of settings")
    train.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any setting, e.g. --set eval_every=5 --set learner.actor_lr=3e-4 (repeatable)",
    )
    train.add_argument(
        "--stop-when-converged",
        action="store_true",
        default=None,
        help="stop after 3 evaluations in a row meet every target",
    )
    train.add_argument(
        "--eval-server",
        action="append",
        default=[],
        metavar="ADDRESS",
        help="a server for the greedy evaluations, which then run in the background while "
        "training goes on (start it with --idle-priority; --set eval_while_training=false: "
        "training waits for them; repeatable; default: a simulator this command starts for "
        "itself at idle priority where it offers the run's scenarios as the --server does, "
        "else the --server, training waiting)",
    )
    train.add_argument(
        "--inline-evaluations",
        action="store_true",
        help="without --eval-server: evaluate on the training --server, training waiting, "
        "instead of on a simulator of their own",
    )
    train.add_argument("--resume", type=Path, metavar="RUN", help="continue runs/NAME")
    train.add_argument(
        "--retry-for",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="when the server is lost, wait this long for it (or a restarted one) to answer, "
        "then continue with a new episode; 0 (default) stops the run with a checkpoint",
    )
    train.add_argument(
        "--sampling",
        choices=("auto", "local", "processes", "ray"),
        help="local: this process steps every --server at once; processes: one sampling "
        "process per --server, each with a copy of the policy, while the learner updates; "
        "ray: the same workers as Ray actors (docs/ray.md); auto (default): processes where "
        "there is one ego per simulation, two cores or more with up to two servers per core, "
        "and evaluations on servers of their own (always with --simulators), else local",
    )
    train.add_argument(
        "--ray-address",
        metavar="ADDRESS",
        help='with --sampling ray: "auto" (this machine\'s Ray cluster) or ray://HOST:10001; '
        "default: start a local Ray",
    )
    train.add_argument(
        "--simulators",
        type=int,
        metavar="N",
        help="with --sampling processes or ray: N sampling workers, each starting a simulator "
        "of its own beside it (with Ray, where Ray places it; --set simulator_args=... its "
        "sim-server options, default --backend sumo), stopped with the run; without --server "
        "a local one answers the handshake and the evaluations",
    )
    train.add_argument(
        "--device",
        help="where the networks learn: cpu (default), cuda, cuda:N, or auto (a CUDA GPU if "
        "torch sees one, else the CPU)",
    )
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.set_defaults(run=run)


def build_config(args: argparse.Namespace) -> TrainConfig:
    """The run's settings: the scenario's recommended ones < --config < flags < --set."""
    from agent_client.training.config import (
        apply_overrides,
        load_config_file,
        parse_assignment,
        recommended,
    )

    file = load_config_file(args.config) if args.config is not None else {}
    assignments = [parse_assignment(text) for text in args.set]

    def chosen(name: str, flag: Any, default: Any) -> Any:
        """What the run's `name` will be: the last --set of it, else the flag, else the file's."""
        named = [a[name] for a in assignments if name in a]
        return named[-1] if named else flag if flag is not None else file.get(name, default)

    scenarios = args.scenario
    flag = None if scenarios is None else scenarios[0] if len(scenarios) == 1 else scenarios
    # the scenario's recommended settings first, then the user's
    config = recommended(
        chosen("scenario", flag, DEFAULT_SCENARIO), chosen("reward", args.reward, "safe")
    )
    if file:
        config = apply_overrides(config, file)
    flags: dict[str, Any] = {
        "reward": args.reward,
        "episodes": args.episodes,
        "seed": args.seed,
        "pretrain_idm": args.pretrain_idm,
        "decision_interval": args.decision_interval,
        "stop_when_converged": args.stop_when_converged,
        "sampling": args.sampling,
        "device": args.device,
        "ray_address": args.ray_address,
        "simulators": args.simulators,
        "max_minutes": args.minutes,
        "egos": args.egos,
    }
    if args.scenario is not None:
        flags["scenario"] = args.scenario[0] if len(args.scenario) == 1 else args.scenario
    if args.option:
        flags["scenario_options"] = {**config.scenario_options, **dict(args.option)}
    config = apply_overrides(config, {k: v for k, v in flags.items() if v is not None})
    if args.algo is not None:
        from agent_client.rl.td3 import TD3Config

        preset = TD3Config.td3() if args.algo == "td3" else TD3Config.ddpg()
        algo = {k: getattr(preset, k) for k in ("n_critics", "policy_delay", "target_noise")}
        config = apply_overrides(config, {"learner": {**config.learner.to_dict(), **algo}})
    for update in assignments:
        config = apply_overrides(config, update)
    return config


class BarReporter:
    """A tqdm bar over episodes with the running reward and speed; messages above it."""

    def __init__(self, total: int, initial: int, quiet: bool) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, initial=initial, unit="ep", disable=quiet, dynamic_ncols=True)
        self.rewards: deque[float] = deque(maxlen=10)
        self.speeds: deque[float] = deque(maxlen=10)
        self.quiet = quiet

    def message(self, text: str) -> None:
        if not self.quiet:
            self.bar.write(text)

    def episode(self, row: dict[str, Any]) -> None:
        self.rewards.append(float(row["total_reward"]))
        self.speeds.append(float(row["average_speed"]))
        self.bar.set_postfix(
            reward=f"{sum(self.rewards) / len(self.rewards):.1f}",
            speed=f"{sum(self.speeds) / len(self.speeds):.2f}",
            end=row["reason"],
            step=row["global_step"],
        )
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def run(args: argparse.Namespace) -> int:
    from agent_client.training.config import TrainConfig, apply_overrides
    from agent_client.training.trainer import Trainer

    if args.inline_evaluations and args.eval_server:
        raise UsageError("--inline-evaluations and --eval-server: choose one")
    if args.resume is not None:
        saved = json.loads((existing_folder(args.resume, "--resume") / "config.json").read_text())
        config = TrainConfig.from_dict(saved)
        changes = {"episodes": args.episodes, "max_minutes": args.minutes, "device": args.device}
        config = apply_overrides(config, {k: v for k, v in changes.items() if v is not None})
        out = args.resume
    else:
        config = build_config(args)
        out = args.out or Path("runs") / f"{config.label}-{config.reward}-{config.seed}"
    reporter = BarReporter(config.episodes, 0, args.quiet)
    with contextlib.ExitStack() as stack:
        servers, eval_servers = args.server or [DEFAULT_ADDRESS], args.eval_server
        if config.simulators and not args.server:  # the workers start theirs; the rest here
            servers = [stack.enter_context(_own_simulator(config.simulator_args))]
            if config.eval_every > 0 and not eval_servers and not args.inline_evaluations:
                evaluations = _own_simulator(config.simulator_args + " --idle-priority")
                eval_servers = [stack.enter_context(evaluations)]
        elif config.eval_every > 0 and not eval_servers and not args.inline_evaluations:
            eval_servers = _evaluation_simulator(stack, servers[0], config, args, reporter)
        trainer = Trainer(
            config,
            servers,
            out,
            args.timeout,
            reporter,
            args.retry_for,
            eval_servers,
            reset_timeout_s=args.reset_timeout,
        )
        return _train(trainer, reporter, out, resumed=args.resume is not None)


@contextlib.contextmanager
def _own_simulator(args: str) -> Iterator[str]:
    """The address of a simulator this process starts for itself (for the handshake, or the
    evaluations, of a run whose sampling workers start their own), stopped when done."""
    from agent_client.training.simulators import OwnSimulator

    with OwnSimulator(args) as simulator:
        yield simulator.address


def _evaluation_simulator(
    stack: contextlib.ExitStack,
    server: str,
    config: TrainConfig,
    args: argparse.Namespace,
    reporter: BarReporter,
) -> list[str]:
    """Where a run without --eval-server evaluates: a simulator of its own where one started
    here serves the run's scenarios as `server` does (the recommended setup: evaluations in
    the background, docs/learner.md), else inline on the training servers ([])."""
    from agent_client.training.simulators import evaluation_simulator

    simulator, line = evaluation_simulator(
        server, config.scenarios, args.timeout, idle=config.eval_while_training
    )
    if simulator is not None:
        stack.callback(simulator.close)
    if line:
        reporter.message(line)
    return [] if simulator is None else [simulator.address]


def _train(trainer: Trainer, reporter: BarReporter, out: Path, resumed: bool) -> int:
    from agent_client.training.plan import plan_lines
    from agent_client.training.plots import plot_training

    try:
        for line in plan_lines(trainer, out):
            reporter.message(line)
        progress = trainer.run(resume=resumed)
    finally:
        reporter.close()
        trainer.close()  # closes the collector too (Ray's workers, if any)
    figure = plot_training(out)
    print(
        f"run folder: {out} (policy.pt, episodes.csv, evaluations.csv, tensorboard/, {figure.name})"
    )
    if progress.converged_episode is not None:
        print(
            f"converged at episode {progress.converged_episode} "
            f"after {progress.converged_time / 60:.1f} min"  # type: ignore[operator]
        )
    return 0
