"""Protocol conformance checks: probe any bridge server with raw frames and judge its replies.

The checks use only the wire (docs/protocol.md), through the client's own transport
(`agent_client.conformance.probe`): frames built with `protocol.codec` (or raw msgpack for
malformed ones), replies parsed with `protocol.codec.decode_reply`. They never look inside a
server, so they judge a server written for any simulator in any language. Every receive has a
deadline. See docs/conformance.md for what each check verifies.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import fields
from typing import Any, TypeVar

from agent_client.conformance.probe import CLIENT_NAME, BadReply, NoReply, Probe
from agent_client.conformance.result import FAIL, PASS, SKIP, WARN, CheckResult, ConformanceReport
from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from agent_client.errors import BridgeError, UsageError
from protocol.errors import ErrorCode
from protocol.messages import (
    Bye,
    Close,
    EndReason,
    Error,
    Hello,
    Observation,
    OptionValue,
    Reply,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.schema import NEIGHBOUR_SLOTS, Flattener
from protocol.transport.endpoint import parse_endpoint
from protocol.version import PROTOCOL_VERSION, format_version

TERMINAL_REASONS = frozenset(reason.value for reason in EndReason if reason.terminates)
"""Documented reasons of a terminated episode; a truncated one says "time_limit"."""

DETERMINISM_STEPS = 50
EPISODE_BUDGET = 3000
"""Steps the termination check waits for an episode to end (with a short time limit if any)."""

_ACTION_PATTERN = (0.5, 0.0, -0.5, 1.0, -1.0)
_LANE_CHANGES = {10: 1, 30: -1}
_ABSURD_ACCELERATION = 1000.0
_SHORT_EPISODE_S = 2.0
_TOLERANCE = 1e-6
_MAX_OVERSIZED_FRAME = 8 * 1024 * 1024
"""Above this announced limit the frame_too_large probe is left out (ZeroMQ caps frames)."""

R = TypeVar("R", bound=Reply)


class ServerUnreachable(BridgeError):
    """The server did not answer the first hello (or another client holds it)."""


class ScenarioNotOffered(UsageError):
    """The scenario asked for is not in the server's welcome (a usage error, not a fault)."""


class CheckFailed(Exception):
    """A check's expectation was not met; the message is the one-line detail."""


def expect(reply: Reply, kind: type[R], what: str) -> R:
    """The reply as `kind`, or CheckFailed naming what was asked and what came back."""
    if isinstance(reply, kind):
        return reply
    if isinstance(reply, Error):
        raise CheckFailed(f"{what}: expected {kind.TYPE}, got error {reply.code}: {reply.message}")
    raise CheckFailed(f"{what}: expected {kind.TYPE}, got {reply.TYPE}")


def expect_error(reply: Reply, code: ErrorCode, what: str) -> Error:
    """The reply as an `Error` with `code`, or CheckFailed."""
    if not isinstance(reply, Error):
        raise CheckFailed(f"{what}: expected error {code.value}, got {reply.TYPE}")
    if reply.code != code.value:
        raise CheckFailed(f"{what}: expected error {code.value}, got {reply.code}: {reply.message}")
    return reply


class Checker:
    """Runs the conformance checks in order against one server."""

    def __init__(
        self,
        address: str,
        scenario: str | None = None,
        timeout_s: float = STEP_TIMEOUT_S,
        reset_timeout_s: float = RESET_TIMEOUT_S,
        episode_budget: int = EPISODE_BUDGET,
    ) -> None:
        parse_endpoint(address)  # ValueError on a malformed address, before any socket
        self.address = address
        self.requested_scenario = scenario
        self.reset_timeout_s = max(timeout_s, reset_timeout_s)
        self.episode_budget = episode_budget
        self.probe = Probe(address, timeout_s)
        self.welcome: Welcome | None = None
        self.scenario: ScenarioInfo | None = None
        self._closed = False

    # ----------------------------------------------------------------------- running

    def run(self) -> ConformanceReport:
        """All checks.

        Raises ServerUnreachable when the first hello gets no answer or `busy`, and
        ScenarioNotOffered when the server does not offer the requested scenario.
        """
        report = ConformanceReport(self.address, self.requested_scenario)
        try:
            first = self._first_contact()
            report.results.append(self._guarded("handshake", lambda: self.check_handshake(first)))
            report.scenario = self.scenario.name if self.scenario else self.requested_scenario
            checks: list[tuple[str, Callable[[], str]]] = [
                ("version_refusal", self.check_version_refusal),
                ("schema", self.check_schema),
                ("reset", self.check_reset),
                ("step", self.check_step),
                ("reconnect", self.check_reconnect),
                ("termination", self.check_termination),
                ("bad_requests", self.check_bad_requests),
                ("determinism", self.check_determinism),
                ("close", self.check_close),
            ]
            silent = 0
            for name, check in checks:
                if self.scenario is None and name != "close":
                    report.results.append(CheckResult(name, SKIP, "needs a valid welcome"))
                    continue
                if silent >= 2:
                    detail = "not run: the server stopped answering"
                    report.results.append(CheckResult(name, FAIL, detail))
                    continue
                result = self._guarded(name, check)
                silent = silent + 1 if result.detail.startswith("no reply") else 0
                report.results.append(result)
        finally:
            self._leave()
        return report

    def _first_contact(self) -> Reply:
        try:
            reply = self.probe.ask(Hello(PROTOCOL_VERSION, CLIENT_NAME))
        except NoReply as exc:
            raise ServerUnreachable(
                f"no reply from {self.address} within {self.probe.timeout_s:g} s "
                "(is the server running and reachable?)"
            ) from exc
        except BadReply as exc:
            return Error("malformed", str(exc))  # judged (and failed) by the handshake check
        if isinstance(reply, Error) and reply.code == ErrorCode.BUSY.value:
            raise ServerUnreachable(f"{self.address} is busy with another client: {reply.message}")
        return reply

    def _guarded(self, name: str, check: Callable[[], str]) -> CheckResult:
        try:
            detail = check()
        except ScenarioNotOffered:
            raise
        except _Warning as exc:
            return CheckResult(name, WARN, str(exc))
        except CheckFailed as exc:
            return CheckResult(name, FAIL, str(exc))
        except NoReply as exc:
            return CheckResult(name, FAIL, f"{exc} (the socket was replaced)")
        except BadReply as exc:
            return CheckResult(name, FAIL, str(exc))
        except Exception as exc:  # a misbehaving server may break any assumption: report it
            return CheckResult(name, FAIL, f"unexpected {type(exc).__name__}: {exc}")
        return CheckResult(name, PASS, detail)

    def _leave(self) -> None:
        """Free the server for the next client (best effort) and release the socket."""
        try:
            if not self._closed:
                with contextlib.suppress(NoReply, BadReply):
                    self.probe.ask(Close(), timeout_s=min(self.probe.timeout_s, 2.0))
        finally:
            self.probe.close()

    # ----------------------------------------------------------------------- helpers

    def _hello(self) -> Welcome:
        self._closed = False
        return expect(self.probe.ask(Hello(PROTOCOL_VERSION, CLIENT_NAME)), Welcome, "hello")

    def _reset(
        self, seed: int | None, options: dict[str, OptionValue] | None = None
    ) -> tuple[bytes, Observation]:
        assert self.scenario is not None
        request = Reset(self.scenario.name, seed, options or {})
        data, reply = self.probe.exchange(request, self.reset_timeout_s)
        obs = expect(reply, Observation, f"reset (seed {seed})")
        if obs.seq != 0:
            raise CheckFailed(f"reset (seed {seed}) answered with seq {obs.seq}, expected 0")
        return data, obs

    def _step(
        self, seq: int, acceleration: float, lane_change: int = 0
    ) -> tuple[bytes, Observation]:
        data, reply = self.probe.exchange(Step(seq, acceleration, lane_change))
        obs = expect(reply, Observation, f"step {seq}")
        if obs.seq != seq:
            raise CheckFailed(f"step {seq} answered with seq {obs.seq}")
        return data, obs

    def _running_episode(self, seed: int, steps: int) -> list[tuple[bytes, Observation]]:
        """Hello, reset and `steps` steps of zero acceleration in an episode that does not end."""
        self._hello()
        for attempt in range(3):
            history = [self._reset(seed + attempt)]
            for seq in range(1, steps + 1):
                history.append(self._step(seq, 0.0))
                if _ended(history[-1][1]):
                    break
            else:
                return history
        raise CheckFailed(f"three episodes ended within {steps} steps; cannot test stepping")

    # ----------------------------------------------------------------------- checks

    def check_handshake(self, reply: Reply) -> str:
        welcome = expect(reply, Welcome, "hello")
        problems = []
        if welcome.protocol[0] != PROTOCOL_VERSION[0]:
            problems.append(f"protocol {format_version(welcome.protocol)} is not major 1")
        if not welcome.scenarios:
            problems.append("no scenario offered")
        names = [f.name for f in welcome.observation_fields]
        if not names:
            problems.append("no observation fields")
        elif len(set(names)) != len(names):
            problems.append("duplicate observation fields")
        try:
            Flattener(welcome.observation_fields)
        except ValueError as exc:
            problems.append(str(exc))
        action = welcome.action
        if not action.acceleration_min < 0 < action.acceleration_max:
            problems.append(
                f"acceleration bounds [{action.acceleration_min}, {action.acceleration_max}] "
                "do not satisfy min < 0 < max"
            )
        if action.lane_change != {"right": -1, "keep": 0, "left": 1}:
            problems.append(
                f"lane_change mapping {action.lane_change} is not right -1/keep 0/left 1"
            )
        if not welcome.sensor_range > 0:
            problems.append(f"sensor_range {welcome.sensor_range} is not > 0")
        if not welcome.max_frame_bytes > 0:
            problems.append(f"max_frame_bytes {welcome.max_frame_bytes} is not > 0")
        if problems:
            raise CheckFailed("; ".join(problems))
        offered = {s.name: s for s in welcome.scenarios}
        wanted = self.requested_scenario or welcome.scenarios[0].name
        if wanted not in offered:
            raise ScenarioNotOffered(
                f"{self.address} offers no scenario {wanted!r}; offered: {', '.join(offered)}"
            )
        self.welcome, self.scenario = welcome, offered[wanted]
        return (
            f"protocol {format_version(welcome.protocol)}, backend {welcome.backend} "
            f"{welcome.backend_version}, {len(offered)} scenario(s), {len(names)} fields, "
            f"acceleration [{action.acceleration_min:g}, {action.acceleration_max:g}] m/s^2"
        )

    def check_version_refusal(self) -> str:
        ours = format_version(self.welcome.protocol if self.welcome else PROTOCOL_VERSION)
        future = (PROTOCOL_VERSION[0] + 1, 0)
        reply = self.probe.ask({"type": "hello", "protocol": list(future), "client": CLIENT_NAME})
        error = expect_error(reply, ErrorCode.VERSION_MISMATCH, f"hello {format_version(future)}")
        missing = [v for v in (format_version(future), ours) if v not in error.message]
        if missing:
            raise CheckFailed(f"version_mismatch message {error.message!r} does not name {missing}")
        self._hello()
        return f"hello {format_version(future)} refused naming both versions; hello {ours} works"

    def check_schema(self) -> str:
        assert self.welcome is not None
        problems = []
        for scenario in self.welcome.scenarios:
            if not scenario.step_length > 0:
                problems.append(f"{scenario.name}: step_length {scenario.step_length} is not > 0")
            for name, default in scenario.options.items():
                if default is not None and not isinstance(default, bool | int | float | str):
                    problems.append(f"{scenario.name}.{name}: default is not a scalar")
                elif isinstance(default, float) and not math.isfinite(default):
                    problems.append(f"{scenario.name}.{name}: default {default} is not finite")
        if problems:
            raise CheckFailed("; ".join(problems))
        self._hello()
        _, obs = self._reset(1)
        vector = Flattener(self.welcome.observation_fields)(obs)
        if len(vector) != len(self.welcome.observation_fields):
            raise CheckFailed(f"flat vector has {len(vector)} values")
        names = [f.name for f in self.welcome.observation_fields]
        bad = [name for name, v in zip(names, vector, strict=True) if not math.isfinite(v)]
        if bad:
            raise CheckFailed(f"non-finite values in the flat vector: {bad}")
        for slot in NEIGHBOUR_SLOTS:
            neighbour = getattr(obs.neighbours, slot)
            absent = (self.welcome.sensor_range, 0.0, 0.0, "")
            if (
                not neighbour.present
                and (
                    neighbour.gap,
                    neighbour.lateral,
                    neighbour.speed,
                    neighbour.id,
                )
                != absent
            ):
                problems.append(f"absent {slot} is not gap=sensor_range, lateral=0, speed=0, id=''")
        if not 0 <= obs.ego.lane < obs.ego.lane_count:
            problems.append(f"ego lane {obs.ego.lane} outside 0..{obs.ego.lane_count - 1}")
        if obs.ego.changing_lane not in (-1, 0, 1):
            problems.append(f"ego changing_lane {obs.ego.changing_lane} is not -1, 0 or 1")
        if problems:
            raise CheckFailed("; ".join(problems))
        total = sum(len(s.options) for s in self.welcome.scenarios)
        return (
            f"{total} option defaults are scalars; a real observation flattens to "
            f"{len(vector)} finite values"
        )

    def check_reset(self) -> str:
        assert self.scenario is not None and self.welcome is not None
        self._hello()
        _, obs = self._reset(3)
        if obs.terminated or obs.truncated or obs.reason:
            raise CheckFailed(
                f"first observation is already over (terminated={obs.terminated}, "
                f"truncated={obs.truncated}, reason={obs.reason!r})"
            )
        offered = {s.name for s in self.welcome.scenarios}
        unknown = "no-such-scenario"
        while unknown in offered:
            unknown += "-really"
        reply = self.probe.ask(Reset(unknown, 1), self.reset_timeout_s)
        expect_error(reply, ErrorCode.UNKNOWN_SCENARIO, f"reset {unknown!r}")
        option = "no_such_option"
        while option in self.scenario.options:
            option += "_really"
        reply = self.probe.ask(Reset(self.scenario.name, 1, {option: 1}), self.reset_timeout_s)
        expect_error(reply, ErrorCode.INVALID_OPTION, f"reset with option {option!r}")
        reply = self.probe.ask(Reset(self.scenario.name, 2**31), self.reset_timeout_s)
        expect_error(reply, ErrorCode.INVALID_NUMBER, "reset with seed 2^31")
        return (
            "seq 0, running; unknown scenario -> unknown_scenario, unknown option -> "
            "invalid_option, seed 2^31 -> invalid_number"
        )

    def check_step(self) -> str:
        assert self.welcome is not None
        n = 5
        history = self._running_episode(10, n)
        last_bytes, last = history[-1]
        retry_bytes, _ = self._step(n, 0.0)
        if retry_bytes != last_bytes:
            raise CheckFailed(f"a retry of step {n} did not return the identical cached reply")
        _, after = self._step(n + 1, 0.0)
        interval = last.time - history[-2][1].time
        if abs((after.time - last.time) - interval) > _TOLERANCE * max(1.0, abs(after.time)):
            raise CheckFailed(
                f"after a retry, step {n + 1} advanced time by {after.time - last.time:g} s "
                f"instead of {interval:g} s: the retry advanced the simulation"
            )
        reply = self.probe.ask(Step(n + 3, 0.0))
        expect_error(reply, ErrorCode.SEQUENCE_ERROR, f"step {n + 3} after step {n + 1}")
        seq = n + 1
        applied = []
        for request in (_ABSURD_ACCELERATION, -_ABSURD_ACCELERATION):
            if _ended(after):  # the previous action ended the episode: start another
                self._hello()
                self._reset(20)
                seq = 0
            seq += 1
            _, after = self._step(seq, request)
            applied.append(self._check_bounds(after, request))
        return (
            f"steps 1..{n + 1} answered in order; retry gave identical bytes without advancing "
            f"time; skipped seq -> sequence_error; +/-{_ABSURD_ACCELERATION:g} applied as "
            f"{applied[0]:g} / {applied[1]:g} m/s^2"
        )

    def _check_bounds(self, obs: Observation, request: float) -> float:
        assert self.welcome is not None
        low, high = self.welcome.action.acceleration_min, self.welcome.action.acceleration_max
        action = obs.action
        if not low - _TOLERANCE <= action.acceleration <= high + _TOLERANCE:
            raise CheckFailed(
                f"requested {request:g} m/s^2, applied {action.acceleration:g} outside the "
                f"announced bounds [{low:g}, {high:g}]"
            )
        if action.requested_acceleration != request:
            raise CheckFailed(
                f"requested {request:g} m/s^2 but the observation reports "
                f"requested_acceleration {action.requested_acceleration:g}"
            )
        if not action.acceleration_limited_by:
            raise CheckFailed(f"requested {request:g} m/s^2: acceleration_limited_by is empty")
        return action.acceleration

    def check_reconnect(self) -> str:
        history = self._running_episode(30, 2)
        last_bytes, _ = history[-1]
        self.probe.drop()  # a fresh socket that keeps the client's routing id
        try:
            again, reply = self.probe.exchange(Step(2, 0.0))
        except NoReply as exc:
            raise CheckFailed(
                "a client that reconnected with the same routing id got no reply: set "
                "ZMQ_ROUTER_HANDOVER on the server socket (protocol.md section 1)"
            ) from exc
        expect(reply, Observation, "step 2 retried on a fresh socket (same routing id)")
        if again != last_bytes:
            raise CheckFailed("step 2 retried on a fresh socket was not the cached reply")
        self._step(3, 0.0)
        return (
            "a fresh socket with the same routing id kept the session: the retried step got "
            "its cached reply and the episode went on"
        )

    def check_termination(self) -> str:
        assert self.scenario is not None
        options: dict[str, OptionValue] = {}
        default = self.scenario.options.get("max_episode_time")
        if isinstance(default, int | float) and not isinstance(default, bool):
            options["max_episode_time"] = type(default)(_SHORT_EPISODE_S)
        self._hello()
        self._reset(30, options)
        for seq in range(1, self.episode_budget + 1):
            data, obs = self._step(seq, 0.0)
            if _ended(obs):
                break
            if obs.reason:
                raise CheckFailed(f"step {seq} is running but has reason {obs.reason!r}")
        else:
            limit = f" with max_episode_time {_SHORT_EPISODE_S:g} s" if options else ""
            raise CheckFailed(f"the episode did not end within {self.episode_budget} steps{limit}")
        expected = {"time_limit"} if obs.truncated else set(TERMINAL_REASONS)
        if obs.terminated and obs.truncated:
            raise CheckFailed(f"step {seq} is both terminated and truncated")
        if obs.reason not in expected:
            kind = "truncated" if obs.truncated else "terminated"
            raise CheckFailed(f"{kind} episode has reason {obs.reason!r}, expected {expected}")
        retry, _ = self._step(seq, 0.0)
        if retry != data:
            raise CheckFailed(f"a retry of the terminal step {seq} did not return its cached reply")
        reply = self.probe.ask(Step(seq + 1, 0.0))
        expect_error(reply, ErrorCode.OUT_OF_ORDER, f"step {seq + 1} after the end")
        how = "truncated" if obs.truncated else "terminated"
        return (
            f"ended after {seq} steps ({how}, {obs.reason}); terminal retry cached; "
            "a step after the end -> out_of_order"
        )

    def check_bad_requests(self) -> str:
        assert self.welcome is not None and self.scenario is not None
        limit = self.welcome.max_frame_bytes
        step = {"type": "step", "seq": 1, "acceleration": 0.0}
        cases: list[tuple[str, bytes | dict[str, Any], ErrorCode]] = [
            ("garbage bytes", b"\xc1\xc1\xc1", ErrorCode.DECODE_ERROR),
            ("reset without scenario", {"type": "reset"}, ErrorCode.INVALID_MESSAGE),
            ("unknown type", {"type": "teleport"}, ErrorCode.UNKNOWN_TYPE),
            ("step before reset", step, ErrorCode.OUT_OF_ORDER),
        ]
        if limit <= _MAX_OVERSIZED_FRAME:
            padding = "x" * limit  # an unknown key, ignored by the receiver: only the size matters
            oversized = {"type": "hello", "protocol": list(PROTOCOL_VERSION), "padding": padding}
            cases.insert(1, (f"a frame over {limit} bytes", oversized, ErrorCode.FRAME_TOO_LARGE))
        problems: list[str] = []
        self._hello()
        for what, frame, code in cases:
            problems.extend(self._refused(frame, code, what))
            try:
                self._hello()  # after each refusal: the server still answers normally
            except (CheckFailed, NoReply, BadReply) as exc:
                problems.append(f"hello after {what}: {exc}")
                raise CheckFailed("; ".join(problems)) from exc
        self._reset(40)
        for value in (math.nan, -math.inf):  # on a running episode: unambiguously the number
            frame = {**step, "acceleration": value}
            problems.extend(self._refused(frame, ErrorCode.INVALID_NUMBER, f"{value} acceleration"))
        try:
            self._step(1, 0.0)
        except CheckFailed as exc:
            problems.append(f"after the refused steps: {exc}")
        if problems:
            raise CheckFailed("; ".join(problems))
        codes = sorted({code.value for _, _, code in cases} | {ErrorCode.INVALID_NUMBER.value})
        return f"{len(cases) + 2} bad requests refused ({', '.join(codes)}); served after each"

    def _refused(self, frame: bytes | dict[str, Any], code: ErrorCode, what: str) -> list[str]:
        """Problems (none or one) with the refusal of one bad request."""
        try:
            expect_error(self.probe.ask(frame), code, what)
        except (CheckFailed, BadReply) as exc:
            return [str(exc)]
        except NoReply as exc:
            return [f"{what}: {exc}"]
        return []

    def check_determinism(self) -> str:
        first = self._stream(7)
        second = self._stream(7)
        if first != second:
            index = next(
                (i for i, (a, b) in enumerate(zip(first, second, strict=False)) if a != b),
                min(len(first), len(second)),
            )
            raise CheckFailed(
                f"seed 7 twice: streams differ at seq {index}{_diff(first, second, index)}"
            )
        other = self._stream(8)
        if other == first:
            raise _Warning(
                f"seeds 7 and 8 gave the same {len(first)} observations: seeds seem ignored"
            )
        return f"seed 7 twice: {len(first)} identical observations; seed 8 differs"

    def _stream(self, seed: int) -> list[Observation]:
        self._hello()
        stream = [self._reset(seed)[1]]
        for seq in range(1, DETERMINISM_STEPS + 1):
            acceleration = _ACTION_PATTERN[seq % len(_ACTION_PATTERN)]
            stream.append(self._step(seq, acceleration, _LANE_CHANGES.get(seq, 0))[1])
            if _ended(stream[-1]):
                break
        return stream

    def check_close(self) -> str:
        self._hello()
        expect(self.probe.ask(Close()), Bye, "close")
        self._closed = True
        name = self.scenario.name if self.scenario else "cf"
        reply = self.probe.ask(Reset(name, 1), self.reset_timeout_s)
        expect_error(reply, ErrorCode.OUT_OF_ORDER, "reset after close")
        return "close -> bye; the session is over (reset -> out_of_order)"


class _Warning(Exception):
    """A check found something suspicious that the protocol does not forbid."""


def _ended(obs: Observation) -> bool:
    return obs.terminated or obs.truncated


def _diff(first: list[Observation], second: list[Observation], index: int) -> str:
    if index >= min(len(first), len(second)):
        return f" (lengths {len(first)} and {len(second)})"
    a, b = first[index], second[index]
    names = [f.name for f in fields(Observation) if getattr(a, f.name) != getattr(b, f.name)]
    return f" (in {', '.join(names)})"


def run_checks(
    address: str,
    scenario: str | None = None,
    timeout_s: float = STEP_TIMEOUT_S,
    reset_timeout_s: float = RESET_TIMEOUT_S,
) -> ConformanceReport:
    """Run every check against the server at `address`; see `Checker`."""
    return Checker(address, scenario, timeout_s, reset_timeout_s).run()
