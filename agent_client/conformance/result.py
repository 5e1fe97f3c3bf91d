"""The outcome of a conformance run: one `CheckResult` per check, and the verdict."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

PASS, FAIL, WARN, SKIP = "pass", "fail", "warn", "skip"
"""Outcomes of a check; only FAIL makes the kit exit 1 (a warning is reported, not failed)."""


@dataclass(frozen=True)
class CheckResult:
    """Outcome of one check: its name, PASS/FAIL/WARN/SKIP and a one-line detail."""

    name: str
    status: str
    detail: str


@dataclass
class ConformanceReport:
    """All check results for one server."""

    server: str
    scenario: str | None
    results: list[CheckResult] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no check failed (warnings and skips do not fail)."""
        return all(result.status != FAIL for result in self.results)

    @property
    def exit_code(self) -> int:
        return 0 if self.ok else 1

    def to_dict(self) -> dict[str, Any]:
        return {
            "server": self.server,
            "scenario": self.scenario,
            "ok": self.ok,
            "checks": [asdict(result) for result in self.results],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    def format_table(self) -> str:
        """A human-readable pass/fail table with a summary line."""
        width = max([len("check"), *(len(r.name) for r in self.results)])
        lines = [f"{'check':<{width}}  result  detail"]
        for result in self.results:
            lines.append(f"{result.name:<{width}}  {result.status:<6}  {result.detail}")
        counts = {s: sum(r.status == s for r in self.results) for s in (PASS, WARN, FAIL, SKIP)}
        verdict = "CONFORMS" if self.ok else "DOES NOT CONFORM"
        lines.append(
            f"{self.server} ({self.scenario or 'no scenario'}): {verdict} - "
            f"{counts[PASS]} passed, {counts[WARN]} warnings, {counts[FAIL]} failed, "
            f"{counts[SKIP]} skipped"
        )
        return "\n".join(lines)
