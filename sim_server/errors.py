"""The simulator side's exceptions: one root, so a caller can catch everything the server raises
on purpose apart from bugs."""

from __future__ import annotations

from protocol.errors import ErrorCode


class SimServerError(Exception):
    """Root of the errors the simulator side raises on purpose."""


class BackendError(SimServerError):
    """A failure the server reports to its client as an `Error` reply with `code`."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class UsageError(SimServerError):
    """A command line that cannot be served as given; ``sim-server`` prints it on one line and
    exits with status 2."""
