"""Soak: thousands of short episodes through one server, with lost replies and killed learners.

One `sim-server` (SUMO by default) on a free loopback port serves, in turns:

* the soak client itself: short episodes (`--episode-time` simulated seconds each) with an IDM
  driver; every `--retry-every`-th step it abandons the request (a zero deadline, as if the
  reply were lost) and asks again, which the server must answer from its retry cache;
* every `--crash-every` episodes, a learner subprocess that opens an episode, steps, and is
  SIGKILLed mid-episode; the soak client must then get the simulator back.

A step is *lost* if its reply does not carry the seq asked for, or if the simulation time did
not advance by exactly one decision interval (a retry that advanced the simulation twice, or a
step that never happened). Lost steps must be zero. The memory (RSS) of the server and of the
soak client is sampled along the way and printed, written to JSON and plotted.

    python benchmarks/soak.py --episodes 2000 --crash-every 20      # ~15 min on 2 cores
    python benchmarks/soak.py --episodes 50 --crash-every 10        # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.idm import IDMDriver
from agent_client.errors import ServerError, ServerTimeout
from agent_client.transport import ZmqChannel
from protocol.messages import Close, Hello, Observation, Reset, Step
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line
from protocol.version import PROTOCOL_VERSION

CRASHING_LEARNER = """
import sys
from agent_client.transport import ZmqChannel
from protocol.messages import Hello, Reset, Step
connection = ZmqChannel(sys.argv[1], timeout_s=60.0)
connection.request(Hello((1, 0), "doomed learner"), timeout_s=60.0)
connection.request(Reset(sys.argv[2], int(sys.argv[3]), {"max_episode_time": 1000.0}), 120.0)
seq = 0
while True:
    seq += 1
    connection.request(Step(seq, 0.5))
    if seq == int(sys.argv[4]):
        print("stepping", flush=True)
"""


@dataclass
class Soak:
    """What the soak measured."""

    backend: str
    scenario: str
    episodes: int = 0
    steps: int = 0
    retried_steps: int = 0
    lost_steps: int = 0
    crashes: int = 0
    takeover_seconds: list[float] = field(default_factory=list)
    samples: list[dict[str, float]] = field(default_factory=list)
    wall_seconds: float = 0.0


def rss_mb(pid: int) -> float:
    """Resident set size of a process in MB (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def start_server(backend: str) -> tuple[subprocess.Popen[str], str]:
    command = [sys.executable, "-m", "sim_server.cli", "--bind", "tcp://127.0.0.1:0"]
    process = subprocess.Popen(
        [*command, "--backend", backend, "--log-level", "WARNING"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        return process, wait_for_line(process, LISTENING, 120.0)
    except NotReady:
        process.kill()
        raise


def hello_when_free(connection: ZmqChannel, limit_s: float) -> float:
    """Say hello until the server stops answering busy; returns the seconds it took."""
    started = time.monotonic()
    while True:
        try:
            connection.request(Hello(PROTOCOL_VERSION, "soak"), timeout_s=limit_s)
            return time.monotonic() - started
        except ServerError as exc:
            if exc.code != "busy" or time.monotonic() - started > limit_s:
                raise
            time.sleep(0.02)


def run_episode(
    connection: ZmqChannel, soak: Soak, seed: int, options: dict[str, float], retry_every: int
) -> None:
    """One IDM episode; every `retry_every`-th step is abandoned once and asked again."""
    driver = IDMDriver()
    obs = connection.request(Reset(soak.scenario, seed, options), timeout_s=120.0)
    assert isinstance(obs, Observation)
    interval = options["decision_interval"]
    seq = 0
    while not (obs.terminated or obs.truncated):
        seq += 1
        acceleration, _ = driver.act(obs)
        step = Step(seq, acceleration)
        if retry_every and (soak.steps + 1) % retry_every == 0:
            try:
                connection.request(step, timeout_s=0.0)  # its reply is "lost"
            except ServerTimeout:
                soak.retried_steps += 1
        reply = connection.request(step)
        assert isinstance(reply, Observation)
        advanced = reply.time - obs.time
        ended_early = reply.terminated and advanced < interval
        if reply.seq != seq or not (abs(advanced - interval) < 1e-6 or ended_early):
            soak.lost_steps += 1
        soak.steps += 1
        obs = reply


def crash_a_learner(address: str, scenario: str, seed: int, steps: int) -> None:
    """A learner that is SIGKILLed mid-episode, after `steps` steps."""
    process = subprocess.Popen(
        [sys.executable, "-c", CRASHING_LEARNER, address, scenario, str(seed), str(steps)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        wait_for_line(process, "stepping", 120.0)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
        assert process.stdout is not None
        process.stdout.close()


def soak(args: argparse.Namespace) -> Soak:
    server, address = start_server(args.backend)
    result = Soak(args.backend, args.scenario)
    options = {"decision_interval": args.decision_interval, "max_episode_time": args.episode_time}
    started = time.monotonic()
    try:
        connection = ZmqChannel(address, timeout_s=30.0)
        hello_when_free(connection, 30.0)
        for episode in range(args.episodes):
            if args.crash_every and episode and episode % args.crash_every == 0:
                connection.request(Close())  # hand the simulator over to the doomed learner
                crash_a_learner(address, args.scenario, 10_000 + episode, 5 + episode % 50)
                result.crashes += 1
                result.takeover_seconds.append(hello_when_free(connection, 30.0))
            run_episode(connection, result, episode, options, args.retry_every)
            result.episodes += 1
            if episode % args.sample_every == 0 or episode == args.episodes - 1:
                sample = {
                    "episode": episode + 1,
                    "seconds": round(time.monotonic() - started, 1),
                    "server_rss_mb": round(rss_mb(server.pid), 1),
                    "client_rss_mb": round(rss_mb(os.getpid()), 1),
                }
                result.samples.append(sample)
                print(
                    f"episode {sample['episode']:>6}  {sample['seconds']:>7.1f} s  "
                    f"server {sample['server_rss_mb']:>7.1f} MB  "
                    f"client {sample['client_rss_mb']:>7.1f} MB  steps {result.steps}  "
                    f"retried {result.retried_steps}  crashes {result.crashes}  "
                    f"lost {result.lost_steps}",
                    flush=True,
                )
        connection.request(Close())
        connection.close()
    finally:
        result.wall_seconds = round(time.monotonic() - started, 1)
        stop_process(server, grace_s=30.0)
    return result


def plot(result: Soak, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes = [s["episode"] for s in result.samples]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(episodes, [s["server_rss_mb"] for s in result.samples], label="sim-server")
    ax.plot(episodes, [s["client_rss_mb"] for s in result.samples], label="soak client")
    ax.set_xlabel("episode")
    ax.set_ylabel("RSS (MB)")
    ax.set_ylim(bottom=0)
    ax.set_title(
        f"soak on {result.backend}/{result.scenario}: {result.steps} steps, "
        f"{result.crashes} killed learners, {result.lost_steps} lost steps",
        fontsize=9,
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", default="sumo", help="sumo (default) or fake")
    parser.add_argument("--scenario", default="cf")
    parser.add_argument("--episodes", type=int, default=2000)
    parser.add_argument("--episode-time", type=float, default=10.0, help="simulated s/episode")
    parser.add_argument("--decision-interval", type=float, default=0.1)
    parser.add_argument("--crash-every", type=int, default=20, help="0: no killed learners")
    parser.add_argument("--retry-every", type=int, default=97, help="0: no abandoned requests")
    parser.add_argument("--sample-every", type=int, default=100)
    parser.add_argument("--out", type=Path, help="JSON results (and a PNG beside it)")
    args = parser.parse_args(argv)
    result = soak(args)
    growth = result.samples[-1]["server_rss_mb"] - result.samples[0]["server_rss_mb"]
    print(
        f"\n{result.episodes} episodes, {result.steps} steps ({result.retried_steps} retried), "
        f"{result.crashes} killed learners in {result.wall_seconds:.0f} s on "
        f"{platform.node()} ({platform.processor() or platform.machine()}): "
        f"lost steps {result.lost_steps}; server RSS {result.samples[0]['server_rss_mb']:.1f} -> "
        f"{result.samples[-1]['server_rss_mb']:.1f} MB ({growth:+.1f}); "
        f"takeover after a kill: max {max(result.takeover_seconds, default=0.0):.2f} s"
    )
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(asdict(result), indent=2))
        plot(result, args.out.with_suffix(".png"))
        print(f"wrote {args.out} and {args.out.with_suffix('.png')}")
    return 0 if result.lost_steps == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
