"""Protocol conformance checks: probe any bridge server with raw frames and judge its replies.

The checks use only the wire (docs/protocol.md), through the client's own transport
(`agent_client.conformance.probe`) and, for the envelope, raw sockets
(`agent_client.conformance.raw`): frames built with `protocol.codec` (or raw msgpack for
malformed ones), replies parsed with `protocol.codec.decode_reply` and judged by the client's
own rules (`agent_client.transport.replies`). They never look inside a server, so they judge a
server written for any simulator in any language. Every receive has a deadline. The checks
themselves are in `wire_checks` (what travels), `session_checks` (the state machine) and
`multi_checks` (many egos, protocol 1.4); see docs/conformance.md for what each verifies.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

from agent_client.conformance import multi_checks as multi
from agent_client.conformance import session_checks as session
from agent_client.conformance import wire_checks as wire
from agent_client.conformance.kit import (
    CheckFailed,
    CheckWarning,
    Kit,
    ScenarioNotOffered,
    ServerUnreachable,
)
from agent_client.conformance.probe import CLIENT_NAME, BadReply, NoReply
from agent_client.conformance.result import FAIL, PASS, SKIP, WARN, CheckResult, ConformanceReport
from agent_client.defaults import RESET_TIMEOUT_S, STEP_TIMEOUT_S
from protocol.errors import ErrorCode
from protocol.messages import Close, Error, Hello, Reply
from protocol.transport.endpoint import parse_endpoint
from protocol.version import PROTOCOL_VERSION

__all__ = ["PASS", "Checker", "ScenarioNotOffered", "ServerUnreachable", "run_checks"]

EPISODE_BUDGET = 3000
"""Steps the termination check waits for an episode to end (with a short time limit if any)."""

Check = Callable[[Kit], str]
CHECKS: tuple[tuple[str, Check], ...] = (
    ("version_refusal", wire.check_version_refusal),
    ("schema", wire.check_schema),
    ("reset", session.check_reset),
    ("step", session.check_step),
    ("reconnect", session.check_reconnect),
    ("ownership", session.check_ownership),
    ("termination", session.check_termination),
    ("ordering", session.check_ordering),
    ("bad_requests", wire.check_bad_requests),
    ("error_codes", wire.check_error_codes),
    ("determinism", session.check_determinism),
    ("multi_ego", multi.check_multi_ego),
    ("close", session.check_close),
)
"""The checks after `transport` and `handshake`, in order."""
NAMES = ("transport", "handshake", *(name for name, _ in CHECKS))


class Checker(Kit):
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
        super().__init__(address, scenario, timeout_s, reset_timeout_s, episode_budget)

    def run(self) -> ConformanceReport:
        """All checks.

        Raises ServerUnreachable when the first hello gets no answer or `busy`, and
        ScenarioNotOffered when the server does not offer the requested scenario.
        """
        report = ConformanceReport(self.address, self.requested_scenario)
        results = report.results
        interrupted = False
        try:
            transport = self._transport()
            results.append(transport)
            first = self._first_contact(transport)
            if self.reaches_req:
                handshake = self._guarded("handshake", lambda kit: wire.check_handshake(kit, first))
            else:
                handshake = CheckResult("handshake", FAIL, wire.UNREACHABLE_REQ)
            results.append(handshake)
            report.scenario = self.scenario.name if self.scenario else self.requested_scenario
            silent = 0
            for name, check in CHECKS:
                if self.scenario is None and (name != "close" or not self.reaches_req):
                    results.append(CheckResult(name, SKIP, "needs a valid welcome"))
                elif silent >= 2:
                    results.append(CheckResult(name, FAIL, "not run: the server stopped answering"))
                else:
                    result = self._guarded(name, check)
                    silent = silent + 1 if result.detail.startswith("no reply") else 0
                    results.append(result)
        except KeyboardInterrupt:
            interrupted = True  # no goodbye: closing the connection frees the server too
            raise
        finally:
            self._leave(polite=not interrupted)
        return report

    def _transport(self) -> CheckResult:
        try:
            return self._guarded("transport", wire.check_transport, strict=True)
        except wire.ServerBusy as exc:
            raise ServerUnreachable(f"{self.address} is busy with another client: {exc}") from exc
        except NoReply as exc:
            raise ServerUnreachable(
                f"no reply from {self.address} within {self.timeout_s:g} s "
                "(is the server running and reachable?)"
            ) from exc

    def _first_contact(self, transport: CheckResult) -> Reply:
        if not self.reaches_req:
            return Error("not run", wire.UNREACHABLE_REQ)
        try:
            reply = self.probe.ask(Hello(PROTOCOL_VERSION, CLIENT_NAME))
        except NoReply as exc:
            if transport.status == FAIL:
                return Error("no reply", str(exc))  # the transport check says why
            raise ServerUnreachable(
                f"no reply from {self.address} within {self.probe.timeout_s:g} s "
                "(is the server running and reachable?)"
            ) from exc
        except BadReply as exc:
            return Error("malformed", str(exc))  # judged (and failed) by the handshake check
        if isinstance(reply, Error) and reply.code == ErrorCode.BUSY.value:
            raise ServerUnreachable(f"{self.address} is busy with another client: {reply.message}")
        return reply

    def _guarded(self, name: str, check: Check, strict: bool = False) -> CheckResult:
        """Run one check; `strict` lets NoReply through (the caller decides what it means)."""
        discarded = self.probe.discarded
        try:
            detail = check(self)
        except ScenarioNotOffered:
            raise
        except CheckWarning as exc:
            return CheckResult(name, WARN, str(exc))
        except CheckFailed as exc:
            return CheckResult(name, FAIL, str(exc))
        except NoReply as exc:
            if strict:
                raise
            return CheckResult(name, FAIL, f"{exc} (the socket was replaced)")
        except BadReply as exc:
            return CheckResult(name, FAIL, str(exc))
        except Exception as exc:  # a misbehaving server may break any assumption: report it
            return CheckResult(name, FAIL, f"unexpected {type(exc).__name__}: {exc}")
        extra = self.probe.discarded - discarded
        if extra and not self.probe.timeouts:  # late replies after a timeout are expected
            return CheckResult(
                name,
                FAIL,
                f"{extra} {'reply' if extra == 1 else 'replies'} arrived that answered no request "
                "in flight (discarded by the REQ socket): one request gets exactly one reply (§1)",
            )
        return CheckResult(name, PASS, detail)

    def _leave(self, polite: bool) -> None:
        """Free the server for the next client (a goodbye, unless interrupted) and release the
        socket."""
        try:
            if polite and not self.closed:
                with contextlib.suppress(NoReply, BadReply):
                    self.probe.ask(Close(), timeout_s=min(self.probe.timeout_s, 2.0))
        finally:
            self.probe.close()


def run_checks(
    address: str,
    scenario: str | None = None,
    timeout_s: float = STEP_TIMEOUT_S,
    reset_timeout_s: float = RESET_TIMEOUT_S,
) -> ConformanceReport:
    """Run every check against the server at `address`; see `Checker`."""
    return Checker(address, scenario, timeout_s, reset_timeout_s).run()
