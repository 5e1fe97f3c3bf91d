"""Training configuration: documented defaults, a TOML file, command-line overrides.

Precedence: defaults < ``--config FILE`` < explicit command-line flags < ``--set KEY=VALUE``.
The learner's own hyper-parameters live in the ``[ddpg]`` table (see `DDPGConfig`).

Example file::

    episodes = 400
    reward = "safe"
    [ddpg]
    actor_lr = 3e-4
    hidden_sizes = [64, 64]
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent_client.ddpg import DDPGConfig

RECOMMENDED_LEARNER = DDPGConfig.td3(gamma=0.98, noise="ou", max_grad_norm=1.0)
"""The configuration the learning benchmark measured (docs/learner.md): TD3 (DDPG with twin
critics, delayed actor updates and target smoothing) with a 5 s horizon (gamma 0.98 at 0.1 s
decisions), temporally correlated exploration and gradient clipping. Plain DDPG with the same
settings is `--algo ddpg`; it converged on one seed of three (README, "Measured")."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved as config.json in the run folder)."""

    scenario: str = "cf"
    """Scenario name offered by the server (cf, cflc, or a user's own)."""
    reward: str = "safe"
    """Reward function: safe (ours, recommended), ra1, ra2, ra3, ra4 or rlc."""
    features: str = "auto"
    """Network inputs: cf, lc, or auto (lc on multi-lane roads, else cf)."""
    lane_change: str = "auto"
    """Learn lane changes: yes, no, or auto (yes on multi-lane roads)."""
    episodes: int = 300
    """Training episodes."""
    seed: int = 0
    """Seed of networks, exploration and of the training episodes (episode i uses seed+i)."""
    decision_interval: float = 0.1
    """Seconds per decision; 1.0 is the paper's enlarged time step."""
    scenario_options: dict[str, Any] = field(default_factory=dict)
    """Extra scenario options sent with every reset (e.g. flow)."""
    warmup_policy: str = "idm"
    """Actions before learning starts: idm (baseline + noise) or random."""
    pretrain_idm: bool = False
    """Behaviour-clone the actor on IDM's actions before DDPG (the paper's §4.3.2 tip)."""
    pretrain_episodes: int = 5
    """IDM episodes collected for pre-training."""
    pretrain_epochs: int = 30
    """Passes over the IDM data when fitting the actor."""
    noise_final: float = 0.2
    """Exploration noise scale at the end of the decay (1 = DDPGConfig.noise_sigma)."""
    noise_decay_steps: int = 100_000
    """Environment steps over which the noise scale decays linearly from 1 to noise_final."""
    eval_every: int = 10
    """Greedy evaluation every N episodes (0 disables)."""
    eval_episodes: int = 10
    """Episodes per greedy evaluation."""
    eval_seed: int = 100_000
    """Seed of the first evaluation episode (disjoint from training seeds)."""
    stop_when_converged: bool = False
    """Stop after `converged_evals` consecutive evaluations meeting every target."""
    converged_evals: int = 3
    """Consecutive passing evaluations that count as converged."""
    checkpoint_every: int = 10
    """Write a checkpoint every N episodes (and on Ctrl-C / SIGTERM)."""
    deploy_averaged: bool = True
    """Evaluate and save the target (Polyak-averaged) networks: a smoothed policy that does
    not jump with every gradient step."""
    torch_threads: int = 1
    """torch intra-op threads (1 is fastest for small networks on a shared CPU)."""
    ddpg: DDPGConfig = field(default_factory=lambda: RECOMMENDED_LEARNER)
    """Learner hyper-parameters (default: `RECOMMENDED_LEARNER`)."""

    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "ddpg"}
        d["ddpg"] = self.ddpg.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        return apply_overrides(cls(), d)


def apply_overrides(config: TrainConfig, values: dict[str, Any]) -> TrainConfig:
    """A copy of `config` with `values` (nested ``ddpg`` table allowed); unknown keys raise."""
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"unknown training settings {sorted(unknown)}; known: {sorted(known)}")
    top = {k: v for k, v in values.items() if k != "ddpg"}
    ddpg = config.ddpg
    if "ddpg" in values:
        ddpg_values = values["ddpg"]
        if isinstance(ddpg_values, DDPGConfig):
            ddpg = ddpg_values
        else:
            ddpg = DDPGConfig.from_dict({**ddpg.to_dict(), **ddpg_values})
    return dataclasses.replace(config, **top, ddpg=ddpg)


def load_config_file(path: Path) -> dict[str, Any]:
    """Settings from a TOML (or JSON) file."""
    text = path.read_text()
    if path.suffix == ".json":
        loaded: dict[str, Any] = json.loads(text)
        return loaded
    return tomllib.loads(text)


def parse_assignment(text: str) -> dict[str, Any]:
    """``KEY=VALUE`` or ``ddpg.KEY=VALUE`` (VALUE as JSON when it parses) to a nested dict."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise ValueError(f"expected KEY=VALUE, got {text!r}")
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if key.startswith("ddpg."):
        return {"ddpg": {key[len("ddpg.") :]: value}}
    return {key: value}
