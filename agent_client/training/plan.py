"""What a training run is about to do, in a few lines for its first screen: the scenarios, the
learner, where it evaluates, the targets it stops at, and where its files go."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from agent_client.constants import JERK_COMFORT_LIMIT
from agent_client.evaluation.targets import (
    CEILING_TARGET,
    HEADWAY_TARGET,
    JERK_TARGET,
    SAFETY_TARGET,
)

if TYPE_CHECKING:
    from agent_client.training.trainer import Trainer


def plan_lines(trainer: Trainer, out: Path) -> list[str]:
    """The run's plan, as the user reads it before the first episode."""
    config = trainer.config
    lanes = "lane changes learned" if trainer.agent.n_lane_actions > 1 else "lane keeping"
    servers = len(trainer.vec.envs)
    egos = f", {config.egos} egos per simulation" if config.egos > 1 else ""
    reference = getattr(trainer.reference, "name", "a policy")
    stops = (
        f"{config.converged_evals} evaluations in a row that meet every target"
        if config.stop_when_converged
        else "never for the targets (--stop-when-converged stops there)"
    )
    limits = [f"{config.episodes} episodes"]
    if config.max_minutes is not None:
        limits.append(f"{config.max_minutes:g} min")
    where = (
        f"in the background on {len(trainer.eval_servers)} evaluation server(s)"
        if trainer.eval_servers and config.eval_while_training
        else f"on {len(trainer.eval_servers)} evaluation server(s), training waiting"
        if trainer.eval_servers
        else "on the training server(s), training waiting"
    )
    per = "per scenario " if len(config.scenarios) > 1 else ""
    evaluations = (
        f"every {config.eval_every} episodes once learning has begun, {config.eval_episodes} "
        f"greedy episodes {per}on held-out seeds, {where}"
        if config.eval_every
        else "none (eval_every = 0)"
    )
    speed = f"{1 + config.speed_gain:g}x as fast as" if config.speed_gain else "as fast as"
    judged = (
        " (collisions, red lights and route ends per scenario; jerk, headways, speed, the "
        "ceiling and the safety layer over the whole evaluation)"
        if len(config.scenarios) > 1
        else ""
    )
    where_trained = (
        f"{config.simulators} simulators the sampling workers start beside them"
        if config.simulators
        else f"{servers} server(s)"
    )
    sampling = {
        "local": "this process steps the servers in lock-step between its updates",
        "processes": "a process per server steps it while this one updates",
        "ray": "a Ray actor per server steps it while this one updates",
    }[trainer.sampling]
    why = " (auto)" if config.sampling == "auto" else ""
    return [
        f"training {config.learner.algo.upper()} (on {trainer.device}) on "
        f"{', '.join(config.scenarios)} (reward "
        f"{config.reward}, {trainer.features.name} features, {lanes}{egos}) on {where_trained}",
        f"  sampling: {trainer.sampling}{why}: {sampling}",
        f"  evaluations: {evaluations}",
        f"  targets: no collision, no red light passed, <= {100 * JERK_TARGET:g} % of jerk "
        f"above {JERK_COMFORT_LIMIT:g} m/s^3, <= {100 * HEADWAY_TARGET:g} % of headways under "
        f"1 s, {speed} the reference ({reference}), >= {100 * CEILING_TARGET:g} % of the "
        "leader-at-entry ceiling, the safety layer driving <= "
        f"{100 * SAFETY_TARGET:g} % of decisions; where lanes end, every episode reaching the "
        "end of its route" + judged,
        f"  stops at: {stops}; at most {' or '.join(limits)}; Ctrl-C checkpoints",
        f"  run folder: {out} (policy.pt, episodes.csv, evaluations.csv, tensorboard/)",
    ]
