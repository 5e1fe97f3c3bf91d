"""Training configuration: documented defaults, a TOML file, command-line overrides.

Precedence: defaults < the scenario's recommended settings (`recommended`) < ``--config FILE`` <
explicit command-line flags < ``--set KEY=VALUE``.
The learner's own hyper-parameters live in the ``[learner]`` table (see `TD3Config`); runs
written before it was renamed call it ``[ddpg]``, which is still read.

Example file::

    episodes = 400
    reward = "safe"
    [learner]
    actor_lr = 3e-4
    hidden_sizes = [64, 64]
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agent_client.defaults import DEFAULT_SCENARIO, TRAINING_EVALUATION_SEED, TRAINING_SEED
from agent_client.errors import UsageError
from agent_client.rl.td3 import TD3Config, parse_device
from agent_client.training.sampling.cores import usable_cores

SAMPLING_KINDS = ("auto", "local", "processes", "ray")
"""Where training episodes run: lock-step in the learner's process, or sampling workers
(`agent_client.training.sampling.chunks`) in processes of their own or on Ray; auto chooses
between the first two (`TrainConfig.sampling_on`)."""

SERVERS_PER_CORE = 2
"""Up to this many training servers per core, `auto` samples in processes: measured faster
than lock-step at 1 to 2 per core, learner included (docs/learner-design.md, "Sampling apart
from the update")."""


if TYPE_CHECKING:
    from agent_client.rl.rewards import RewardFn

LEARNER = "learner"
"""The table of the learner's own hyper-parameters."""
LEGACY_LEARNER = "ddpg"
"""Its name before 0.2, still read from older runs' config.json and ``--set ddpg.KEY``."""
REWARD_PARAMS = "reward_params"
"""The table of the reward's parameters (``--set reward_params.KEY=VALUE``)."""

RECOMMENDED_LEARNER = TD3Config.td3(
    gamma=0.98, noise="ou", max_grad_norm=1.0, batch_size=128, action_l2=0.1, smoothness=5.0
)
"""The recommended learner (docs/learner.md): TD3 (DDPG with twin critics, delayed actor updates
and target smoothing) with a 5 s horizon (gamma 0.98 at 0.1 s decisions), temporally correlated
exploration, gradient clipping, minibatches of 128, a small cost on the action (keeps the actor
out of tanh saturation, where the crash phase after learning starts locks it) and CAPS's
smoothness term. Plain DDPG with the same settings is `--algo ddpg`."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved as config.json in the run folder)."""

    scenario: str | list[str] = DEFAULT_SCENARIO
    """Scenario offered by the server (cf, cflc, merge, exit, lanedrop, or a user's own), or a
    list of them: one policy over all, each episode driving the one its seed picks, converged
    when every scenario meets its collision, route-end and ceiling targets and the whole
    evaluation its jerk, headway and speed targets (`agent_client.evaluation.targets.judge`)."""
    reward: str = "safe"
    """Reward function: safe (ours, recommended), ra1, ra2, ra3, ra4 or rlc."""
    reward_params: dict[str, float] = field(default_factory=dict)
    """Keyword parameters of the reward, e.g. ``{desired_headway = 1.1}`` for safe (the fields
    of its class in `agent_client.rl.rewards`); {}: the reward's defaults."""
    features: str = "auto"
    """Network inputs: cf, lc, road, or auto: road where a lane ends along some scenario's route
    (from a server that reports the road ahead, protocol 1.6), lc on other roads of several
    lanes (cflc, as measured), cf on one lane."""
    residual: str = "auto"
    """What the actor's acceleration is: none (the acceleration itself) or idm+mobil (a
    correction of up to ±2 m/s² of IDM + MOBIL's acceleration, residual policy learning: the
    policy starts as good as the reference and learns to do better); auto: idm+mobil where some
    scenario's route makes the ego change lanes (a lane end or an exit), else none."""
    residual_reach: float = 2.0
    """m/s²: how far a residual actor's output reaches from the acceleration its reference
    wants (at ±1). 9 covers the whole action range from any reference acceleration: the policy
    chooses any acceleration, the reference's where its output is 0."""
    residual_shield: bool = True
    """Fade a residual policy's reach out where its reference says the drive is at stake (a
    lane end close, a standstill): there the reference drives. False: the policy decides there
    too; the safety layer overrides it only where a stated rule says the drive is at stake,
    counted."""
    residual_lanes: str = "follow"
    """How a residual policy's lane choice relates to its reference's: follow (the reference's
    change is the only choice), default (the reference's change is the first of four choices,
    keep / left / right the policy's own: it starts as the reference and leaves it where a
    choice of its own is worth more) or own (keep / left / right alone)."""
    residual_burn_in: int = 20_000
    """Critic updates before a residual policy's actor learns (the burn-in of Silver et al.
    2018: the critic first learns the values of the reference's driving, so that the actor's
    first gradients, on an untrained critic, do not undo it)."""
    reference: str = "auto"
    """The driver the evaluations compare the policy with, on the same seeds (``as fast as``):
    a driver spec (idm, idm+mobil, idm:PARAMS.json, a policy file), or auto: idm+mobil where
    some scenario's route makes the ego change lanes (a lane end or an exit), else idm (lane
    keeping). `cflc`'s recommended settings name idm+mobil."""
    lane_change: str = "auto"
    """Learn lane changes: yes, no, or auto (yes on multi-lane roads)."""
    episodes: int = 300
    """Training episodes."""
    max_minutes: float | None = None
    """Stop after this many minutes of wall time (checkpointed, like a Ctrl-C); None: no limit."""
    seed: int = TRAINING_SEED
    """Seed of networks, exploration and of the training episodes (episode i uses seed+i)."""
    decision_interval: float = 0.1
    """Seconds per decision; 1.0 is the paper's enlarged time step."""
    lane_decision_interval: float = 1.0
    """Seconds between two lane decisions (rounded to whole decisions, at least one): in
    between, the policy only chooses the acceleration. A lane change is a decision, not a
    request repeated every 0.1 s (docs/learner.md)."""
    lane_gap_rule: bool = True
    lane_route_masks: bool = True
    """Near the end of a lane the route must leave, the change towards the route is the only
    lane choice, and changes away from it are masked (`agent_client.rl.lanes.LaneChoice`).
    False: the policy decides its mandatory lane changes as well; the safety layer asks for the
    change only where the lane end is about to be missed (counted)."""
    """Mask lane changes into gaps the observation shows shorter than a safe driver's secure
    gap (`agent_client.rl.lanes.secure_gap`): asked for only when they can happen."""
    scenario_options: dict[str, Any] = field(default_factory=dict)
    """Extra scenario options sent with every reset (e.g. flow)."""
    egos: int = 1
    """Egos per training simulation (protocol 1.4): more than 1 drives that many egos in every
    server's simulation with the one shared policy, every ego's steps feeding the one replay
    buffer, one training episode per ego's drive (docs/learner.md, "Many egos: one shared
    policy"); evaluations stay one-ego. 1: one ego per server, as before."""
    warmup_policy: str = "auto"
    """Actions before learning starts: random (uniform; the critic sees stops and crashes, not
    only a baseline's driving: measured best on cf and cflc, docs/learner-design.md), idm (IDM +
    noise), idm+mobil (with its lane changes, those a route needs included, + noise; a residual
    policy's zero plus noise), or auto: idm+mobil for a residual policy, else random."""
    pretrain_idm: bool = False
    """Behaviour-clone the actor on IDM's actions before TD3 (the paper's §4.3.2 tip); where
    lanes are learned on the reference's (IDM + MOBIL), its lane changes kept in the buffer."""
    pretrain_episodes: int = 5
    """IDM episodes collected for pre-training."""
    pretrain_epochs: int = 30
    """Passes over the IDM data when fitting the actor."""
    noise_final: float = 0.2
    """Exploration noise scale at the end of the decay (1 = TD3Config.noise_sigma)."""
    noise_decay_steps: int = 100_000
    """Environment steps over which the noise scale decays linearly from 1 to noise_final."""
    eval_every: int = 10
    """Greedy evaluation every N episodes (0 disables), the first N episodes after learning
    began (before, the policy is the initial one)."""
    eval_episodes: int = 10
    """Episodes per greedy evaluation."""
    eval_gate: int = 3
    """Evaluate only when the last `eval_gate` training episodes ended without a collision (a
    policy that still crashes with exploration noise is not worth `eval_episodes` greedy ones); 0
    evaluates every `eval_every` episodes regardless."""
    eval_screen: bool = True
    """End an evaluation as soon as its first seeds (in order) have failed a target for
    certain, whatever the others give (`agent_client.evaluation.targets.FailureScreen`); False:
    only at a collision. A pass is unchanged: every episode, every target."""
    eval_budget: float | None = 0.4
    """Evaluation env steps per training env step after a failed evaluation: the next waits
    until training has driven the failed one's steps / `eval_budget` more (an evaluation step
    costs about half a training step, no update: 0.4 keeps them near 15 % of the time). After a
    pass the next runs when due, so passes in a row stay `eval_every` apart. The same
    evaluations of `eval_episodes` episodes, fewer while the policy fails; counted in steps, not
    seconds, so a run stays repeatable. None: evaluate whenever due."""
    eval_while_training: bool = True
    """With evaluation servers (`agent-client train --eval-server`): evaluate on them in the
    background, their workers in the kernel's idle scheduling class (start the servers with
    `sim-server --idle-priority`), each verdict read at the next episode where another
    evaluation may be due (the next multiple of `eval_every`); one that could complete
    convergence runs while training waits. The run is the one False gives: training waits for
    every evaluation (docs/learner.md, "Evaluations during training")."""
    eval_seed: int = TRAINING_EVALUATION_SEED
    """Seed of the first evaluation episode (disjoint from training seeds)."""
    safety_layer_training: bool = False
    """Train through the safety layer (`agent_client.drivers.safety`), as the policy drives
    when evaluated and deployed: exploration never runs a red light or into a vehicle it could
    still avoid; `override_penalty` is taken off the reward of an overridden decision, stored
    as executed or as the policy's own (`learn_own_decision`), so that the policy learns not
    to need the layer. (Episodes of many egos, ``egos`` > 1, are not shielded.)"""
    override_penalty: float = 1.0
    """Reward taken off a decision the safety layer overrode in training (the most one step of
    the `safe` reward's driving pays)."""
    learn_own_decision: bool = False
    """Where the safety layer overrode a decision in training, store the policy's own decision
    (charged `override_penalty`) instead of the executed one: the penalty then falls on what
    the policy chose, as post-posed shielding punishes the unsafe action (Alshiekh et al.
    2018), where otherwise it falls on the layer's choice, which the actor never proposed."""
    speed_gain: float = 0.0
    """How much faster than the reference a converged policy must drive, as a share of the
    reference's speed on the same seeds (0: as fast; the integrated driver over the built-in
    roads asks 0.01: better than the reference, not equal to it)."""
    stop_when_converged: bool = False
    """Stop after `converged_evals` consecutive evaluations meeting every target."""
    converged_evals: int = 3
    """Consecutive passing evaluations that count as converged."""
    checkpoint_every: int = 10
    """Write a checkpoint every N episodes (and on Ctrl-C / SIGTERM)."""
    deploy_averaged: bool = True
    """Evaluate and save the slow average of the networks (`learner.deploy_tau`): a smoothed
    policy that does not jump with every gradient step."""
    torch_threads: int = 1
    """torch intra-op threads (1 is fastest for small networks on a shared CPU)."""
    device: str = "cpu"
    """Where the networks learn: cpu, cuda, cuda:N, or auto (a CUDA GPU if torch sees one, else
    the CPU). Acting, the replay buffer and the sampling workers stay on the CPU. Not auto by
    default: the GPU path has not been measured yet (docs/learner.md, "On a GPU")."""
    sampling: str = "auto"
    """Where training episodes run: local (this process steps every server at once, the learner
    updating while they simulate), processes (one sampling process per server, each with a
    copy of the policy, feeding the replay buffer while the learner updates), ray (the same
    workers as Ray actors, across a cluster; docs/ray.md), or auto (`sampling_on`)."""
    sampling_chunk: int = 64
    """sampling = processes or ray: steps a worker takes per request."""
    chunks_in_flight: int = 1
    """sampling = processes or ray: requests each worker has at a time (2: it starts its next
    chunk as soon as it sends one, not when the learner, done with its updates, asks again;
    7-10 % more env steps/s, measured not to pay on cf seeds: docs/learner-design.md)."""
    policy_sync_every: int = 500
    """sampling = processes or ray: transitions between two refreshes of the workers' policy
    copies."""
    ray_address: str = ""
    """sampling = ray: "" starts a local Ray, "auto" joins this machine's Ray cluster,
    ray://HOST:10001 one through Ray Client."""
    simulators: int = 0
    """sampling = processes or ray: N sampling workers, each starting a simulator of its own
    beside it (`simulator_args`; with Ray wherever Ray places it), stopped with it; 0: one
    worker per server."""
    simulator_args: str = "--backend sumo"
    """The sim-server command line of the simulators the learner starts (without --bind)."""
    learner: TD3Config = field(default_factory=lambda: RECOMMENDED_LEARNER)
    """Learner hyper-parameters (default: `RECOMMENDED_LEARNER`)."""

    def _check_reference(self) -> None:
        if self.reference == "sumo":
            raise UsageError(
                "reference 'sumo' cannot be the trainer's reference: the simulator's own driver "
                "sends no actions to clone or evaluate beside the policy's; use idm, idm+mobil, "
                "idm:PARAMS.json or a policy file (evaluate --reference sumo compares with it)"
            )
        if self.residual_burn_in < 0:
            raise UsageError(f"residual_burn_in must be >= 0, got {self.residual_burn_in}")

    def _check_sampling(self) -> None:
        if self.simulators < 0:
            raise UsageError(f"simulators must be at least 0, got {self.simulators}")
        if self.simulators and self.sampling == "local":  # auto: processes start them
            raise UsageError(
                f"simulators {self.simulators} needs sampling workers to start them beside: "
                "--sampling processes (on this machine) or --sampling ray"
            )
        if self.egos > 1 and self.simulators:
            raise UsageError(
                f"egos {self.egos} with simulators {self.simulators}: the sampling workers that "
                "start simulators drive one ego each (train many egos on --server addresses)"
            )
        if self.egos > 1 and self.sampling not in ("auto", "local"):
            raise UsageError(
                f"egos {self.egos} needs sampling = local: the sampling workers drive one "
                f"ego each (train many egos without --sampling {self.sampling})"
            )

    def __post_init__(self) -> None:
        from agent_client.rl.features import FEATURE_SETS
        from agent_client.rl.rewards import REWARDS

        choices = {
            "reward": tuple(REWARDS),
            "features": ("auto", *FEATURE_SETS),
            "lane_change": ("auto", "yes", "no"),
            "warmup_policy": ("auto", "idm", "idm+mobil", "random"),
            "residual": ("auto", "none", "idm+mobil"),
            "residual_lanes": ("follow", "default", "own"),
            "sampling": SAMPLING_KINDS,
        }
        for name, valid in choices.items():
            if getattr(self, name) not in valid:
                raise UsageError(
                    f"{name} {getattr(self, name)!r} is not one of: {', '.join(valid)}"
                )
        self.reward_fn()  # a parameter the reward lacks, or a bad value, is a UsageError
        names = self.scenarios
        if not names or not all(isinstance(n, str) and n for n in names):
            raise UsageError(f"scenario must be a name or a list of names, got {self.scenario!r}")
        if len(set(names)) != len(names):
            raise UsageError(f"scenario lists a scenario twice: {', '.join(names)}")
        self._check_reference()
        for setting in dataclasses.fields(self):  # --set eval_screen=False is not false
            value = getattr(self, setting.name)
            if isinstance(setting.default, bool) and not isinstance(value, bool):
                raise UsageError(f"{setting.name} must be true or false, got {value!r}")
        for name in (
            "episodes",
            "egos",
            "eval_episodes",
            "converged_evals",
            "checkpoint_every",
            "sampling_chunk",
            "chunks_in_flight",
            "policy_sync_every",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UsageError(f"{name} must be a whole number of at least 1, got {value!r}")
        self._check_sampling()
        parse_device(self.device)  # a typo now, not when the trainer starts
        if self.eval_budget is not None and not self.eval_budget > 0:
            raise UsageError(f"eval_budget must be > 0 (or None: no limit), got {self.eval_budget}")
        if not 0.0 <= self.speed_gain < 1.0:
            raise UsageError(f"speed_gain must be within [0, 1), got {self.speed_gain}")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise UsageError(f"max_minutes must be > 0, got {self.max_minutes}")
        if self.decision_interval <= 0:
            raise UsageError(f"decision_interval must be > 0, got {self.decision_interval}")
        if self.lane_decision_interval <= 0:
            raise UsageError(
                f"lane_decision_interval must be > 0, got {self.lane_decision_interval}"
            )

    def sampling_on(self, servers: int, evaluation_servers: int, cores: int | None = None) -> str:
        """The sampling a run on `servers` training servers uses: `sampling` itself, or for
        auto a sampling process per server where the servers are free for them (one ego per
        simulation; evaluations on servers of their own, or none) on two cores or more (the
        learner is not alone with them on one), up to `SERVERS_PER_CORE` servers per core;
        else local (docs/learner.md, "Sampling")."""
        if self.sampling != "auto":
            return self.sampling
        if self.simulators:
            return "processes"
        cores = usable_cores() if cores is None else cores
        free = self.eval_every == 0 or evaluation_servers > 0
        fits = cores >= 2 and servers <= SERVERS_PER_CORE * cores
        return "processes" if self.egos == 1 and free and fits else "local"

    def reward_fn(self) -> RewardFn:
        """The reward `reward` with `reward_params`; `UsageError` naming a bad parameter."""
        from agent_client.rl.rewards import REWARDS, make_reward

        if not isinstance(self.reward_params, dict):
            raise UsageError(f"reward_params must be a table, got {self.reward_params!r}")
        known = inspect.signature(REWARDS[self.reward]).parameters
        for key, value in self.reward_params.items():
            if key not in known:
                raise UsageError(
                    f"reward_params.{key}: reward {self.reward} has no such parameter; "
                    f"its parameters: {', '.join(known)}"
                )
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise UsageError(f"reward_params.{key} must be a number, got {value!r}")
        try:
            return make_reward(self.reward, **self.reward_params)
        except ValueError as exc:
            raise UsageError(f"reward_params for {self.reward}: {exc}") from exc

    @property
    def scenarios(self) -> tuple[str, ...]:
        """The scenarios trained on (one, or several: see `scenario`)."""
        return (self.scenario,) if isinstance(self.scenario, str) else tuple(self.scenario)

    @property
    def label(self) -> str:
        """The scenarios as a name: ``cf``, ``merge+exit+cflc``."""
        return "+".join(self.scenarios)

    @property
    def lane_decision_every(self) -> int:
        """Decisions per lane decision: `lane_decision_interval` in whole decisions, at least one
        (so any `decision_interval` works, also on a one-lane road where lanes are not learned)."""
        return max(1, round(self.lane_decision_interval / self.decision_interval))

    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != LEARNER}
        d[LEARNER] = self.learner.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        return apply_overrides(cls(), d)


RECOMMENDED: dict[str, dict[str, Any]] = {
    "cf": {
        "eval_budget": 1.0,
        "reward_params": {
            "desired_headway": 1.1,
            "headway_far_sigma": 0.5,
            "headway_far_weight": 0.5,
        },
        LEARNER: {"deploy_tau": 0.001},
    },
    "cflc": {
        "reward_params": {"headway_sigma": 0.2},
        "residual": "idm+mobil",
        "residual_reach": 9.0,
        "residual_shield": False,
        "residual_lanes": "default",
        "reference": "idm+mobil",
        "pretrain_idm": True,
        "speed_gain": 0.05,
        "safety_layer_training": True,
        "override_penalty": 2.0,
    },
}
"""Settings measured best for one scenario, on top of the defaults (`recommended`; docs/results.md,
"Measured: learning car following on cf" and "... car following and lane changing on cflc"): on
cf, the safe reward's knee 0.1 s closer and a far leader costing part of the drive term (closing
up pays), a slower average of the deployed actor, and after a failed evaluation a wait of its
steps only; on cflc, a steeper headway term below the knee (following under the evaluation's
1 s costs twice as much), and the integrated driver's parametrisation of its acceleration and
lanes (`INTEGRATED`'s: its own, starting from IDM + MOBIL's, the safety layer in training)
judged against IDM + MOBIL, converged only 5 % faster than it (on 100 tuning seeds, 3 % gave
a policy 2.2 % faster than IDM + MOBIL, 5 % one 3.3 % faster; docs/results.md, "The integrated
driver"); unlike `INTEGRATED`, the `lc` features (cflc has no light and no lane end to read),
the route's lane masks (none binds on cflc) and five demonstrated episodes. configs/cf.toml and
configs/cflc.toml spell them out."""


INTEGRATED: dict[str, Any] = {
    "residual": "idm+mobil",
    "residual_reach": 4.0,
    "residual_shield": False,
    "residual_lanes": "default",
    "features": "drive",
    "lane_route_masks": False,
    "reference": "idm+mobil",
    "pretrain_idm": True,
    "pretrain_episodes": 10,
    "speed_gain": 0.01,
    "safety_layer_training": True,
    "override_penalty": 2.0,
    "learn_own_decision": True,
    "reward_params": {"headway_sigma": 0.2},
    LEARNER: {"deploy_tau": 0.0002},
}
"""The integrated driver over several scenarios (the built-in roads: `cflc`, `merge`, `exit`,
`lanedrop`, `urban`): it decides its acceleration and every lane change itself, the route's
mandatory ones included: its actor's output reaches ±4 m/s² from the acceleration IDM + MOBIL
wants (that acceleration where the output is 0: it starts from the reference and the action
cost pulls it back there where nothing is to be gained; ±4 is the setting the roads training
converged with on 12-07: docs/results.md, "The integrated driver"), a slow average of the
deployed actor (`deploy_tau` 0.0002, a half-life of ~3,500 actor updates, some nine episodes:
at 0.001 the evaluated policy changed between evaluations two episodes apart, and the roads
training, which asks three passed in a row, converged on 2 of 3 seeds, on 5 of 5 at 0.0002),
no fade-out where the drive is at stake, its own lane choices
(learned Q-heads that start from IDM + MOBIL's choices by a margin, no lane masks of the
route's); the safety layer overrides it only where
the drive is at stake, in training too, counted and charged to the policy's own decision
(`learn_own_decision`: with the faster average the roads training converged on 2 of 3 seeds
so, 1 of 3 with the penalty on the layer's decision; docs/results.md, "The integrated
driver"). It reads the
stop line and the next light (features ``drive``), and converges only 1 % faster than IDM +
MOBIL on the same seeds
(docs/learner.md, "The integrated driver")."""


def recommended(scenario: str | list[str] = DEFAULT_SCENARIO, reward: str = "safe") -> TrainConfig:
    """The recommended configuration for `scenario` and `reward`: the defaults, and where a scenario
    has settings of its own (`RECOMMENDED`) those (its reward parameters only with the reward they
    are for, safe); several scenarios get `episodes` each. `agent-client train` starts from it; a
    ``--config`` file, flags and ``--set`` override it."""
    config = TrainConfig(scenario=scenario, reward=reward)
    names = config.scenarios
    own = dict(RECOMMENDED.get(names[0], {})) if len(names) == 1 else dict(INTEGRATED)
    if len(names) > 1:  # as many episodes of each scenario as one alone would get
        own["episodes"] = config.episodes * len(names)
    if reward != "safe":
        own.pop(REWARD_PARAMS, None)
    return apply_overrides(config, own) if own else config


def apply_overrides(config: TrainConfig, values: dict[str, Any]) -> TrainConfig:
    """A copy of `config` with `values` (a nested ``learner`` table is merged into the learner's
    settings); an unknown or invalid setting raises `UsageError` naming it and the valid ones."""
    values = dict(values)
    if LEGACY_LEARNER in values:  # config.json of a run written before the rename
        values[LEARNER] = {**values.pop(LEGACY_LEARNER), **values.get(LEARNER, {})}
    known = [f.name for f in dataclasses.fields(TrainConfig)]
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise UsageError(f"unknown training setting {unknown[0]!r}; known: {', '.join(known)}")
    if isinstance(values.get(REWARD_PARAMS), dict):  # merged, as the learner's table is
        values[REWARD_PARAMS] = {**config.reward_params, **values[REWARD_PARAMS]}
    top = {k: v for k, v in values.items() if k != LEARNER}
    learner = config.learner
    if LEARNER in values:
        given = values[LEARNER]
        learner = (
            given
            if isinstance(given, TD3Config)
            else TD3Config.from_dict({**learner.to_dict(), **given})
        )
    try:
        return dataclasses.replace(config, **top, learner=learner)
    except (TypeError, ValueError) as exc:
        raise UsageError(str(exc)) from exc


def load_config_file(path: Path) -> dict[str, Any]:
    """Settings from a TOML (or JSON) file; a missing or malformed file is a `UsageError`."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise UsageError(f"--config {path}: {exc.strerror or exc}") from exc
    try:
        loaded: dict[str, Any] = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise UsageError(
            f"--config {path}: not valid {path.suffix.lstrip('.') or 'TOML'}: {exc}"
        ) from exc
    if not isinstance(loaded, dict):
        raise UsageError(f"--config {path}: expected a table of settings")
    return loaded


def parse_assignment(text: str) -> dict[str, Any]:
    """``KEY=VALUE``, ``learner.KEY=VALUE`` or ``reward_params.KEY=VALUE`` (VALUE as JSON when
    it parses) to a nested dict."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise UsageError(f"--set {text!r}: expected KEY=VALUE")
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    table, dot, name = key.partition(".")
    if dot and table in (LEARNER, LEGACY_LEARNER):
        return {LEARNER: {name: value}}
    if dot and table == REWARD_PARAMS:
        return {REWARD_PARAMS: {name: value}}
    return {key: value}
