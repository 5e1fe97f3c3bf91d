"""The learner side's defaults, in one place: scenario, deadlines and seed bands.

The seed bands keep every kind of episode apart, so that no evaluation ever drives an episode
the policy was trained on, and no comparison uses the seeds that chose the policy.
"""

from __future__ import annotations

DEFAULT_SCENARIO = "cf"
"""The paper's car-following case; every server built on this project offers it."""

STEP_TIMEOUT_S = 10.0
"""Seconds to wait for the reply to a hello or a step."""
RESET_TIMEOUT_S = 300.0
"""Seconds to wait for the reply to a reset: it may build a network, warm a large one up and
wait for the ego to enter."""
CLOSE_TIMEOUT_S = 1.0
"""Seconds to wait for the goodbye of a server that may be gone."""

INSERTION_ATTEMPTS = 5
"""Resets tried when the ego cannot enter (``insertion_failed``) before giving up, each with
another seed (`INSERTION_RETRY_SEED_STRIDE`)."""
INSERTION_RETRY_SEED_STRIDE = 2**27
"""Retry k of seed s uses seed (s + k * stride) mod 2^31: far from every seed band below, so a
retried episode is never another episode of the same run."""

TRAINING_SEED = 0
"""Training episode i of a run with seed s uses seed s + i."""
TRAINING_EVALUATION_SEED = 100_000
"""First seed of the greedy evaluations during training (they choose ``policy.pt``)."""
EVALUATION_SEED = 200_000
"""First seed of `agent-client evaluate`: disjoint from training and from the evaluations that
chose the policy."""
TEST_SEED = 500_000
"""First of the table's test seeds (benchmarks/test_seeds.json): fixed before any result on
them, never trained, evaluated during training or tuned on."""
CALIBRATION_SEED = 300_000
"""First seed of the episodes recorded for `agent-client calibrate-idm`."""
CALIBRATION_EPISODES = 5
"""Episodes `agent-client calibrate-idm` records by default: each one gives the car following of
every background vehicle (on `cf` 50-85 followers), not of one stand-in."""
PRETRAIN_SEED = 1_000_000
"""First seed of the IDM episodes recorded for behaviour cloning (`--pretrain-idm`)."""
