"""The bridge's wire: versioned msgpack messages over ZeroMQ, shared by server and client.

This package imports neither the simulator side nor the learner side, nor SUMO, nor torch.
"""

from protocol.codec import DEFAULT_MAX_FRAME_BYTES, decode_reply, decode_request, encode
from protocol.errors import ErrorCode, ProtocolError
from protocol.messages import (
    AccelerationLimit,
    ActionSchema,
    AppliedAction,
    Bye,
    Close,
    Ego,
    EndReason,
    Error,
    Events,
    FieldSpec,
    Hello,
    LaneChange,
    LaneChangeRefusal,
    LeaderTrip,
    Message,
    Neighbour,
    Neighbours,
    Observation,
    Reply,
    Request,
    Reset,
    ScenarioInfo,
    Step,
    Welcome,
)
from protocol.schema import NEIGHBOUR_SLOTS, OBSERVATION_FIELDS, Flattener
from protocol.transport.endpoint import DEFAULT_ADDRESS, Endpoint, parse_endpoint
from protocol.version import PROTOCOL_VERSION, format_version, is_compatible

__all__ = [
    "DEFAULT_ADDRESS",
    "DEFAULT_MAX_FRAME_BYTES",
    "NEIGHBOUR_SLOTS",
    "OBSERVATION_FIELDS",
    "PROTOCOL_VERSION",
    "AccelerationLimit",
    "ActionSchema",
    "AppliedAction",
    "Bye",
    "Close",
    "Ego",
    "EndReason",
    "Endpoint",
    "Error",
    "ErrorCode",
    "Events",
    "FieldSpec",
    "Flattener",
    "Hello",
    "LaneChange",
    "LaneChangeRefusal",
    "LeaderTrip",
    "Message",
    "Neighbour",
    "Neighbours",
    "Observation",
    "ProtocolError",
    "Reply",
    "Request",
    "Reset",
    "ScenarioInfo",
    "Step",
    "Welcome",
    "decode_reply",
    "decode_request",
    "encode",
    "format_version",
    "is_compatible",
    "parse_endpoint",
]
