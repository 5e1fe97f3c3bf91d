"""The training loop of the paper's Fig. 1: read the state, score the last action, learn, act.

One learner, one or more remote simulators: every step the learner receives the recognition
state from each server, computes the reward of its last action from it, stores the transitions
in one replay buffer, runs its gradient updates and sends the next commands (to all servers at
once, so they simulate in parallel). Greedy evaluations on held-out seeds, on the first server,
judge the policy against the IDM baseline and the leader-at-entry ceiling; checkpoints make a
run resumable.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, Protocol, TypeVar

import numpy as np
import torch

from agent_client.defaults import PRETRAIN_SEED, STEP_TIMEOUT_S
from agent_client.drivers.episode import Episode, run_episode
from agent_client.drivers.idm import IDMDriver
from agent_client.drivers.policy import LANE_COMMANDS, ActionScale, PolicyDriver, save_policy
from agent_client.envs.remote_env import RemoteEnv
from agent_client.envs.vector_env import RemoteVectorEnv
from agent_client.errors import ServerError, ServerUnavailable
from agent_client.evaluation.metrics import EpisodeSummary, aggregate, episode_summary
from agent_client.evaluation.targets import targets_met
from agent_client.rl.checkpoint import load_checkpoint, save_checkpoint
from agent_client.rl.features import FeatureMap, FeatureMismatch
from agent_client.rl.rewards import q_upper_bound
from agent_client.rl.td3 import Agent
from agent_client.training.config import TrainConfig
from agent_client.training.run_log import RunLog
from protocol.errors import ErrorCode
from protocol.messages import Observation

EPISODE_FAILURES = (ErrorCode.SIMULATOR_ERROR.value, ErrorCode.INSERTION_FAILED.value)
"""Error codes after which the server's next reset starts afresh: the trainer tries again."""
MAX_FAILURES_IN_A_ROW = 5

T = TypeVar("T")


class Reporter(Protocol):
    """Where a run reports progress; the CLI draws a progress bar, tests stay quiet."""

    def message(self, text: str) -> None:
        """A line for the user."""

    def episode(self, row: dict[str, Any]) -> None:
        """Metrics of a finished training episode."""


class QuietReporter:
    """Reports nothing."""

    def message(self, text: str) -> None:
        pass

    def episode(self, row: dict[str, Any]) -> None:
        pass


@dataclass
class Progress:
    """Counters that a checkpoint restores."""

    episode: int = 0
    global_step: int = 0
    wall_time: float = 0.0
    passed_in_a_row: int = 0
    converged_episode: int | None = None
    converged_time: float | None = None
    best_score: float = -float("inf")
    evaluations: list[dict[str, Any]] = field(default_factory=list)
    reconnects: int = 0
    failed_episodes: int = 0


@dataclass
class _Slot:
    """The training episode running on one server."""

    seed: int
    obs: Observation
    x: np.ndarray
    recorder: Episode
    states: list[np.ndarray] = field(default_factory=list)
    accelerations: list[float] = field(default_factory=list)
    lanes: list[int] = field(default_factory=list)


Finished = tuple[EpisodeSummary, list[float], float]
"""A finished training episode: its summary, the critic losses since the last one, its mean Q."""


class Trainer:
    """Owns the environment, the agent, the buffer and the run folder."""

    def __init__(
        self,
        config: TrainConfig,
        server: str | Sequence[str],
        out: Path,
        timeout_s: float = STEP_TIMEOUT_S,
        reporter: Reporter | None = None,
        retry_for_s: float = 0.0,
    ) -> None:
        """Train on one `server` address or several (one simulation each, stepped at once).

        `retry_for_s` > 0: when a server is lost, wait that long for it to come back.
        """
        self.config = config
        self.retry_for_s = retry_for_s
        self.out = out
        self.reporter: Reporter = reporter or QuietReporter()
        self.say = self.reporter.message
        torch.set_num_threads(config.torch_threads)
        options = {"decision_interval": config.decision_interval, **config.scenario_options}
        servers = [server] if isinstance(server, str) else list(server)
        self.vec = RemoteVectorEnv(
            servers, config.scenario, reward=config.reward, timeout_s=timeout_s, **options
        )
        self.env: RemoteEnv = self.vec.envs[0]
        """Where pre-training and the greedy evaluations run."""
        multi_lane = self._multi_lane()
        features = config.features if config.features != "auto" else ("lc" if multi_lane else "cf")
        lane_change = config.lane_change == "yes" or (config.lane_change == "auto" and multi_lane)
        self.features = FeatureMap(features)
        self.scale = ActionScale.from_schema(self.env.welcome.action)
        self.agent = Agent(
            self.features.dim, 3 if lane_change else 1, config.learner, config.seed,
            n_envs=len(servers),
        )  # fmt: skip
        from agent_client.rl.replay import ReplayBuffer

        self.buffer = ReplayBuffer(config.learner.buffer_size, self.features.dim, config.seed)
        self.rng = np.random.default_rng(config.seed)
        self.idm = IDMDriver()
        self.progress = Progress()
        self.q_bound = q_upper_bound(config.reward, config.learner.gamma)
        self.idm_eval: dict[str, float] | None = None
        self._stop_requested = False
        self._slots: list[_Slot | None] = [None] * len(servers)
        self._episodes_started = 0
        self._losses: list[float] = []

    def _multi_lane(self) -> bool:
        _, info = self.env.reset(seed=self.config.seed)
        return bool(info["observation"].ego.lane_count > 1)

    # ----------------------------------------------------------------------- public

    def run(self, resume: bool = False) -> Progress:
        """Train until `episodes`, convergence (if asked) or a stop signal; always checkpoints."""
        self.out.mkdir(parents=True, exist_ok=True)
        if resume:
            self._restore()
        else:
            (self.out / "config.json").write_text(json.dumps(self.config.to_dict(), indent=2))
        log = RunLog(self.out, resume=resume)
        started = time.monotonic() - self.progress.wall_time
        try:
            with self._signals():
                if self.idm_eval is None and self.config.eval_every > 0:
                    self.say("evaluating the IDM baseline on the evaluation seeds")
                    self.idm_eval = aggregate(self._resilient(lambda: self._evaluate(self.idm)))
                    (self.out / "idm_eval.json").write_text(json.dumps(self.idm_eval, indent=2))
                if self.config.pretrain_idm and self.progress.global_step == 0:
                    self._resilient(self._pretrain)
                self._episodes_started = self.progress.episode
                while self.progress.episode < self.config.episodes and not self._stop_requested:
                    for summary, losses, q_mean in self._resilient(self._train_step):
                        self.progress.episode += 1
                        self.progress.wall_time = time.monotonic() - started
                        row = self._episode_row(summary, losses, q_mean)
                        log.episode(row)
                        self.reporter.episode(row)
                        if self._evaluation_due():
                            evaluation = self._resilient(self._evaluate_policy)
                            self._slots[0] = None  # the evaluation used the first server
                            log.evaluation(evaluation)
                            self.say(evaluation_line(evaluation))
                            if self._converged():
                                self._stop_requested = True
                        if self.progress.episode % self.config.checkpoint_every == 0:
                            self._checkpoint()
                        if self._stop_requested or self.progress.episode >= self.config.episodes:
                            break
        finally:
            self.progress.wall_time = time.monotonic() - started
            self._checkpoint()
            self._save_policy("policy_final.pt")
            if not (self.out / "policy.pt").exists():
                self._save_policy("policy.pt")
            log.close()
        return self.progress

    def _resilient(self, work: Callable[[], T]) -> T:
        """Run `work`; on a lost server (if a retry time is set) or a failed simulator episode,
        reconnect or reset and run it again. The buffer and the counters are kept."""
        failures = 0
        while True:
            try:
                return work()
            except ServerUnavailable as exc:
                if self.retry_for_s <= 0:
                    raise
                self.say(f"{exc}; waiting up to {self.retry_for_s:g} s for the server")
                self._slots = [None] * len(self._slots)
                for env in self.vec.envs:
                    env.reconnect(self.retry_for_s)
                self.progress.reconnects += 1
                self.say(f"reconnected to {', '.join(self.vec.addresses)}; new episodes start")
            except ServerError as exc:
                failures += 1
                if exc.code not in EPISODE_FAILURES or failures >= MAX_FAILURES_IN_A_ROW:
                    raise
                self.progress.failed_episodes += 1
                self._slots = [None] * len(self._slots)
                self.say(f"the simulator failed ({exc}); starting new episodes")

    def request_stop(self) -> None:
        """Finish the current step, checkpoint and return from `run` (safe from handlers)."""
        self._stop_requested = True

    def close(self) -> None:
        self.vec.close()

    # ----------------------------------------------------------------------- episodes

    def _train_step(self) -> list[Finished]:
        """One step on every server (starting episodes where none runs), then the updates due."""
        if self._stop_requested:
            return []
        self._start_episodes()
        slots = [slot for slot in self._slots if slot is not None]
        us, lanes = self._act(slots)
        results = self.vec.step_each(
            [self.scale.to_env(u) for u in us], [LANE_COMMANDS[lane] for lane in lanes]
        )
        finished: list[Finished] = []
        for i, (slot, u, lane, result) in enumerate(zip(slots, us, lanes, results, strict=True)):
            _, reward, terminated, truncated, info = result
            next_obs = info["observation"]
            next_x = self.features(next_obs)
            self.buffer.add(slot.x, u, lane, reward, next_x, terminated)
            slot.states.append(slot.x)
            slot.accelerations.append(u)
            slot.lanes.append(lane)
            slot.recorder.add(next_obs, reward)
            slot.obs, slot.x = next_obs, next_x
            self.progress.global_step += 1
            if terminated or truncated:
                finished.append(self._finish(slot))
                self._slots[i] = None
        for _ in range(self.agent.updates_due(len(slots))):
            metrics = self.agent.update(self.buffer.sample(self.config.learner.batch_size))
            self._losses.append(metrics["critic_loss"])
        return finished

    def _start_episodes(self) -> None:
        """Reset every server without a running episode (at once), each with the next seed."""
        seeds: dict[int, int | None] = {}
        for i, slot in enumerate(self._slots):
            if slot is None:
                seeds[i] = self.config.seed + self._episodes_started
                self._episodes_started += 1
        for i, (_, info) in self.vec.reset_each(seeds).items():
            obs = info["observation"]
            seed = int(info["seed"])
            recorder = Episode(self._episodes_started, seed, self.env.step_length)
            recorder.add(obs)
            self.agent.reset_noise(i)
            self._slots[i] = _Slot(seed, obs, self.features(obs), recorder)

    def _finish(self, slot: _Slot) -> Finished:
        q = self.agent.q_values(np.stack(slot.states), np.array(slot.accelerations))
        q_mean = float(np.mean(np.take_along_axis(q, np.array(slot.lanes)[:, None], axis=1)))
        losses, self._losses = self._losses, []
        return episode_summary(slot.recorder), losses, q_mean

    def _act(self, slots: list[_Slot]) -> tuple[list[float], list[int]]:
        """Warm-up actions before learning starts, the noisy policy afterwards."""
        cfg = self.config
        fraction = min(1.0, self.progress.global_step / max(cfg.noise_decay_steps, 1))
        self.agent.noise_scale = 1.0 + (cfg.noise_final - 1.0) * fraction
        if self.progress.global_step >= cfg.learner.learning_starts:
            us, lanes = self.agent.act_batch(np.stack([slot.x for slot in slots]), explore=True)
            return [float(u) for u in us], [int(lane) for lane in lanes]
        actions = [self._warmup_action(slot.obs) for slot in slots]
        return [u for u, _ in actions], [lane for _, lane in actions]

    def _warmup_action(self, obs: Observation) -> tuple[float, int]:
        cfg = self.config
        if cfg.warmup_policy == "idm":
            acceleration, _ = self.idm.act(obs)
            u = self.scale.to_policy(acceleration) + self.rng.normal(0.0, cfg.learner.noise_sigma)
            lane = (
                int(self.rng.integers(self.agent.n_lane_actions)) if self.rng.random() < 0.05 else 0
            )
            return float(np.clip(u, -1.0, 1.0)), lane
        return float(self.rng.uniform(-1.0, 1.0)), int(self.rng.integers(self.agent.n_lane_actions))

    def _pretrain(self) -> None:
        """Behaviour cloning on IDM's actions, then critic-only updates on that data."""
        cfg = self.config
        self.say(f"pre-training: {cfg.pretrain_episodes} IDM episodes through the bridge")
        states: list[np.ndarray] = []
        targets: list[float] = []

        def remember(before: Observation, action: Any, reward: float, after: Observation) -> None:
            x, u = self.features(before), self.scale.to_policy(action[0])
            self.buffer.add(x, u, 0, reward, self.features(after), after.terminated)
            states.append(x)
            targets.append(u)

        for index in range(cfg.pretrain_episodes):
            seed = PRETRAIN_SEED + 1000 * cfg.seed + index
            run_episode(self.env, self.idm, seed, index, on_step=remember)
        loss = self.agent.behaviour_clone(np.stack(states), np.array(targets), cfg.pretrain_epochs)
        for _ in range(len(states)):
            self.agent.update(self.buffer.sample(cfg.learner.batch_size), actor=False)
        self.say(f"pre-training: actor fitted to {len(states)} IDM actions (MSE {loss:.4f})")

    # ----------------------------------------------------------------------- evaluation

    def _evaluate(self, driver: Any) -> list[EpisodeSummary]:
        cfg = self.config
        return [
            episode_summary(run_episode(self.env, driver, cfg.eval_seed + index, index))
            for index in range(cfg.eval_episodes)
        ]

    def _evaluation_due(self) -> bool:
        every = self.config.eval_every
        return every > 0 and self.progress.episode % every == 0

    def _evaluate_policy(self) -> dict[str, Any]:
        assert self.idm_eval is not None
        driver = PolicyDriver(
            self.agent.policy(self.config.deploy_averaged), self.features, self.scale
        )
        result = aggregate(self._evaluate(driver))
        met = targets_met(result, self.idm_eval)
        progress = self.progress
        progress.passed_in_a_row = progress.passed_in_a_row + 1 if all(met.values()) else 0
        score = sum(met.values()) + result["speed_ratio_to_ceiling"]
        if score >= progress.best_score:
            progress.best_score = score
            self._save_policy("policy.pt")
        evaluation = {
            "episode": progress.episode,
            "global_step": progress.global_step,
            "wall_time": progress.wall_time,
            **result,
            "speed_ratio_to_idm": result["average_speed"] / self.idm_eval["average_speed"],
            **{f"target_{name}": passed for name, passed in met.items()},
            "passed_in_a_row": progress.passed_in_a_row,
        }
        progress.evaluations.append(evaluation)
        return evaluation

    def _converged(self) -> bool:
        progress = self.progress
        if progress.passed_in_a_row < self.config.converged_evals:
            return False
        if progress.converged_episode is None:
            progress.converged_episode = progress.episode
            progress.converged_time = progress.wall_time
            self.say(
                f"converged: {self.config.converged_evals} passing evaluations in a row at "
                f"episode {progress.episode} ({progress.wall_time / 60:.1f} min)"
            )
        return self.config.stop_when_converged

    # ----------------------------------------------------------------------- bookkeeping

    def _episode_row(
        self, summary: EpisodeSummary, losses: list[float], q_mean: float
    ) -> dict[str, Any]:
        return {
            "episode": self.progress.episode,
            "global_step": self.progress.global_step,
            "wall_time": round(self.progress.wall_time, 2),
            **{k: v for k, v in summary.to_dict().items() if k != "episode"},
            "critic_loss": float(np.mean(losses)) if losses else float("nan"),
            "q_mean": q_mean,
            "q_upper_bound": self.q_bound,
            "noise_scale": self.agent.noise_scale,
        }

    def _save_policy(self, name: str) -> None:
        save_policy(
            self.out / name, self.agent, self.features.name, self.scale, self.config.deploy_averaged
        )

    def _checkpoint(self) -> None:
        state = {
            "agent": self.agent.state_dict(),
            "buffer": self.buffer.state_dict(),
            "rng": _generator_state(self.rng),
            "progress": _plain(dataclasses.asdict(self.progress)),
            "idm_eval": self.idm_eval,
            "config": self.config.to_dict(),
        }
        save_checkpoint(self.out / "checkpoint.pt", state)

    def _restore(self) -> None:
        state = load_checkpoint(self.out / "checkpoint.pt")
        saved_dim = state["agent"].get("obs_dim")
        if saved_dim != self.features.dim:
            raise FeatureMismatch(
                f"{self.out}: the run's networks take {saved_dim} features, but feature set "
                f"{self.features.name!r} now has {self.features.dim} (the run was made by an "
                "older version): start a new run"
            )
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.rng.bit_generator.state = state["rng"]
        self.progress = Progress(**state["progress"])
        self.idm_eval = state["idm_eval"]
        self.say(
            f"resumed {self.out} at episode {self.progress.episode}, "
            f"step {self.progress.global_step}, {len(self.buffer)} transitions in the buffer"
        )

    @contextmanager
    def _signals(self) -> Iterator[None]:
        """Ctrl-C and SIGTERM finish the current step, then checkpoint and return."""

        def on_signal(signum: int, frame: FrameType | None) -> None:
            self.request_stop()

        previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)


def _generator_state(rng: np.random.Generator) -> dict[str, Any]:
    return _plain(rng.bit_generator.state)  # type: ignore[no-any-return]


def _plain(value: Any) -> Any:
    """Numbers, strings, lists and dicts only (safe for torch.load(weights_only=True))."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def evaluation_line(evaluation: dict[str, Any]) -> str:
    passed = [
        k.removeprefix("target_") for k, v in evaluation.items() if k.startswith("target_") and v
    ]
    return (
        f"  eval @ {evaluation['episode']}: speed {evaluation['average_speed']:.2f} m/s "
        f"({evaluation['speed_ratio_to_idm']:.3f}x IDM, "
        f"{evaluation['speed_ratio_to_ceiling']:.3f}x ceiling), "
        f"collisions/ep {evaluation['collisions_per_episode']:.2f}, "
        f"jerk>5.6 {100 * evaluation['jerk_share_above_limit']:.2f}%, "
        f"headway<1s {100 * evaluation['headway_share_below_1s']:.2f}% | "
        f"passed: {', '.join(passed) or 'none'} | in a row: {evaluation['passed_in_a_row']}"
    )
