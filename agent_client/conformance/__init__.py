"""The protocol conformance kit: checks any bridge server over the wire (docs/conformance.md)."""

from agent_client.conformance.checks import (
    Checker,
    ScenarioNotOffered,
    ServerUnreachable,
    run_checks,
)
from agent_client.conformance.result import FAIL, PASS, SKIP, WARN, CheckResult, ConformanceReport

__all__ = [
    "FAIL",
    "PASS",
    "SKIP",
    "WARN",
    "CheckResult",
    "Checker",
    "ConformanceReport",
    "ScenarioNotOffered",
    "ServerUnreachable",
    "run_checks",
]
