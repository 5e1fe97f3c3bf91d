"""Every error the learner side raises, under one root: `BridgeError`.

Usage errors (a bad scenario, reward, option, driver spec or file) are `UsageError`: the CLI
prints their one line and exits with status 2. The others say what went wrong with the server
or the wire.
"""

from __future__ import annotations


class BridgeError(Exception):
    """Base class of the client's errors."""


class ServerUnavailable(BridgeError):
    """The server cannot be reached or stopped answering; a retry policy may reconnect."""


class ServerTimeout(ServerUnavailable):
    """The server did not answer within the deadline (dead, hung or unreachable)."""


class ServerLost(ServerUnavailable):
    """The connection broke while a request was in flight (the server died or froze)."""


class AuthenticationFailed(BridgeError):
    """The server refused the CURVE handshake (wrong keys, or keys where none are expected)."""


class ServerError(BridgeError):
    """The server refused a request with an `Error` reply."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class MalformedReply(BridgeError):
    """The server sent something that is not a valid reply of this protocol."""


class InvalidReply(MalformedReply):
    """A reply that breaks one rule of docs/protocol.md: `field` names where, `value` what was
    sent there (None when the frame itself is at fault) and `rule` what the protocol requires.

    Raised by the client on every reply (`agent_client.transport.replies`); the conformance kit
    fails a server with the same words.
    """

    def __init__(self, field: str, value: object, rule: str, source: str = "") -> None:
        shown = f"{field} = {_show(value)}" if value is not None else field
        super().__init__(f"{source}: {shown}: {rule}" if source else f"{shown}: {rule}")
        self.field = field
        self.value = value
        self.rule = rule
        self.source = source


def _show(value: object) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value) if isinstance(value, str) else str(value)


class InsertionFailed(BridgeError):
    """The ego could not enter the simulation: every reset attempt got ``insertion_failed``.

    Not a `ServerError`: the retries (`agent_client.defaults.INSERTION_ATTEMPTS` resets, each
    with another seed) are done, so catching it means giving up on these scenario settings.
    """

    def __init__(self, scenario: str, seeds: list[int], message: str) -> None:
        super().__init__(
            f"scenario {scenario}: the ego could not enter in {len(seeds)} attempt(s) "
            f"(seeds {', '.join(map(str, seeds))}); the server said: {message}"
        )
        self.scenario = scenario
        self.seeds = seeds
        self.message = message


class UsageError(BridgeError, ValueError):
    """A bad value given by the user (one line naming it and the valid ones)."""


class FeatureMismatch(BridgeError):
    """A saved network takes another number of features than its feature set now has."""
