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


class UsageError(BridgeError, ValueError):
    """A bad value given by the user (one line naming it and the valid ones)."""


class FeatureMismatch(BridgeError):
    """A saved network takes another number of features than its feature set now has."""
