"""What a `RemoteEnv` does with its scenario: the options it may send, and the first observation
of an episode, with insertion failures retried on other seeds.

Both are the client's side of docs/protocol.md §2.3 and §3 Reset, written once: driving,
evaluating, calibrating and training all reset through `RemoteEnv`, so an ego that cannot enter
is retried the same way everywhere (`INSERTION_ATTEMPTS` resets, then `InsertionFailed`).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TypeVar

from agent_client.defaults import INSERTION_ATTEMPTS, INSERTION_RETRY_SEED_STRIDE
from agent_client.errors import InsertionFailed, MalformedReply, ServerError, UsageError
from agent_client.transport.channel import Channel
from agent_client.transport.replies import TOLERANCE, ReplyChecker
from protocol.errors import ErrorCode
from protocol.messages import (
    Error,
    MultiObservation,
    Observation,
    OptionValue,
    Reset,
    ScenarioInfo,
)

log = logging.getLogger("agent_client")

SEEDS = 2**31
"""Seeds are 0 <= seed < 2^31 (§2.1)."""


def scenario_options(
    info: ScenarioInfo, options: dict[str, OptionValue], address: str
) -> dict[str, OptionValue]:
    """The options to send with every reset of `info`: those the user asked for, each one the
    scenario offers; raises `UsageError` naming the first it does not.

    A scenario without a ``decision_interval`` option decides at every simulation step
    (§2.3): asking for an interval equal to its ``step_length`` then needs no option and is
    dropped, any other interval is refused.
    """
    wanted = dict(options)
    if "decision_interval" in wanted and "decision_interval" not in info.options:
        interval = wanted.pop("decision_interval")
        step = info.step_length
        assert step is not None  # filled in by `replies.check_welcome`
        same = isinstance(interval, int | float) and not isinstance(interval, bool)
        if not (same and abs(float(interval) - step) <= TOLERANCE * max(1.0, step)):  # type: ignore[arg-type]
            raise UsageError(
                f"scenario {info.name} at {address} has no decision_interval option: each "
                f"step lasts one simulation step of {step:g} s, so decision_interval {interval} "
                f"cannot be applied (ask for {step:g}, or leave it out)"
            )
    unknown = sorted(set(wanted) - set(info.options))
    if unknown:
        raise UsageError(
            f"scenario {info.name} has no option {unknown[0]!r}; known: {', '.join(info.options)}"
        )
    return wanted


def retry_seed(seed: int, attempt: int) -> int:
    """The seed of retry `attempt` (1, 2, ...) of an episode of `seed` whose ego could not enter."""
    return (seed + attempt * INSERTION_RETRY_SEED_STRIDE) % SEEDS


First = TypeVar("First", Observation, MultiObservation)
"""What answers a reset: an observation, or a multi-ego frame after a reset naming ``egos``."""


def first_observation(
    channel: Channel, replies: ReplyChecker, timeout_s: float
) -> tuple[Observation, int | None]:
    """The observation answering the reset in flight on `channel`, and its seed (`first_reply`)."""
    return first_reply(channel, replies, timeout_s, Observation)


def first_reply(
    channel: Channel, replies: ReplyChecker, timeout_s: float, kind: type[First]
) -> tuple[First, int | None]:
    """The reply (of `kind`) to the reset in flight on `channel` and the seed that episode runs
    with.

    An ``insertion_failed`` reply is answered with the same reset on another seed
    (`retry_seed`), up to `INSERTION_ATTEMPTS` resets in all, then `InsertionFailed`; any other
    error reply raises `ServerError`, a reply that breaks the protocol `InvalidReply`.
    """
    tried: list[int] = []
    while True:
        request = channel.sent
        reply = replies.check(request, channel.receive(timeout_s))
        if isinstance(reply, kind):
            return reply, request.seed if isinstance(request, Reset) else None
        if not isinstance(reply, Error):
            raise MalformedReply(f"{channel.address}: expected {kind.TYPE}, got {reply.TYPE}")
        retryable = isinstance(request, Reset) and request.seed is not None
        if reply.code != ErrorCode.INSERTION_FAILED.value or not retryable:
            raise ServerError(reply.code, reply.message)
        assert isinstance(request, Reset) and request.seed is not None
        tried.append(request.seed)
        if len(tried) >= INSERTION_ATTEMPTS:
            raise InsertionFailed(request.scenario, tried, reply.message)
        seed = retry_seed(tried[0], len(tried))
        log.warning(
            "%s: the ego could not enter with seed %d (%s); retrying with seed %d (%d/%d)",
            request.scenario, request.seed, reply.message, seed, len(tried) + 1,
            INSERTION_ATTEMPTS,
        )  # fmt: skip
        channel.send(replace(request, seed=seed))
