"""The checks of the state machine: episodes, steps and their order, who owns the simulator,
and the end of a session (docs/conformance.md)."""

from __future__ import annotations

import itertools
import time
from dataclasses import fields

from agent_client.conformance.kit import (
    CheckFailed,
    CheckWarning,
    Kit,
    ended,
    expect,
    expect_error,
)
from agent_client.conformance.probe import CLIENT_NAME, NoReply, Probe
from agent_client.transport.replies import TOLERANCE
from protocol.errors import ErrorCode
from protocol.messages import (
    Bye,
    Close,
    Error,
    Hello,
    Observation,
    OptionValue,
    Reset,
    Step,
    Welcome,
)
from protocol.version import PROTOCOL_VERSION

DETERMINISM_STEPS = 50
_ACTION_PATTERN = (0.5, 0.0, -0.5, 1.0, -1.0)
_LANE_CHANGES = {10: 1, 30: -1}
_ABSURD_ACCELERATION = 1000.0
_SHORT_EPISODE_S = 2.0
_TAKEOVER_POLL_S = 0.05


def check_reset(kit: Kit) -> str:
    """A reset starts a running episode at seq 0; bad resets get their codes (§3 Reset)."""
    assert kit.scenario is not None and kit.welcome is not None
    kit.hello()
    kit.reset(3)
    offered = {s.name for s in kit.welcome.scenarios}
    unknown = "no-such-scenario"
    while unknown in offered:
        unknown += "-really"
    reply = kit.ask(Reset(unknown, 1), kit.reset_timeout_s)
    expect_error(reply, ErrorCode.UNKNOWN_SCENARIO, f"reset {unknown!r}")
    option = "no_such_option"
    while option in kit.scenario.options:
        option += "_really"
    reply = kit.ask(Reset(kit.scenario.name, 1, {option: 1}), kit.reset_timeout_s)
    expect_error(reply, ErrorCode.INVALID_OPTION, f"reset with option {option!r}")
    reply = kit.ask(Reset(kit.scenario.name, 2**31), kit.reset_timeout_s)
    expect_error(reply, ErrorCode.INVALID_NUMBER, "reset with seed 2^31")
    return (
        "seq 0, running; unknown scenario -> unknown_scenario, unknown option -> "
        "invalid_option, seed 2^31 -> invalid_number"
    )


def check_step(kit: Kit) -> str:
    """Steps answered in order, retried from cache, each one decision long (§3 Steps)."""
    n = 5
    history = kit.running_episode(10, n)
    last_bytes, _ = history[-1]
    retry_bytes, _ = kit.step(n, 0.0)
    if retry_bytes != last_bytes:
        raise CheckFailed(f"a retry of step {n} did not return the identical cached reply")
    _, after = kit.step(n + 1, 0.0)
    interval = kit.decision_interval
    times = [obs.time for _, obs in history] + [after.time]
    for seq, (before, now) in enumerate(itertools.pairwise(times), start=1):
        if abs((now - before) - interval) > TOLERANCE * max(1.0, abs(now)):
            raise CheckFailed(
                f"step {seq} advanced time by {now - before:g} s instead of one decision of "
                f"{interval:g} s (the scenario's decision_interval, else its step_length; "
                "§2.3)" + (": the retry advanced the simulation" if seq == n + 1 else "")
            )
    reply = kit.ask(Step(n + 3, 0.0))
    expect_error(reply, ErrorCode.SEQUENCE_ERROR, f"step {n + 3} after step {n + 1}")
    seq = n + 1
    applied = []
    for request in (_ABSURD_ACCELERATION, -_ABSURD_ACCELERATION):
        if ended(after):  # the previous action ended the episode: start another
            kit.hello()
            kit.reset(20)
            seq = 0
        seq += 1
        _, after = kit.step(seq, request)
        applied.append(after.action.acceleration)
    return (
        f"steps 1..{n + 1} answered in order, each {interval:g} s long; retry gave identical "
        f"bytes without advancing time; skipped seq -> sequence_error; "
        f"+/-{_ABSURD_ACCELERATION:g} applied as {applied[0]:g} / {applied[1]:g} m/s^2"
    )


def check_reconnect(kit: Kit) -> str:
    """A second connection under the same routing id takes the session over (§1, §7.1)."""
    history = kit.running_episode(30, 2)
    last_bytes, _ = history[-1]
    old = kit.probe.handover()  # the first connection stays up meanwhile
    try:
        again, reply = kit.probe.exchange(Step(2, 0.0))
    except NoReply as exc:
        raise CheckFailed(
            "a second connection with the same routing id got no reply while the first was "
            "still up: hand the routing id over to the new connection (ZeroMQ: a ROUTER socket "
            "with ZMQ_ROUTER_HANDOVER; protocol.md §7.1)"
        ) from exc
    finally:
        old.close()
    expect(reply, Observation, "step 2 retried on a second connection (same routing id)")
    if again != last_bytes:
        raise CheckFailed("step 2 retried on a second connection was not the cached reply")
    kit.step(3, 0.0)
    return (
        "a second connection with the same routing id, opened while the first was up, took "
        "the session over: the retried step got its cached reply and the episode went on"
    )


def check_ownership(kit: Kit) -> str:
    """One client at a time; a client whose connection closed frees the server at once (§3)."""
    kit.running_episode(50, 1)
    other = Probe(kit.address, kit.timeout_s, "agent-client-check-other")
    try:
        first = other.ask(Hello(PROTOCOL_VERSION, CLIENT_NAME))
        if isinstance(first, Welcome):  # a server of several sessions: this one was free
            return _sessions_apart(kit, other)
        expect_error(first, ErrorCode.BUSY, "another client's hello")
        for request in (Step(2, 0.0), Close()):
            expect_error(other.ask(request), ErrorCode.BUSY, f"another client's {request.TYPE}")
        kit.step(2, 0.0)  # the owner's episode is untouched
        kit.probe.drop()  # the owner is "killed": its connection closes without a close
        waited = _take_over(kit, other)
        reply = kit.ask(Hello(PROTOCOL_VERSION, CLIENT_NAME))  # back, under its old routing id
        expect_error(reply, ErrorCode.BUSY, "the first client's hello after the takeover")
        expect(other.ask(Close()), Bye, "the second client's close")
        kit.hello()
    finally:
        other.close()
    return (
        "another client's hello, step and close -> busy; after the owner's connection closed "
        f"the other took over in {waited:.2f} s; then the first got busy until the other closed"
    )


def _sessions_apart(kit: Kit, other: Probe) -> str:
    """A second client welcomed beside the first (a pool, §3 Ownership): its episode and the
    owner's go on side by side, neither disturbing the other."""
    assert kit.scenario is not None
    expect(other.ask(Reset(kit.scenario.name, 2), kit.reset_timeout_s), Observation,
           "the second session's reset")  # fmt: skip
    for seq in (1, 2, 3):  # past the owner's next seq: on one shared episode its 2 is refused
        expect(other.ask(Step(seq, 0.0)), Observation, f"the second session's step {seq}")
    kit.step(2, 0.0)  # the owner's episode is untouched: its seq 2 is still the next
    expect(other.ask(Close()), Bye, "the second client's close")
    kit.step(3, 0.0)
    return (
        "a second client was welcomed beside the first (a server of several sessions): both "
        "episodes went on side by side, each in its own order"
    )


def _take_over(kit: Kit, other: Probe) -> float:
    """Seconds until the second client's hello is welcomed (the owner's connection is gone)."""
    start = time.monotonic()
    deadline = start + kit.timeout_s
    while True:
        reply = other.ask(Hello(PROTOCOL_VERSION, CLIENT_NAME))
        if not (isinstance(reply, Error) and reply.code == ErrorCode.BUSY.value):
            expect(reply, Welcome, "the second client's hello")
            return time.monotonic() - start
        if time.monotonic() >= deadline:
            raise CheckFailed(
                f"{kit.timeout_s:g} s after the owner's connection closed (without close) the "
                "server still answered busy: free the simulator when the owner's connection goes "
                "(§3 Ownership; how to learn of it: protocol.md §7.1)"
            )
        time.sleep(_TAKEOVER_POLL_S)


def check_termination(kit: Kit) -> str:
    """An episode ends, terminated or truncated with its reason; then out_of_order (§3, §4.1)."""
    assert kit.scenario is not None
    options: dict[str, OptionValue] = {}
    default = kit.scenario.options.get("max_episode_time")
    if isinstance(default, int | float) and not isinstance(default, bool):
        options["max_episode_time"] = type(default)(_SHORT_EPISODE_S)
    kit.hello()
    kit.reset(30, options)
    for seq in range(1, kit.episode_budget + 1):
        data, obs = kit.step(seq, 0.0)
        if ended(obs):
            break
    else:
        limit = f" with max_episode_time {_SHORT_EPISODE_S:g} s" if options else ""
        raise CheckFailed(f"the episode did not end within {kit.episode_budget} steps{limit}")
    retry, _ = kit.step(seq, 0.0)
    if retry != data:
        raise CheckFailed(f"a retry of the terminal step {seq} did not return its cached reply")
    for after in (seq + 1, seq + 5):
        expect_error(
            kit.ask(Step(after, 0.0)), ErrorCode.OUT_OF_ORDER, f"step {after} after the end"
        )
    how = "truncated" if obs.truncated else "terminated"
    return (
        f"ended after {seq} steps ({how}, {obs.reason}); terminal retry cached; "
        "steps after the end -> out_of_order"
    )


def check_ordering(kit: Kit) -> str:
    """The state machine's corners: seq 0 and negative seqs, refused resets, hello (§3)."""
    assert kit.scenario is not None
    kit.hello()
    kit.reset(60)
    for seq in (0, -1, 2):
        expect_error(kit.ask(Step(seq, 0.0)), ErrorCode.SEQUENCE_ERROR, f"step {seq} after reset")
    expect_error(
        kit.ask({"type": "step", "seq": 2**63, "acceleration": 0.0}),
        ErrorCode.INVALID_NUMBER,
        "step 2^63 (outside int64)",
    )
    kit.step(1, 0.0)
    reply = kit.ask(Reset("no-such-scenario-at-all", 1), kit.reset_timeout_s)
    expect_error(reply, ErrorCode.UNKNOWN_SCENARIO, "reset of an unknown scenario")
    kit.step(2, 0.0)  # a refused reset leaves the running episode as it was
    kit.reset(61)
    kit.reset(62)  # a reset while an episode runs starts another
    kit.step(1, 0.0)
    kit.hello()  # a hello ends the episode
    expect_error(kit.ask(Step(2, 0.0)), ErrorCode.OUT_OF_ORDER, "step 2 after a new hello")
    return (
        "step 0, -1 and 2 after reset -> sequence_error, seq 2^63 -> invalid_number; a refused "
        "reset keeps the episode; a reset restarts it; a hello ends it (step -> out_of_order)"
    )


def check_determinism(kit: Kit) -> str:
    """The same seed gives the same stream (§3 Reset)."""
    first = _stream(kit, 7)
    second = _stream(kit, 7)
    if first != second:
        index = next(
            (i for i, (a, b) in enumerate(zip(first, second, strict=False)) if a != b),
            min(len(first), len(second)),
        )
        raise CheckFailed(
            f"seed 7 twice: streams differ at seq {index}{_diff(first, second, index)}"
        )
    other = _stream(kit, 8)
    if other == first:
        raise CheckWarning(
            f"seeds 7 and 8 gave the same {len(first)} observations: seeds seem ignored"
        )
    return f"seed 7 twice: {len(first)} identical observations; seed 8 differs"


def _stream(kit: Kit, seed: int) -> list[Observation]:
    kit.hello()
    stream = [kit.reset(seed)[1]]
    for seq in range(1, DETERMINISM_STEPS + 1):
        acceleration = _ACTION_PATTERN[seq % len(_ACTION_PATTERN)]
        stream.append(kit.step(seq, acceleration, _LANE_CHANGES.get(seq, 0))[1])
        if ended(stream[-1]):
            break
    return stream


def _diff(first: list[Observation], second: list[Observation], index: int) -> str:
    if index >= min(len(first), len(second)):
        return f" (lengths {len(first)} and {len(second)})"
    a, b = first[index], second[index]
    names = [f.name for f in fields(Observation) if getattr(a, f.name) != getattr(b, f.name)]
    return f" (in {', '.join(names)})"


def check_close(kit: Kit) -> str:
    """Close gets bye and ends the session (§2.1, §3)."""
    kit.hello()
    expect(kit.ask(Close()), Bye, "close")
    kit.closed = True
    name = kit.scenario.name if kit.scenario else "cf"
    reply = kit.ask(Reset(name, 1), kit.reset_timeout_s)
    expect_error(reply, ErrorCode.OUT_OF_ORDER, "reset after close")
    return "close -> bye; the session is over (reset -> out_of_order)"
