"""Error codes carried by `Error` replies, and the exception the codec raises."""

from __future__ import annotations

from enum import StrEnum


class ErrorCode(StrEnum):
    """Stable, machine-readable reasons for refusing a request (see docs/protocol.md)."""

    DECODE_ERROR = "decode_error"
    """The frame is not a msgpack map."""
    FRAME_TOO_LARGE = "frame_too_large"
    """The frame is longer than the announced `max_frame_bytes`."""
    INVALID_MESSAGE = "invalid_message"
    """A field is missing or has the wrong type."""
    INVALID_NUMBER = "invalid_number"
    """A number is NaN or infinite, or outside its allowed range."""
    UNKNOWN_TYPE = "unknown_type"
    """The ``type`` key names no request of this protocol."""
    OUT_OF_ORDER = "out_of_order"
    """The request is not allowed now (a step before reset, a reset before hello...)."""
    VERSION_MISMATCH = "version_mismatch"
    """The client's major protocol version differs from the server's."""
    UNKNOWN_SCENARIO = "unknown_scenario"
    """The reset names a scenario the server does not offer."""
    INVALID_OPTION = "invalid_option"
    """A reset option is unknown or has a bad value."""
    SEQUENCE_ERROR = "sequence_error"
    """A step's sequence number is neither the next one nor a repeat of the last one."""
    INSERTION_FAILED = "insertion_failed"
    """The ego could not enter the simulation within the allowed time."""
    SIMULATOR_ERROR = "simulator_error"
    """The simulator failed; the episode is over and the next reset starts afresh."""
    BUSY = "busy"
    """Another client holds the simulation."""


class ProtocolError(Exception):
    """A message that cannot be accepted; `code` says why, `field` where ("" for the frame)."""

    def __init__(self, code: ErrorCode, message: str, field: str = "") -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.field = field
