"""What every check shares: the probe, the welcome, the client's own reply rules, and helpers.

A check is a function of the `Kit` that returns its one-line detail, or raises `CheckFailed`
(or `CheckWarning`). Every observation the helpers receive is judged by the client's
`ReplyChecker` (`agent_client.transport.replies`), so a server the client would refuse fails
here with the same words.
"""

from __future__ import annotations

from typing import Any, TypeVar

from agent_client.conformance.probe import CLIENT_NAME, Probe, describe
from agent_client.errors import BridgeError, InvalidReply, UsageError
from agent_client.transport.replies import ReplyChecker
from protocol.errors import ErrorCode
from protocol.messages import (
    Error,
    Hello,
    Observation,
    OptionValue,
    Reply,
    Request,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.version import PROTOCOL_VERSION

R = TypeVar("R", bound=Reply)


class ServerUnreachable(BridgeError):
    """The server did not answer the first hello (or another client holds it)."""


class ScenarioNotOffered(UsageError):
    """The scenario asked for is not in the server's welcome (a usage error, not a fault)."""


class CheckFailed(Exception):
    """A check's expectation was not met; the message is the one-line detail."""


class CheckWarning(Exception):
    """A check found something suspicious that the protocol does not forbid."""


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


def ended(obs: Observation) -> bool:
    return obs.terminated or obs.truncated


class Kit:
    """The state the checks share: one probe (one client), the welcome and the reply rules."""

    def __init__(
        self,
        address: str,
        scenario: str | None,
        timeout_s: float,
        reset_timeout_s: float,
        episode_budget: int,
    ) -> None:
        self.address = address
        self.requested_scenario = scenario
        self.timeout_s = timeout_s
        self.reset_timeout_s = max(timeout_s, reset_timeout_s)
        self.episode_budget = episode_budget
        self.probe = Probe(address, timeout_s)
        self.welcome: Welcome | None = None
        """The welcome, with the step lengths a 1.0/1.1 server left out assumed."""
        self.announced: Welcome | None = None
        """The welcome as the server sent it."""
        self.scenario: ScenarioInfo | None = None
        self.notes: list[str] = []
        """What the kit assumed about the welcome (a 1.0/1.1 server without step lengths)."""
        self.replies: ReplyChecker | None = None
        self.closed = False
        self.reaches_req = True
        """False when the transport check saw replies without the request-id frame."""

    # ----------------------------------------------------------------------- requests

    def judged(self, request: Request, reply: Reply) -> Reply:
        """`reply` if the client's rules accept it as the answer to `request`."""
        if self.replies is None:
            return reply
        try:
            return self.replies.check(request, reply)
        except InvalidReply as exc:
            raise CheckFailed(f"{describe(request)}: {exc}") from exc

    def hello(self) -> Welcome:
        self.closed = False
        request = Hello(PROTOCOL_VERSION, CLIENT_NAME)
        return expect(self.judged(request, self.probe.ask(request)), Welcome, "hello")

    def reset(
        self, seed: int | None, options: dict[str, OptionValue] | None = None
    ) -> tuple[bytes, Observation]:
        assert self.scenario is not None
        request = Reset(self.scenario.name, seed, options or {})
        data, reply = self.probe.exchange(request, self.reset_timeout_s)
        obs = expect(self.judged(request, reply), Observation, describe(request))
        return data, obs

    def step(
        self, seq: int, acceleration: float, lane_change: int = 0
    ) -> tuple[bytes, Observation]:
        request = Step(seq, acceleration, lane_change)
        data, reply = self.probe.exchange(request)
        return data, expect(self.judged(request, reply), Observation, f"step {seq}")

    def ask(
        self, request: Request | dict[str, Any] | bytes, timeout_s: float | None = None
    ) -> Reply:
        """A request whose reply the kit judges itself (errors, malformed requests)."""
        return self.probe.ask(request, timeout_s)

    def running_episode(self, seed: int, steps: int) -> list[tuple[bytes, Observation]]:
        """Hello, reset and `steps` steps of zero acceleration in an episode that does not end."""
        self.hello()
        for attempt in range(3):
            history = [self.reset(seed + attempt)]
            for seq in range(1, steps + 1):
                history.append(self.step(seq, 0.0))
                if ended(history[-1][1]):
                    break
            else:
                return history
        raise CheckFailed(f"three episodes ended within {steps} steps; cannot test stepping")

    # ----------------------------------------------------------------------- the scenario

    @property
    def decision_interval(self) -> float:
        """Seconds a step lasts with the scenario's defaults (§2.3)."""
        assert self.scenario is not None and self.scenario.step_length is not None
        interval = self.scenario.options.get("decision_interval")
        return interval if isinstance(interval, float) else self.scenario.step_length

    def option_of(self, kind: type) -> tuple[str, OptionValue] | None:
        """An option of the scenario whose default is of `kind` (None if it has none)."""
        assert self.scenario is not None
        for name, default in self.scenario.options.items():
            if type(default) is kind:
                return name, default
        return None
