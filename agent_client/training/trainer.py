"""The training loop of the paper's Fig. 1: read the state, score the last action, learn, act.

One learner, one or more remote simulators. Each iteration has its collector send every server
its next command, runs the gradient updates due while the simulators compute, then receives:
the replies become transitions in one replay buffer. Updating while the simulator steps is what
lets the learner keep up with it (docs/learner-design.md, "Speed"). Who steps the servers is the
collector's business: this process in lock-step (`sampling.collect`), or a sampling worker per
server in a process of its own or on Ray (`sampling.chunks`). When and where the policy is
evaluated, and what its verdicts make of the run (the best policy, convergence), is
`evaluations.runner`'s business.

With ``egos`` > 1 every server runs simulations of that many egos, all driven by the one shared
policy, every ego's steps feeding the one buffer (`agent_client.training.sampling.many_egos`); the
evaluations stay one-ego episodes.

What stays here: building the run, the loop, resilience (a lost server is waited for, a failed
simulator episode replaced), checkpoints and signals. Checkpoints make a run resumable; with
one training server the same seed and configuration give the same run (a sampling worker's
exploration noise starts afresh on a resumed one).
"""

from __future__ import annotations

import dataclasses
import json
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar

import numpy as np
import torch

from agent_client.defaults import PRETRAIN_SEED, RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.drivers.episode import run_episode
from agent_client.drivers.idm import IDMDriver
from agent_client.drivers.mobil import IDMMobilDriver
from agent_client.drivers.policy import ActionScale, PolicyDriver, lane_choice, save_policy
from agent_client.drivers.safety import SafetyLayer
from agent_client.drivers.spec import load_driver
from agent_client.envs.remote_env import RemoteEnv
from agent_client.envs.vector_env import RemoteVectorEnv
from agent_client.errors import (
    FeatureMismatch,
    ServerError,
    ServerUnavailable,
    UsageError,
)
from agent_client.rl.checkpoint import load_checkpoint, save_checkpoint
from agent_client.rl.features import FeatureMap
from agent_client.rl.policy import Policy
from agent_client.rl.replay import ReplayBuffer
from agent_client.rl.rewards import TRAFFIC_REWARDS, q_upper_bound
from agent_client.rl.td3 import Agent, resolve_device
from agent_client.training.config import TrainConfig
from agent_client.training.evaluations.pool import EvaluationPool
from agent_client.training.evaluations.reference import Reference
from agent_client.training.evaluations.runner import Evaluations, TrainingSide
from agent_client.training.progress import (
    Profile,
    Progress,
    QuietReporter,
    Reporter,
)
from agent_client.training.run_log import RunLog
from agent_client.training.sampling.chunks import ChunkCollector, chunk_collector
from agent_client.training.sampling.collect import (
    EPISODE_FAILURES,
    MAX_FAILURES_IN_A_ROW,
    Collected,
    LocalCollector,
    Slot,
)
from agent_client.training.sampling.exploration import WarmupDriver, learning, noise_scale_at
from agent_client.training.sampling.many_egos import (
    EgoSlot,
    MultiEgoCollector,
    MultiEgoLink,
    batch_by_ego,
)
from protocol.messages import ROAD_RANGE, Observation, Road
from protocol.version import ROAD_VERSION

T = TypeVar("T")

COMPILED_LOAD_NOTICE_S = 1.0
"""A first update slower than this was the compiled update loading: said as such."""

PROBE_STEPS = 600
"""Decisions of each scenario's first episode driven to see whether its lanes change and a
lane ends along its route (a minute at 0.1 s: an on-ramp's lanes start after the ramp, an
exit's lane ends show within the road ahead's 1000 m)."""

__all__ = ["Progress", "QuietReporter", "Reporter", "Trainer"]


class Trainer:
    """Owns the environments, the agent, the buffer and the run folder."""

    def __init__(
        self,
        config: TrainConfig,
        server: str | Sequence[str],
        out: Path,
        timeout_s: float = STEP_TIMEOUT_S,
        reporter: Reporter | None = None,
        retry_for_s: float = 0.0,
        eval_servers: Sequence[str] = (),
        reset_timeout_s: float = RESET_TIMEOUT_S,
    ) -> None:
        """Train on one `server` address or several (one simulation each, stepped at once);
        evaluate on `eval_servers` in the background, or there while training waits with
        `config.eval_while_training` off (default: inline, on the training servers).

        `retry_for_s` > 0: when a server is lost, wait that long for it to come back.
        """
        self.config = config
        self.retry_for_s = retry_for_s
        self.out = out
        self.reporter: Reporter = reporter or QuietReporter()
        self.say = self.reporter.message
        torch.set_num_threads(config.torch_threads)
        servers = [server] if isinstance(server, str) else list(server)
        overlap = set(servers) & set(eval_servers)
        if overlap:
            raise UsageError(f"{sorted(overlap)[0]} is both a training and an evaluation server")
        options = {"decision_interval": config.decision_interval, **config.scenario_options}
        if config.reward in TRAFFIC_REWARDS:  # it reads every vehicle's speed
            options.setdefault("report_traffic", True)
        reward = config.reward_fn()
        self.vec = RemoteVectorEnv(
            servers, config.scenarios, reward=reward, timeout_s=timeout_s,
            reset_timeout_s=reset_timeout_s, **options,
        )  # fmt: skip
        self.eval_servers = list(eval_servers)
        self.eval_pool: EvaluationPool | None = None
        """The evaluation servers' workers, one process per server; idle-priority ones when
        the evaluations run in the background."""
        try:
            if eval_servers:
                self.eval_pool = EvaluationPool(
                    eval_servers, config.scenarios, config.reward, config.reward_params, options,
                    timeout_s, idle_priority=config.eval_while_training,
                    reset_timeout_s=reset_timeout_s,
                )  # fmt: skip
            self._build(len(servers))
        except BaseException:
            self.close()
            raise

    def _build(self, n_envs: int) -> None:
        config = self.config
        self.env: RemoteEnv = self.vec.envs[0]
        """Where pre-training and inline evaluations run."""
        multi_lane, routed = self._lanes_and_routes()
        self._one_lane = not multi_lane
        """On one lane nobody passes the leader-at-entry: its ceiling bounds any driver's speed."""
        features = config.features
        if features == "auto":
            road = self.env.welcome.protocol >= ROAD_VERSION
            features = ("road" if road and routed else "lc") if multi_lane else "cf"
        lane_change = config.lane_change == "yes" or (config.lane_change == "auto" and multi_lane)
        every = config.lane_decision_every if lane_change else 1
        self.features = FeatureMap(features, lane_phase_every=every)
        residual = config.residual if config.residual != "auto" else "idm+mobil" if routed else ""
        residual = residual.replace("none", "")
        choices = (
            1 if not lane_change else 4 if residual and config.residual_lanes == "default" else 3
        )
        self.lanes = lane_choice(
            choices, every, config.lane_gap_rule, residual, config.lane_route_masks,
            config.residual_lanes,
        )  # fmt: skip
        self.scale = ActionScale.from_schema(
            self.env.welcome.action, residual, config.decision_interval, config.residual_reach,
            config.residual_shield,
        )  # fmt: skip
        self.sampling = config.sampling_on(n_envs, len(self.eval_servers))
        """Where training episodes run: local, processes or ray (auto resolved)."""
        n_envs *= config.egos  # one exploration noise process per ego slot
        self.device = resolve_device(config.device)
        self.agent = Agent(
            self.features.dim, self.lanes.n_choices, config.learner, config.seed, n_envs=n_envs,
            device=self.device,
        )  # fmt: skip
        self.buffer = ReplayBuffer(
            config.learner.buffer_size, self.features.dim, config.seed, self.lanes.n_choices
        )
        self.rng = np.random.default_rng(config.seed)
        self.idm = IDMDriver()
        """Pre-training clones its actions."""
        self.reference = load_driver(
            config.reference if config.reference != "auto" else "idm+mobil" if routed else "idm"
        )
        """The driver evaluations compare the policy with (`TrainConfig.reference`)."""
        eval_seeds = [
            config.eval_seed + i for i in range(config.eval_episodes * len(config.scenarios))
        ]
        self.figures = Reference(eval_seeds, self.env.scenario_for, config.speed_gain)
        """The reference's figures on the evaluation seeds (a seed picks its scenario)."""
        warmup = config.warmup_policy
        if warmup == "auto":
            warmup = "idm+mobil" if self.scale.residual else "random"
        self.warmup = WarmupDriver(warmup, self.scale, config.learner.noise_sigma, self.rng)
        self.progress = Progress()
        self.profile = Profile()
        self.q_bound = q_upper_bound(config.reward, config.learner.gamma, **config.reward_params)
        self.collector = self._make_collector()
        self._pairs = n_envs > 1 and config.learner.policy_delay == 2
        """With several servers the updates due each iteration run as TD3 pairs."""
        self._stop_requested = False
        self._interrupted = False
        """Ctrl-C or SIGTERM asked to stop: a background evaluation is given up, not waited for
        (the checkpoint keeps it: a resumed run starts it again)."""
        self._episodes_started = 0
        self._updates_due = 0
        self._received = 0
        """Transitions the last receive brought (finished episodes' rows count up to theirs)."""
        self._losses: list[float] = []
        self._actor_learned = False
        """The actor has had an update (a residual policy's waits for its burn-in)."""
        self._failures_in_a_row = 0
        self._started = time.monotonic()
        training = TrainingSide(
            envs=self.vec.envs, resilient=self._resilient,
            drop_episodes=self.collector.drop_episodes, policy_state=self._policy_state,
            trained=self._actor_trained, driver=self._driver, save_policy=self._save_policy,
            elapsed=lambda: time.monotonic() - self._started, one_lane=self._one_lane,
        )  # fmt: skip
        # `say` is looked up at each call: a caller may replace the trainer's
        self.evaluations = Evaluations(
            config, self.out, self.reference, self.figures, self.eval_pool, training,
            self.profile, lambda text: self.say(text), self.retry_for_s,
        )  # fmt: skip
        """When the policy is evaluated, where, and what its verdicts make of the run."""

    def _make_collector(self) -> LocalCollector | MultiEgoCollector | ChunkCollector:
        """Who steps the training servers (`self.sampling`): this process in lock-step (one
        multi-ego simulation per server with ``egos`` > 1), or a sampling worker per server."""
        config = self.config
        # The leader-at-entry ceiling costs the server a run-on of up to ~100 ms at every
        # episode end: only the evaluations, whose targets use it, ask for it.
        reset_options = {"report_ceiling": False} if _offers(self.env, "report_ceiling") else {}
        if config.egos > 1:  # one multi-ego simulation per server, in the envs' own sessions
            links = [MultiEgoLink.sharing(env, config.egos) for env in self.vec.envs]
            return MultiEgoCollector(
                links, self.features, self.lanes, self.scale, self._choose_egos,
                self._next_seed, self.agent.reset_noise, reset_options,
            )  # fmt: skip
        if self.sampling != "local":  # a worker per server, in a process or on Ray
            return chunk_collector(
                config, self.vec, self.features, self.lanes, reset_options,
                sampling=self.sampling, residual=self.scale.residual,
                warmup_policy=self.warmup.policy,
                policy_state=self.agent.policy_state_dict,
                global_step=lambda: self.progress.global_step,
                lane_epsilon=lambda: self.agent.lane_epsilon, next_seed=self._next_seed,
                retry_for_s=self.retry_for_s, eval_servers=len(self.eval_servers),
            )  # fmt: skip
        safety = (
            SafetyLayer(config.decision_interval, self.scale.low)
            if config.safety_layer_training
            else None
        )
        return LocalCollector(
            self.vec.envs, self.features, self.lanes, self.scale, self._choose,
            self._next_seed, self.agent.reset_noise, reset_options, safety,
            config.override_penalty, config.learn_own_decision,
        )  # fmt: skip

    def _lanes_and_routes(self) -> tuple[bool, bool]:
        """Whether lanes can be changed on some scenario (a road of several lanes), and
        whether some route makes the ego change them (a lane to leave, or one beside that ends:
        `Road`): seen within the first `PROBE_STEPS` decisions of an episode of each, driven by
        IDM + MOBIL."""
        env, seed = self.env, self.config.seed
        lanes = routed = False
        for index in range(len(env.scenarios)):
            probe = seed + (index - seed) % len(env.scenarios)  # a seed of scenario `index`
            _, info = env.reset(seed=probe)
            obs, driver = info["observation"], IDMMobilDriver()
            for _ in range(PROBE_STEPS):
                lanes = lanes or obs.ego.lane_count > 1
                routed = routed or _lane_ends(obs.road)
                if routed or obs.terminated or obs.truncated:
                    break
                env.send_command(*driver.act(obs))
                obs, _ = env.receive_observation()
        return lanes or routed, routed

    # ----------------------------------------------------------------------- public

    def run(self, resume: bool = False) -> Progress:
        """Train until `episodes`, convergence (if asked) or a stop signal; always checkpoints."""
        self.out.mkdir(parents=True, exist_ok=True)
        if resume:
            self._restore()
        else:
            (self.out / "config.json").write_text(json.dumps(self.config.to_dict(), indent=2))
        log = RunLog(self.out, resume=resume)
        self._started = time.monotonic() - self.progress.wall_time
        try:
            with self._signals():
                self._prepare(log)
                self._episodes_started = self.progress.episode
                while not self._finished():
                    self.evaluations.poll()
                    for slot in self._resilient(self._iteration):
                        if self.progress.episode < self.config.episodes:  # a chunk brings several
                            self._episode_done(slot, log)
                if self.evaluations.pending is not None and not self._interrupted:
                    self.evaluations.collect()
            if isinstance(self.collector, ChunkCollector):  # the servers are this process's again
                self.collector.release(self.env.timeout_s)
        finally:
            try:
                self.progress.wall_time = time.monotonic() - self._started
                self._checkpoint()  # with an evaluation still running: a resumed run redoes it
                self._save_policy("policy_final.pt", self._policy_state())
                if not (self.out / "policy.pt").exists():
                    self._save_policy("policy.pt", self._policy_state())
                (self.out / "profile.json").write_text(json.dumps(self.profile.to_dict(), indent=2))
                log.close()
            finally:
                self.evaluations.cancel()
                if isinstance(self.collector, ChunkCollector):  # a failed run: no worker left
                    self.collector.close()
        self.say(self.profile.line())
        return self.progress

    def request_stop(self) -> None:
        """Finish the current step, checkpoint and return from `run` (safe from handlers); an
        evaluation running in the background is waited for and booked."""
        self._stop_requested = True

    def close(self) -> None:
        """Close every connection and stop the evaluation workers, whatever fails first."""
        try:
            if hasattr(self, "collector"):  # absent when the constructor failed before it
                self.collector.close()  # Ray's sampling workers hold connections of their own
            self.vec.close()
        finally:
            if self.eval_pool is not None:
                self.eval_pool.close()

    # ----------------------------------------------------------------------- the loop

    def _finished(self) -> bool:
        limit = self.config.max_minutes
        if limit is not None and time.monotonic() - self._started > 60 * limit:
            self.say(f"stopping at the time limit of {limit:g} min")
            self._stop_requested = True
        stop = self._stop_requested or self.evaluations.converged
        return stop or self.progress.episode >= self.config.episodes

    def _prepare(self, log: RunLog) -> None:
        """The reference's evaluation (on the evaluation servers, else the training ones), an
        evaluation a resumed run had under way, pre-training."""
        self.evaluations.begin(self.progress, log)
        if self.config.pretrain_idm and self.progress.global_step == 0:
            self._resilient(self._pretrain)

    def _iteration(self) -> list[Slot]:
        """Send, update while the simulators step, receive; returns the episodes that ended."""
        seconds, clock = self.profile.seconds, time.perf_counter
        agent, batch_size = self.agent, self.config.learner.batch_size
        started = clock()
        self.collector.send()
        sent = clock()
        due = self._updates_due
        if self._pairs:  # TD3's updates two at a time (one compiled call); an odd one waits
            due -= due % 2
        if due:
            first = not self.progress.updates
            if first:  # a wait of its own, said as such: no iteration after it pays it
                loading = (
                    "; loading the compiled update first (~4 s; ~15 s to compile it the first "
                    "time on a machine)"
                    if self.config.learner.compile
                    else ""
                )
                self.say(f"learning begins at {self.progress.global_step} env steps{loading}")
            batches = [self.buffer.sample(batch_size) for _ in range(due)]
            actor = not self.scale.residual or self.progress.updates >= self.config.residual_burn_in
            self._losses += [m["critic_loss"] for m in agent.update_many(batches, actor)]
            self._actor_learned = self._actor_learned or actor
            if first and clock() - sent > COMPILED_LOAD_NOTICE_S:
                self.say(
                    f"the compiled update took {clock() - sent:.1f} s to load (once per process; "
                    "the first time on a machine it is compiled, ~15 s, then cached)"
                )
        self.progress.updates += due
        self._updates_due -= due
        updated = clock()
        collected = self.collector.receive()
        received = clock()
        self._store(collected)
        stored = clock()
        seconds["act_and_send"] += sent - started
        seconds["update"] += updated - sent
        seconds["wait_and_receive"] += received - updated
        seconds["bookkeeping"] += stored - received
        self.profile.iterations += 1
        self._failures_in_a_row = 0
        return collected.finished

    def _store(self, collected: Collected) -> None:
        self._received = len(collected.transitions)
        for t in collected.transitions:
            self.buffer.add(t.x, t.u, t.lane, t.reward, t.next_x, t.terminated, t.mask, t.next_mask)
        self.progress.global_step += len(collected.transitions)
        self.progress.failed_episodes += collected.failed_episodes  # a sampling worker's
        self.progress.reconnects += collected.reconnects
        self._updates_due += self.agent.updates_due(len(collected.transitions))

    def _choose(self, slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray]:
        """Warm-up actions before learning starts, the noisy policy afterwards."""
        step = self.progress.global_step
        self.agent.noise_scale = noise_scale_at(self.config, step)
        if learning(self.config, step):
            if len(slots) == 1:
                x, masks = slots[0].x[None], slots[0].mask[None]
            else:
                x, masks = np.stack([s.x for s in slots]), np.stack([s.mask for s in slots])
            return self.agent.act_batch(x, explore=True, masks=masks)
        actions = [self.warmup(slot) for slot in slots]
        return np.array([u for u, _ in actions]), np.array([lane for _, lane in actions])

    def _choose_egos(self, slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray]:
        """`_choose` for many egos: one batch, in which ego slot i always acts with noise
        process i (its own, reset when its drive starts), whichever egos are still driving."""
        step = self.progress.global_step
        if not learning(self.config, step):
            return self._choose(slots)
        self.agent.noise_scale = noise_scale_at(self.config, step)
        x, masks, rows = batch_by_ego(slots)
        us, lanes = self.agent.act_batch(x, explore=True, masks=masks)
        return us[rows], lanes[rows]

    def _next_seed(self) -> int:
        seed = self.config.seed + self._episodes_started
        self._episodes_started += 1
        return seed

    def _own_connections(self) -> list[RemoteEnv]:
        """The connections this process drives: with Ray sampling the training servers belong
        to the workers (which reconnect on their own); the evaluation pool's workers are
        reconnected by the pool."""
        if isinstance(self.collector, LocalCollector | MultiEgoCollector):
            return list(self.vec.envs)
        return []

    def _resilient(self, work: Callable[[], T]) -> T:
        """Run `work`; on a lost server (if a retry time is set) or a failed simulator episode,
        reconnect or reset and run it again. The buffer and the counters are kept."""
        while True:
            try:
                return work()
            except ServerUnavailable as exc:
                if self.retry_for_s <= 0:
                    raise
                self.say(f"{exc}; waiting up to {self.retry_for_s:g} s for the server")
                self._drop_running()
                for env in self._own_connections():
                    env.reconnect(self.retry_for_s)
                if self.eval_pool is not None:
                    self.eval_pool.reconnect(self.retry_for_s)
                self.progress.reconnects += 1
                self.say(f"reconnected to {', '.join(self.vec.addresses)}; new episodes start")
            except ServerError as exc:
                self._failures_in_a_row += 1
                if exc.code not in EPISODE_FAILURES or (
                    self._failures_in_a_row >= MAX_FAILURES_IN_A_ROW
                ):
                    raise
                self.progress.failed_episodes += 1
                self._drop_running()
                self.say(f"the simulator failed ({exc}); starting new episodes")

    def _drop_running(self) -> None:
        """Forget the training episodes under way (a background evaluation the failure ended
        runs again, from its start, when its verdict is due)."""
        self.collector.drop_episodes()
        self._updates_due = 0

    # ----------------------------------------------------------------------- episodes

    def _episode_done(self, slot: Slot, log: RunLog) -> None:
        progress = self.progress
        progress.episode += 1
        progress.wall_time = time.monotonic() - self._started
        row = self._episode_row(slot)
        log.episode(row)
        self.reporter.episode(row)
        collided = int(row["collisions"]) > 0
        learning = progress.global_step >= self.config.learner.learning_starts
        self.evaluations.episode_ended(collided, learning, interrupted=self._interrupted)
        if progress.episode % self.config.checkpoint_every == 0:
            self._checkpoint()

    def _episode_row(self, slot: Slot) -> dict[str, Any]:
        summary = slot.figures()
        q = self.agent.q_values(np.stack(slot.states), np.array(slot.accelerations))
        q_mean = float(np.mean(np.take_along_axis(q, np.array(slot.lanes)[:, None], axis=1)))
        losses, self._losses = self._losses, []
        ego = {"ego": slot.ego_id} if isinstance(slot, EgoSlot) else {}
        ended = self._received if slot.ended_at is None else slot.ended_at
        global_step = self.progress.global_step - self._received + ended
        return {
            "episode": self.progress.episode,
            **ego,
            "global_step": global_step,
            "wall_time": round(self.progress.wall_time, 2),
            **{k: v for k, v in summary.to_dict().items() if k != "episode"},
            "critic_loss": float(np.mean(losses)) if losses else float("nan"),
            "q_mean": q_mean,
            "q_upper_bound": self.q_bound,
            # the schedule's, not the agent's: sampling workers act with their own noise
            "noise_scale": noise_scale_at(self.config, global_step),
        }

    def _pretrain(self) -> None:
        """Behaviour cloning on IDM's actions (IDM + MOBIL's where lanes are learned, its lane
        changes kept in the buffer), then critic-only updates on that data."""
        cfg = self.config
        demo = self.reference if self.lanes.n_choices > 1 else self.idm
        name = getattr(demo, "name", "reference")
        self.say(f"pre-training: {cfg.pretrain_episodes} {name} episodes through the bridge")
        states: list[np.ndarray] = []
        targets: list[float] = []
        lanes: list[int] = []
        masks: list[np.ndarray] = []

        def remember(before: Observation, action: Any, reward: float, after: Observation) -> None:
            x, u = self.features(before), self.scale.to_policy(action[0], before)
            mask, next_mask = self.lanes.mask(before), self.lanes.mask(after)
            lane = self.lanes.index_of(action[1], before) if self.lanes.n_choices > 1 else 0
            lane = lane if mask[lane] else int(np.flatnonzero(mask)[0])  # the buffer: valid ones
            self.buffer.add(x, u, lane, reward, self.features(after),
                            after.terminated, mask, next_mask)  # fmt: skip
            states.append(x)
            targets.append(u)
            lanes.append(lane)
            masks.append(mask)

        for index in range(cfg.pretrain_episodes):
            seed = PRETRAIN_SEED + 1000 * cfg.seed + index
            run_episode(self.env, demo, seed, index, on_step=remember)
        self.collector.drop_episode(0)  # the first server's training episode was replaced
        loss = self.agent.behaviour_clone(np.stack(states), np.array(targets), cfg.pretrain_epochs)
        for _ in range(len(states)):
            self.agent.update(self.buffer.sample(cfg.learner.batch_size), actor=False)
        self.say(f"pre-training: actor fitted to {len(states)} {name} actions (MSE {loss:.4f})")
        if self.lanes.n_choices > 1 and (not self.lanes.reference or self.lanes.n_choices == 4):
            stacked = np.stack(states)
            margin = self.agent.clone_lanes(
                stacked, np.array(targets), np.array(lanes), np.stack(masks), cfg.pretrain_epochs
            )
            self.say(
                f"pre-training: critics lead with {name}'s lane choices (margin loss {margin:.4f})"
            )

    # ----------------------------------------------------------------------- the policy

    def _policy_state(self) -> dict[str, Any]:
        return self.agent.policy_state_dict(self.config.deploy_averaged)

    def _driver(self, policy_state: dict[str, Any]) -> PolicyDriver:
        return PolicyDriver(
            Policy.from_state_dict(policy_state), self.features, self.scale, self.lanes
        )

    def _actor_trained(self) -> bool:
        """Whether the policy has learned anything yet: a residual policy's actor waits for its
        burn-in, and until then it drives as its reference, whose passes say nothing of what
        was learned (they do not count towards convergence)."""
        return not self.scale.residual or self._actor_learned

    # ----------------------------------------------------------------------- files

    def _save_policy(self, name: str, policy_state: dict[str, Any]) -> None:
        save_policy(self.out / name, policy_state, self.features, self.scale, self.lanes)

    def _checkpoint(self) -> None:
        state = {
            "agent": self.agent.state_dict(),
            "buffer": self.buffer.state_dict(),
            "rng": _plain(self.rng.bit_generator.state),
            "progress": _plain(dataclasses.asdict(self.progress)),
            **self.figures.state_dict(),
            "config": self.config.to_dict(),
            "running_evaluation": self.evaluations.running(),
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
        try:
            self.agent.load_state_dict(state["agent"])
            self.buffer.load_state_dict(state["buffer"])
        except ValueError as exc:
            raise UsageError(f"{self.out}: cannot resume this run: {exc}") from exc
        self.rng.bit_generator.state = state["rng"]
        self.progress = Progress(**state["progress"])
        self.figures.load_state_dict(state, self.config.scenarios[0])
        running = state.get("running_evaluation")
        if running is not None and self.figures.known and self.config.eval_every > 0:
            self.evaluations.resume(running)
        self.say(
            f"resumed {self.out} at episode {self.progress.episode}, "
            f"step {self.progress.global_step}, {len(self.buffer)} transitions in the buffer"
        )

    @contextmanager
    def _signals(self) -> Iterator[None]:
        """Ctrl-C and SIGTERM finish the current step, then checkpoint and return; a second
        Ctrl-C interrupts at once (a reply may take up to the step timeout)."""

        def on_signal(signum: int, frame: FrameType | None) -> None:
            self.request_stop()
            self._interrupted = True  # the user is waiting: a background evaluation is given up
            if signum == signal.SIGINT:
                signal.signal(signal.SIGINT, previous[signal.SIGINT])

        previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)


def _offers(env: RemoteEnv, option: str) -> bool:
    return option in env.scenario_options


def _plain(value: Any) -> Any:
    """Numbers, strings, lists and dicts only (safe for torch.load(weights_only=True))."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _lane_ends(road: Road | None) -> bool:
    """Whether the road ahead shows a lane that ends along the route: the ego's own (a change
    to make) or one beside it (0 there: no lane)."""
    if road is None:
        return False
    beside = (road.left_lane_end, road.right_lane_end)
    return bool(road.lanes_to_change) or any(0.0 < end < ROAD_RANGE for end in beside)
