"""What does the bridge cost? Steps/s and per-step round trips, against SUMO in-process and TraCI.

In one run, on the same scenario, seeds and per-step queries, the same number of steps of:

* ``inproc`` - the ceiling: `SumoBackend` on libsumo called directly in this process;
* ``tcp``    - our bridge: a real ``sim-server`` subprocess on a free loopback port, and this
  process as the client (`agent_client.transport.ZmqChannel`: hello, reset, step...);
* ``ipc``    - the same over an ``ipc://`` socket;
* ``direct`` - the same over ``direct://``: a plain TCP socket, no ZeroMQ
  (`protocol.transport.direct`), both ends busy-waiting up to ``--spin-us`` for each other
  before blocking;
* ``traci``  - the peer: `SumoBackend` over SUMO's own TraCI socket (a ``sumo`` process), called
  in this process;
* ``tcp-raw`` (on request) - the tcp bridge with a bare client instead of `ZmqChannel` (a REQ
  socket, a poll with the deadline, the codec): what the client's own bookkeeping costs;
* the floor, what no bridge in Python can go below: ``cached-tcp`` and ``cached-direct`` - our
  server answering a repeated step from its reply cache (the whole server path and both codecs,
  no simulation: the bridge's own round trip);
  ``zmq-echo`` - a bare ZeroMQ ROUTER echoing an observation-sized frame to a bare REQ socket
  (`echo.py`); ``tcp-echo`` - the same over a plain blocking TCP socket.

The ego is driven by a fixed policy (IDM keeping its lane, or a constant acceleration); each
variant's episode k starts from seed ``--seed + k``, so every variant drives the same episodes.
Only the steps are timed (resets are not); the round trip of a step is the time from the client's
call to the decoded observation (for ``inproc`` and ``traci``: the call of ``SumoBackend.step``).

The machine may be shared and noisy, so the variants run interleaved: all of them are started,
then each runs a block of ``--block`` steps in turn until each has run ``--steps``. A burst of
load then hits every variant alike; the ratios are also given per round (one block of each), as
the median and the 10-90 % range, to show the spread.

    python benchmarks/bridge.py                       # cf and cflc, 5000 steps each
    python benchmarks/bridge.py --scenarios cflc --steps 20000 --json --save

This is a measurement, not a test.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent_client.drivers.idm import IDMDriver
from agent_client.transport import connect
from protocol.codec import decode_reply, encode
from protocol.messages import Hello, Observation, OptionValue, Reset, Step
from protocol.readiness import LISTENING, NotReady, stop_process, wait_for_line
from protocol.transport.direct import DEFAULT_SPIN_US
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.fake import FakeBackend

VARIANTS = (
    "inproc", "tcp", "ipc", "direct", "traci", "tcp-raw",
    "cached-tcp", "cached-direct", "zmq-echo", "tcp-echo",
)  # fmt: skip
DEFAULT_VARIANTS = VARIANTS[:5] + VARIANTS[6:]
FLOORS = ("cached-tcp", "cached-direct", "zmq-echo", "tcp-echo")
BRIDGES = ("direct", "tcp", "ipc", "tcp-raw")
LABELS = {
    "inproc": "in-process libsumo (ceiling)",
    "tcp": "bridge tcp://",
    "ipc": "bridge ipc://",
    "direct": "bridge direct://",
    "traci": "TraCI socket (peer)",
    "tcp-raw": "bridge tcp://, bare client",
    "cached-tcp": "floor: our tcp:// server, cached reply",
    "cached-direct": "floor: our direct:// server, cached reply",
    "zmq-echo": "floor: ZeroMQ echo",
    "tcp-echo": "floor: plain TCP echo",
}
RESULTS = ROOT / "benchmarks" / "results" / "bridge.json"
TARGETS = {"bridge_over_inproc_cflc": 0.6, "bridge_over_traci": 5.0, "bridge_p99_us": 300.0}
READY_TIMEOUT_S = 60.0
OBSERVATION_BYTES = 905
"""Size of an encoded cflc observation with six neighbours (the echo servers' reply)."""

Policy = Callable[[Observation], tuple[float, int]]
StepFn = Callable[[int, float, int], Observation]
ResetFn = Callable[[int], Observation]


class Runner:
    """One variant: resets and steps on demand, timing every step."""

    def __init__(self, variant: str, reset: ResetFn, step: StepFn, policy: Policy, seed: int):
        self.variant = variant
        self._reset, self._step, self._policy = reset, step, policy
        self.seed = seed
        self.latencies_ns: list[int] = []
        self.blocks: list[tuple[int, int]] = []  # (steps, ns) of each block
        self.episodes = 0
        self._obs: Observation | None = None
        self._seq = 0

    def run(self, steps: int, record: bool = True) -> None:
        clock = time.perf_counter_ns
        latencies: list[int] = []
        while len(latencies) < steps:
            obs = self._obs
            if obs is None or obs.terminated or obs.truncated:
                obs = self._reset(self.seed + self.episodes)
                self.episodes += 1
                self._seq = 0
            acceleration, lane_change = self._policy(obs)
            self._seq += 1
            before = clock()
            obs = self._step(self._seq, acceleration, lane_change)
            latencies.append(clock() - before)
            self._obs = obs
        if record:
            self.latencies_ns += latencies
            self.blocks.append((len(latencies), sum(latencies)))

    @property
    def steps_per_s(self) -> float:
        return len(self.latencies_ns) / (sum(self.latencies_ns) / 1e9)

    def percentile_us(self, q: float) -> float:
        ordered = sorted(self.latencies_ns)
        return ordered[min(len(ordered) - 1, int(q * len(ordered)))] / 1e3

    def to_dict(self) -> dict[str, Any]:
        return {
            "steps": len(self.latencies_ns),
            "episodes": self.episodes,
            "steps_per_s": round(self.steps_per_s, 1),
            "p50_us": round(self.percentile_us(0.50), 1),
            "p99_us": round(self.percentile_us(0.99), 1),
            "mean_us": round(statistics.fmean(self.latencies_ns) / 1e3, 1),
        }


def make_policy(name: str) -> Policy:
    if name == "idm":
        return IDMDriver().act
    if name == "constant":
        return lambda obs: (0.0, 0)
    raise ValueError(f"unknown policy {name!r}")


# --------------------------------------------------------------------------- the variants


def in_process(
    stack: contextlib.ExitStack, variant: str, scenario: str, extra: dict[str, OptionValue],
    cache_dir: Path, spin_us: float = DEFAULT_SPIN_US,
) -> tuple[ResetFn, StepFn]:  # fmt: skip
    from sim_server.backends.sumo.backend import SumoBackend

    over: dict[str, Any] = {"traci": True} if variant == "traci" else {}
    backend = SumoBackend(cache_dir=cache_dir, **over)
    stack.callback(backend.close)
    info = {s.name: s for s in backend.scenarios()}[scenario]
    options = {**info.options, **extra}
    return (lambda seed: backend.reset(scenario, seed, options)), backend.step


def over_the_bridge(
    stack: contextlib.ExitStack, variant: str, scenario: str, extra: dict[str, OptionValue],
    cache_dir: Path, spin_us: float = DEFAULT_SPIN_US,
) -> tuple[ResetFn, StepFn]:  # fmt: skip
    if variant == "ipc":
        bind = f"ipc://{tempfile.gettempdir()}/av-bridge-bench-{os.getpid()}.sock"
    elif variant == "direct":
        bind = "direct://127.0.0.1:0"
    else:
        bind = "tcp://127.0.0.1:0"
    spin = ["--spin-us", str(spin_us)] if variant == "direct" else []
    address = stack.enter_context(sim_server(bind, cache_dir, spin))
    request = (
        bare_client(stack, address)
        if variant == "tcp-raw"
        else stack.enter_context(connect(address, timeout_s=30.0, spin_us=spin_us)).request
    )
    request(Hello(PROTOCOL_VERSION, "benchmark"))

    def reset(seed: int) -> Observation:
        reply = request(Reset(scenario, seed, extra), 120.0)
        assert isinstance(reply, Observation), reply
        return reply

    def step(seq: int, acceleration: float, lane_change: int) -> Observation:
        reply = request(Step(seq, acceleration, lane_change))
        assert isinstance(reply, Observation), reply
        return reply

    return reset, step


def transport_floor(
    stack: contextlib.ExitStack, variant: str, scenario: str, extra: dict[str, OptionValue],
    cache_dir: Path, spin_us: float = DEFAULT_SPIN_US,
) -> tuple[ResetFn, StepFn]:  # fmt: skip
    """Round trips that simulate nothing: what the transport and the server path cost alone."""
    if variant.startswith("cached-"):
        reset_real, step_real = over_the_bridge(
            stack, variant.removeprefix("cached-"), scenario, extra, cache_dir, spin_us
        )

        def reset_cached(seed: int) -> Observation:
            reset_real(seed)
            return step_real(1, 0.0, 0)

        return reset_cached, lambda seq, acceleration, lane_change: step_real(1, 0.0, 0)
    kind = variant.removesuffix("-echo")
    address = stack.enter_context(echo_server(kind, OBSERVATION_BYTES))
    fake = FakeBackend()  # its observation is what the policy sees; the wire carries bytes
    canned = fake.reset("cf", 1, dict(fake.scenarios()[0].options))
    request = encode(Step(1, 0.0, 0))
    if kind == "zmq":
        send_receive = bare_client(stack, address, decode=False)
    else:
        send_receive = plain_tcp_client(stack, address)
    return (
        lambda seed: canned
    ), lambda seq, acceleration, lane_change: send_receive(request) and canned


def plain_tcp_client(stack: contextlib.ExitStack, address: str) -> Callable[[bytes], bytes]:
    import socket
    import struct

    host, _, port = address.rpartition(":")
    connection = socket.create_connection((host, int(port)), timeout=30.0)
    connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    stack.callback(connection.close)
    length = struct.Struct("<I")

    def send_receive(frame: bytes) -> bytes:
        connection.sendall(length.pack(len(frame)) + frame)
        (size,) = length.unpack(connection.recv(4, socket.MSG_WAITALL))
        return connection.recv(size, socket.MSG_WAITALL)

    return send_receive


@contextlib.contextmanager
def echo_server(kind: str, reply_bytes: int) -> Iterator[str]:
    bind = "tcp://127.0.0.1:0" if kind == "zmq" else "127.0.0.1:0"
    command = [sys.executable, str(ROOT / "benchmarks" / "echo.py"), kind, bind,
               "--reply-bytes", str(reply_bytes)]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        yield wait_for_line(process, LISTENING, READY_TIMEOUT_S)
    finally:
        process.kill()
        process.wait(timeout=10)
        if process.stdout is not None:
            process.stdout.close()


def bare_client(
    stack: contextlib.ExitStack, address: str, decode: bool = True
) -> Callable[..., Any]:
    """The floor of a client: one REQ socket, send, poll with a deadline, receive, decode."""
    import zmq

    context = zmq.Context()
    socket = context.socket(zmq.REQ)
    socket.setsockopt(zmq.LINGER, 0)
    socket.connect(address)
    stack.callback(context.term)
    stack.callback(socket.close, 0)
    poller = zmq.Poller()
    poller.register(socket, zmq.POLLIN)

    def request(message: Any, timeout_s: float = 30.0) -> Any:
        socket.send(encode(message) if decode else message)
        if not poller.poll(int(timeout_s * 1000)):
            raise TimeoutError(f"no reply from {address}")
        return decode_reply(socket.recv()) if decode else socket.recv()

    return request


@contextlib.contextmanager
def sim_server(bind: str, cache_dir: Path, extra: list[str]) -> Iterator[str]:
    """A real ``sim-server`` subprocess; yields the address it printed, always cleans up."""
    command = [sys.executable, "-m", "sim_server.cli", "--bind", bind, "--backend", "sumo",
               "--log-level", "WARNING", *extra]  # fmt: skip
    env = {**os.environ, "XDG_CACHE_HOME": str(cache_dir.parent.parent), "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryFile(mode="w+") as log:
        process = subprocess.Popen(
            command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=log, text=True
        )
        try:
            try:
                yield wait_for_line(process, LISTENING, READY_TIMEOUT_S)
            except NotReady as exc:
                log.seek(0)
                raise RuntimeError(f"sim-server did not become ready: {exc}\n{log.read()}") from exc
        finally:
            stop_process(process)


# --------------------------------------------------------------------------- measuring


def measure(
    scenario: str, variants: list[str], args: argparse.Namespace, extra: dict[str, OptionValue],
    policy: Policy, cache_dir: Path,
) -> dict[str, Runner]:  # fmt: skip
    """Start every variant, warm each up, then run them block by block, in turn."""
    with contextlib.ExitStack() as stack:
        runners = {}
        for variant in variants:
            start = (
                in_process
                if variant in ("inproc", "traci")
                else transport_floor
                if variant in FLOORS
                else over_the_bridge
            )
            reset, step = start(stack, variant, scenario, extra, cache_dir, args.spin_us)
            runners[variant] = Runner(variant, reset, step, policy, args.seed)
        for runner in runners.values():
            runner.run(50, record=False)  # imports, caches, first episode
            runner.episodes, runner._obs = 0, None  # the timed run starts at --seed
        done = 0
        while done < args.steps:
            block = min(args.block, args.steps - done)
            for runner in runners.values():
                runner.run(block)
            done += block
        return runners


def ratios(runners: dict[str, Runner]) -> dict[str, dict[str, float]]:
    """Overall ratio of steps/s, and the median and 10-90 % range of the per-round ratios."""
    out = {}
    for bridge in BRIDGES:
        for reference in ("inproc", "traci"):
            if bridge not in runners or reference not in runners:
                continue
            a, b = runners[bridge], runners[reference]
            per_round = sorted(
                (nb * ta) / (na * tb)  # (bridge steps/s) / (reference steps/s) in that round
                for (na, tb), (nb, ta) in zip(a.blocks, b.blocks, strict=True)
            )
            deciles = (
                statistics.quantiles(per_round, n=10, method="inclusive")
                if len(per_round) > 1
                else per_round
            )
            out[f"{bridge}_over_{reference}"] = {
                "overall": round(a.steps_per_s / b.steps_per_s, 3),
                "round_median": round(statistics.median(per_round), 3),
                "round_p10": round(deciles[0], 3),
                "round_p90": round(deciles[-1], 3),
            }
    return out


def overheads(runners: dict[str, Runner]) -> dict[str, float]:
    """Mean microseconds per step each bridge adds to in-process SUMO (the floors: all of it)."""
    if "inproc" not in runners:
        return {}
    base = runners["inproc"].to_dict()["mean_us"]
    return {
        v: r.to_dict()["mean_us"] - (0.0 if v in FLOORS else base)
        for v, r in runners.items()
        if v != "inproc" and v != "traci"
    }


def table(scenario: str, runners: dict[str, Runner], rates: dict[str, dict[str, float]]) -> str:
    steps = next(iter(runners.values())).to_dict()["steps"]
    lines = [
        f"{scenario}: {steps} steps per variant, interleaved",
        "| variant | steps/s | p50 us | p99 us | episodes |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for variant, runner in runners.items():
        d = runner.to_dict()
        lines.append(
            f"| {LABELS[variant]} | {d['steps_per_s']:,.0f} | {d['p50_us']:.0f} "
            f"| {d['p99_us']:.0f} | {d['episodes']} |"
        )
    overhead = overheads(runners)
    if overhead:
        lines.append(
            "mean us per step above in-process: "
            + ", ".join(f"{LABELS[v]} {us:.0f}" for v, us in overhead.items())
        )
    for name, r in rates.items():
        lines.append(
            f"{name}: {r['overall']:.3g} (per round: median {r['round_median']:.3g}, "
            f"10-90% {r['round_p10']:.3g}-{r['round_p90']:.3g})"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["cf", "cflc"])
    parser.add_argument("--steps", type=int, default=5000, help="timed steps per variant")
    parser.add_argument("--block", type=int, default=250, help="steps per variant and round")
    parser.add_argument("--seed", type=int, default=1, help="seed of the first episode")
    parser.add_argument("--policy", choices=("idm", "constant"), default="idm")
    parser.add_argument(
        "--spin-us", type=float, default=DEFAULT_SPIN_US,
        help="direct:// busy-wait of both ends before blocking (default %(default)g)",
    )  # fmt: skip
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(DEFAULT_VARIANTS))
    parser.add_argument(
        "--option", action="append", default=[], metavar="NAME=VALUE",
        help="scenario option sent with every reset (value parsed as JSON, else a string)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--save", action="store_true", help=f"write {RESULTS.relative_to(ROOT)}")
    args = parser.parse_args()

    extra: dict[str, OptionValue] = {}
    for assignment in args.option:
        name, _, text = assignment.partition("=")
        try:
            extra[name] = json.loads(text)
        except json.JSONDecodeError:
            extra[name] = text
    policy = make_policy(args.policy)
    report: dict[str, Any] = {
        "command": " ".join(["python", "benchmarks/bridge.py", *sys.argv[1:]]),
        "machine": f"{platform.machine()}, {os.cpu_count()} cpus, "
        f"Python {platform.python_version()}, load average {os.getloadavg()[0]:.2f} at start",
        "steps": args.steps,
        "block": args.block,
        "seed": args.seed,
        "policy": args.policy,
        "spin_us": args.spin_us,
        "options": extra,
        "targets": TARGETS,
        "scenarios": {},
    }
    cache_root = Path(tempfile.mkdtemp(prefix="av-bridge-bench-"))
    cache_dir = cache_root / "av-bridge" / "scenarios"  # the servers' XDG_CACHE_HOME layout
    try:
        for scenario in args.scenarios:
            runners = measure(scenario, args.variants, args, extra, policy, cache_dir)
            rates = ratios(runners)
            report["scenarios"][scenario] = {
                "variants": {v: r.to_dict() for v, r in runners.items()},
                "ratios": rates,
                "overhead_us": {v: round(us, 1) for v, us in overheads(runners).items()},
            }
            if not args.json:
                print(table(scenario, runners, rates), end="\n\n", flush=True)
    finally:
        shutil.rmtree(cache_root, ignore_errors=True)
    if args.json:
        print(json.dumps(report, indent=2))
    if args.save:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(report, indent=2) + "\n")
        if not args.json:
            print(f"wrote {RESULTS.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
