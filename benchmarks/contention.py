"""What a busy second core costs a SUMO step: the part of the bridge's overhead no code removes.

`direct://` keeps the learner busy-waiting for the reply while the server steps SUMO, so that
neither falls asleep (a wake-up costs tens of microseconds on a VM). This measures what that
busy neighbour costs the step itself: `SumoBackend` on libsumo in this process drives the same
IDM episodes while another process, in turn, does nothing (``none``), runs a pure Python loop
(``busy``) or spins as the learner's `spin_wait` does (``spin``: a zero-timeout poll and a
``sched_yield``, over and over). The modes alternate in blocks of ``--block`` steps, so the
machine's noise hits all alike; each neighbour is stopped (SIGSTOP) outside its blocks.

    python benchmarks/contention.py                 # cflc, 80 rounds of 100 steps per mode

This is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.idm import IDMDriver
from protocol.readiness import stop_process, wait_for_line

READY = "neighbour ready"
NEIGHBOURS = {
    "busy": "while True:\n    pass\n",
    "spin": (
        "import os, select, socket\n"
        "a, b = socket.socketpair()\n"
        "poller = select.poll()\n"
        "poller.register(a, select.POLLIN)\n"
        "while True:\n"
        "    poller.poll(0)\n"
        "    os.sched_yield()\n"
    ),
}


@contextlib.contextmanager
def neighbour(kind: str) -> Iterator[subprocess.Popen[str]]:
    """A process looping as `kind`, stopped until its blocks start; always cleaned up."""
    code = f"print({READY!r}, flush=True)\n" + NEIGHBOURS[kind]
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        wait_for_line(process, READY, 30.0)
        os.kill(process.pid, signal.SIGSTOP)
        yield process
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(process.pid, signal.SIGCONT)  # a stopped process cannot handle SIGTERM
        stop_process(process, grace_s=2.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="cflc")
    parser.add_argument("--rounds", type=int, default=80)
    parser.add_argument("--block", type=int, default=100, help="steps per mode and round")
    args = parser.parse_args()

    from sim_server.backends.sumo.backend import SumoBackend

    backend = SumoBackend()
    options = dict({s.name: s for s in backend.scenarios()}[args.scenario].options)
    driver = IDMDriver()
    modes = ["none", *NEIGHBOURS]
    total_ns = dict.fromkeys(modes, 0)
    steps = dict.fromkeys(modes, 0)
    with contextlib.ExitStack() as stack:
        processes = {kind: stack.enter_context(neighbour(kind)) for kind in NEIGHBOURS}
        stack.callback(backend.close)
        episode, seq = 0, 0
        obs = backend.reset(args.scenario, 1, options)
        for done in range(args.rounds):
            for mode in modes:
                process = processes.get(mode)
                if process is not None:
                    os.kill(process.pid, signal.SIGCONT)
                for _ in range(args.block):
                    if obs.terminated or obs.truncated:
                        episode, seq = episode + 1, 0
                        obs = backend.reset(args.scenario, 1 + episode, options)
                    acceleration, lane_change = driver.act(obs)
                    seq += 1
                    before = time.perf_counter_ns()
                    obs = backend.step(seq, acceleration, lane_change)
                    total_ns[mode] += time.perf_counter_ns() - before
                    steps[mode] += 1
                if process is not None:
                    os.kill(process.pid, signal.SIGSTOP)
            if (done + 1) % 20 == 0:
                print(f"round {done + 1}/{args.rounds}", file=sys.stderr, flush=True)
    mean_us = {mode: total_ns[mode] / steps[mode] / 1e3 for mode in modes}
    print(f"{args.scenario}: mean us per SUMO step, {steps['none']} steps per mode, interleaved")
    for mode in modes:
        extra = mean_us[mode] - mean_us["none"]
        print(f"  neighbour {mode:5s} {mean_us[mode]:6.1f} us  (+{extra:4.1f} us, "
              f"{mean_us[mode] / mean_us['none']:.2f}x)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
