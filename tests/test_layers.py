"""What each folder may touch: the layers inside each side, checked on every import.

A folder may import the folders listed for it (and its own modules); everything else is a
layering mistake, even where it would not make a cycle. The rules are docs/architecture.md's.
"""

from __future__ import annotations

import pytest

from tests.test_import_cycles import graph

BASE = {"agent_client.errors", "agent_client.defaults", "agent_client.constants"}
PROTOCOL = {
    "protocol",
    "protocol.messages",
    "protocol.errors",
    "protocol.codec",
    "protocol.schema",
    "protocol.version",
    "protocol.recording",
    "protocol.readiness",
    "protocol.transport",
}
MAY_IMPORT: dict[str, set[str]] = {
    "protocol.transport": {"protocol.errors"},
    "agent_client.transport": BASE | PROTOCOL,
    "agent_client.rl": BASE | {"protocol.messages"},
    "agent_client.envs": BASE | PROTOCOL | {"agent_client.transport", "agent_client.rl"},
    "agent_client.drivers": BASE | PROTOCOL | {"agent_client.envs", "agent_client.rl"},
    "agent_client.evaluation": BASE | PROTOCOL | {"agent_client.envs", "agent_client.drivers"},
    "agent_client.conformance": BASE | PROTOCOL | {"agent_client.transport"},
    "sim_server.backends": {
        "sim_server.errors",
        "protocol.messages",
        "protocol.errors",
        "protocol.recording",  # the replay backend reads recordings through protocol/ only
    },
    "sim_server.session": {"sim_server.backends", "sim_server.errors", *PROTOCOL},
    "sim_server.serve": {"sim_server.session", "sim_server.backends", *PROTOCOL},
}


def folder(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else module


def crossings() -> dict[str, set[str]]:
    found: dict[str, set[str]] = {}
    for source, targets in graph().items():
        for target in targets:
            if folder(source) != folder(target):
                found.setdefault(source, set()).add(folder(target))
    return found


@pytest.mark.parametrize("layer", sorted(MAY_IMPORT))
def test_a_folder_imports_only_the_layers_below_it(layer: str) -> None:
    allowed = MAY_IMPORT[layer]
    wrong = {
        source: sorted(targets - allowed)
        for source, targets in crossings().items()
        if folder(source) == layer and targets - allowed
    }
    assert not wrong, wrong
