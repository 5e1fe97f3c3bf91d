from __future__ import annotations

import pytest

from protocol.transport.endpoint import parse_endpoint
from protocol.version import is_compatible


@pytest.mark.parametrize(
    ("address", "loopback"),
    [
        ("tcp://127.0.0.1:5555", True),
        ("tcp://localhost:0", True),
        ("tcp://[::1]:5555", True),
        ("ipc:///tmp/x.sock", True),
        ("tcp://0.0.0.0:5555", False),
        ("tcp://10.1.2.3:5555", False),
    ],
)
def test_loopback_detection(address: str, loopback: bool) -> None:
    assert parse_endpoint(address).is_loopback is loopback


@pytest.mark.parametrize(
    "address", ["127.0.0.1:5555", "tcp://127.0.0.1", "tcp://h:99999", "ipc://"]
)
def test_malformed_addresses_are_refused(address: str) -> None:
    with pytest.raises(ValueError, match=r"expected|needs"):
        parse_endpoint(address)


def test_endpoint_round_trips_to_text() -> None:
    assert str(parse_endpoint("tcp://127.0.0.1:5555")) == "tcp://127.0.0.1:5555"
    assert str(parse_endpoint("tcp://[::1]:7")) == "tcp://[::1]:7"


def test_major_version_decides_compatibility() -> None:
    assert is_compatible((1, 0), (1, 7))
    assert not is_compatible((1, 0), (2, 0))
