"""Train a policy for the ring that damps its stop-and-go waves (docs/learner-design.md, its end).

Starts its own ``sim-server --backend sumo`` on a free loopback port (waits for its readiness
line, stops it at the end) and runs ``agent-client train`` on the ``ring`` scenario with the
``wave`` reward (agent_client/rl/rewards.py) and the options `benchmarks/mixed_autonomy.py`
measures with: 22 vehicles on 230 m, EIDM humans, a 300 s warm-up (the waves have formed when
the client takes over), the unreasonable-stop rule off (``stop_patience`` 3600 s: stopping in a
wave does not end the drive), ``report_traffic`` on (the reward reads every vehicle's speed).
Training episodes are 120 s after the hand-over, decisions every 0.5 s (gamma 0.98: a 25 s
horizon, about half the wave's period on this ring), no greedy evaluations (the ring reports no
leader-at-entry ceiling, so they cannot rank policies: the run's policy.pt is its final one),
and by default the recommended learner without its action cost (``action_l2`` pulls the
normalised action to 0, which on the ego's bounds of -6 to 3 m/s^2 is braking at 1.5 m/s^2)
and with a lighter smoothness term (1 instead of 5); ``--set learner.action_l2=0.1 --set
learner.smoothness=5`` restores the recommended learner. What each trained, measured with
`benchmarks/mixed_autonomy.py`: docs/learner-design.md, "Learning to damp the ring's waves".

    python benchmarks/ring_training.py --egos 4 --minutes 14 --out runs/ring-policy/wave2-4ego
    python benchmarks/ring_training.py --egos 1 --out runs/ring-policy/wave-1ego \\
        --set learner.action_l2=0.1 --set learner.smoothness=5
    python benchmarks/mixed_autonomy.py --driver idm runs/ring-policy/wave2-4ego/policy.pt \\
        --shares 4.55 9.1 13.6 18.2 50 --out runs/ring-policy/eval

Extra ``--set KEY=VALUE`` are passed on to ``agent-client train``. A measurement, not a test:
the run takes the minutes it is given.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocol.readiness import LISTENING, stop_process, wait_for_line

RING_OPTIONS = {
    "warmup": 300,
    "stop_patience": 3600,
    "report_traffic": "true",
    "ring_length": 230,
    "vehicles": 22,
    "human_model": "eidm",
    "max_episode_time": 120,
}
"""The ring as `benchmarks/mixed_autonomy.py` measures it, with 120 s training episodes."""
SETTINGS = (
    "eval_every=0",
    "learner.learning_starts=2000",
    "noise_decay_steps=150000",
    "learner.action_l2=0",
    "learner.smoothness=1",
)
"""``--set`` of the training run (docs/learner-design.md, "Learning to damp the ring's waves")."""


def train_command(args: argparse.Namespace, address: str) -> list[str]:
    command = [
        sys.executable, "-c", "import sys; from agent_client.cli import main; sys.exit(main())",
        "train", "--server", address,
        "--scenario", "ring", "--reward", args.reward, "--decision-interval", "0.5",
        "--egos", str(args.egos), "--episodes", "100000", "--minutes", str(args.minutes),
        "--seed", str(args.seed), "--out", str(args.out), "--quiet",
    ]  # fmt: skip
    for name, value in RING_OPTIONS.items():
        command += ["--option", f"{name}={value}"]
    for setting in (*SETTINGS, *args.set):
        command += ["--set", setting]
    return command


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--egos", type=int, default=4, help="egos per training simulation")
    parser.add_argument("--minutes", type=float, default=14.0, help="wall-time budget")
    parser.add_argument("--reward", choices=("wave", "wave_own"), default="wave")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "ring-policy" / "wave")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryDirectory(prefix="av-bridge-ring-") as cache:
        server = subprocess.Popen(
            [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0",
             "--backend", "sumo", "--cache-dir", cache, "--log-level", "WARNING",
             "--exit-with-parent"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        try:
            address = wait_for_line(server, LISTENING, 60.0)
            command = train_command(args, address)
            print(" ".join(command), flush=True)
            return subprocess.run(command, cwd=ROOT, env=env, check=False).returncode
        finally:
            stop_process(server)


if __name__ == "__main__":
    sys.exit(main())
