"""The check of many egos in one simulation (since protocol 1.4, docs/protocol.md §3.1): resets
naming ``egos`` (and ``ego_share``, 1.5, where a scenario offers it), their ``multi_observation``
replies judged by the client's own rules, and the command set a ``multi_step`` must carry
(docs/conformance.md)."""

from __future__ import annotations

from agent_client.conformance.kit import CheckFailed, Kit, expect, expect_error
from protocol.errors import ErrorCode
from protocol.messages import (
    Command,
    Error,
    MultiObservation,
    MultiStep,
    Reply,
    Reset,
    Step,
)
from protocol.version import EGO_SHARE_VERSION, MANY_EGOS_VERSION, format_version

MULTI_STEPS = 3
"""multi_steps judged per episode."""
_ACCELERATIONS = (0.5, 0.0, -0.5)
_SEEDS = (70, 80, 90)
"""Seeds of the one-ego, the two-ego and the ``ego_share`` episodes (the one-ego check tries
the next two if its episode ends within `MULTI_STEPS`)."""
_SHARE = 0.5


def check_multi_ego(kit: Kit) -> str:
    """Resets with egos 1 and 2 answered with multi_observation, stepped with multi_step; a
    wrong command set gets invalid_message, a step out_of_order (§3.1)."""
    assert kit.scenario is not None and kit.welcome is not None
    if kit.welcome.protocol < MANY_EGOS_VERSION:
        return (
            f"protocol {format_version(kit.welcome.protocol)}: many egos came with "
            f"{format_version(MANY_EGOS_VERSION)}, nothing to check"
        )
    if "egos" not in kit.scenario.options:
        return (
            f"scenario {kit.scenario.name} offers no option egos (one ego only): nothing to check"
        )
    kit.hello()
    frame, seq = _running(kit, 1, _SEEDS[0])
    ids = ", ".join(e.id for e in frame.egos)
    _wrong_commands(kit, frame, seq)
    two = _two(kit)
    return (
        f"egos 1 ({ids}): seq 0 and {seq} multi_steps judged, the retry cached; missing, unknown "
        f"and repeated commands -> invalid_message, step -> out_of_order; egos 2: {two}; "
        f"ego_share: {_share(kit)}"
    )


def _share(kit: Kit) -> str:
    """A share of the traffic (1.5) where the scenario offers it: its frames judged (egos that
    join included), and egos named beside it refused with invalid_option."""
    assert kit.scenario is not None and kit.welcome is not None
    if kit.welcome.protocol < EGO_SHARE_VERSION or "ego_share" not in kit.scenario.options:
        return "not offered"
    both = Reset(kit.scenario.name, _SEEDS[2], {"egos": 2, "ego_share": _SHARE})
    expect_error(kit.ask(both), ErrorCode.INVALID_OPTION, "a reset naming egos and ego_share")
    request = Reset(kit.scenario.name, _SEEDS[2], {"ego_share": _SHARE})
    reply = kit.judged(request, kit.probe.ask(request, kit.reset_timeout_s))
    first = expect(reply, MultiObservation, f"reset with ego_share {_SHARE}")
    _, seq = _steps(kit, first)
    return (
        f"{_SHARE:g} -> {len(first.egos)} egos at seq 0, {seq} multi_steps judged; with egos "
        "-> invalid_option"
    )


def _two(kit: Kit) -> str:
    """Two egos, or invalid_option from a server that drives one."""
    assert kit.scenario is not None
    request = Reset(kit.scenario.name, _SEEDS[1], {"egos": 2})
    reply = kit.judged(request, kit.probe.ask(request, kit.reset_timeout_s))
    if isinstance(reply, Error) and reply.code == ErrorCode.INVALID_OPTION.value:
        return "invalid_option (one ego only)"
    first = expect(reply, MultiObservation, "reset with egos 2")
    _, seq = _steps(kit, first)
    return (
        f"{len(first.egos)} egos ({', '.join(e.id for e in first.egos)}), {seq} multi_steps judged"
    )


def _reset(kit: Kit, egos: int, seed: int) -> MultiObservation:
    assert kit.scenario is not None
    request = Reset(kit.scenario.name, seed, {"egos": egos})
    reply = kit.probe.ask(request, kit.reset_timeout_s)
    return expect(kit.judged(request, reply), MultiObservation, f"reset with egos {egos}")


def _running(kit: Kit, egos: int, seed: int) -> tuple[MultiObservation, int]:
    """The last frame and seq of `MULTI_STEPS` multi_steps in an episode that goes on (three
    seeds tried), the last one retried."""
    for attempt in range(3):
        frame, seq = _steps(kit, _reset(kit, egos, seed + attempt))
        if not _ended(frame):
            return frame, seq
    raise CheckFailed(
        f"three episodes with egos {egos} ended within {MULTI_STEPS} steps; cannot test stepping"
    )


def _steps(kit: Kit, frame: MultiObservation) -> tuple[MultiObservation, int]:
    """Up to `MULTI_STEPS` multi_steps, one command per running ego, each judged; the last is
    sent twice and must get its first answer's bytes (§3 Steps)."""
    seq, data, request = 0, b"", None
    while seq < MULTI_STEPS and not _ended(frame):
        seq += 1
        request = MultiStep(seq, _commands(frame, _ACCELERATIONS[seq % len(_ACCELERATIONS)]))
        data, reply = kit.probe.exchange(request)
        frame = expect(kit.judged(request, reply), MultiObservation, f"multi_step {seq}")
    if request is not None:
        again, reply = kit.probe.exchange(request)
        kit.judged(request, reply)
        if again != data:
            raise CheckFailed(f"a retry of multi_step {seq} did not return the identical reply")
    return frame, seq


def _wrong_commands(kit: Kit, frame: MultiObservation, seq: int) -> None:
    """Commands missing, for no such ego, or twice for one: invalid_message, and the episode
    goes on; a one-ego step in it: out_of_order."""
    commands = _commands(frame, 0.0)
    ghost = "no-such-ego"
    while ghost in {e.id for e in frame.egos}:
        ghost += "-really"
    wrong = {
        "a multi_step without commands": (),
        f"a multi_step with a command for {ghost!r}": (*commands, Command(ghost, 0.0)),
        "a multi_step with two commands for one ego": (*commands, commands[0]),
    }
    for what, bad in wrong.items():
        request = MultiStep(seq + 1, bad)
        expect_error(_judged(kit, request), ErrorCode.INVALID_MESSAGE, what)
    step = Step(seq + 1, 0.0)
    expect_error(kit.ask(step), ErrorCode.OUT_OF_ORDER, "a step in a multi-ego episode")
    request = MultiStep(seq + 1, commands)
    expect(_judged(kit, request), MultiObservation, f"multi_step {seq + 1} after the refusals")


def _judged(kit: Kit, request: MultiStep) -> Reply:
    return kit.judged(request, kit.probe.ask(request))


def _commands(frame: MultiObservation, acceleration: float) -> tuple[Command, ...]:
    return tuple(
        Command(e.id, acceleration) for e in frame.egos if not (e.terminated or e.truncated)
    )


def _ended(frame: MultiObservation) -> bool:
    return frame.terminated or frame.truncated
