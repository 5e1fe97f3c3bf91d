"""The policies the project ships: trained by the documented commands, each with a model card.

``pretrained:NAME`` as a driver spec (``agent-client drive --policy pretrained:roads``) drives
the policy ``NAME.pt`` of this folder; ``NAME.md`` is its model card (the command that trained
it, its seeds, its rows of the table, what it was not trained for) and ``NAME.json`` the
settings it was trained with (its scenarios, decision interval and scenario options), which
`drive` and `evaluate` take as defaults, as they take a run folder's ``config.json``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

PREFIX = "pretrained:"
FOLDER = Path(__file__).resolve().parent


def names() -> list[str]:
    """The shipped policies, by name."""
    return sorted(path.stem for path in FOLDER.glob("*.pt"))


def policy_file(name: str) -> Path | None:
    """The file of the shipped policy `name`, or None where there is none."""
    path = FOLDER / f"{name}.pt"
    return path if name and path.is_file() else None


def settings(name: str) -> dict[str, Any]:
    """The training settings of a shipped policy (``scenario``, ``decision_interval``,
    ``scenario_options``), as its ``NAME.json`` holds them; {} if it has none."""
    path = FOLDER / f"{name}.json"
    if not path.is_file():
        return {}
    loaded: dict[str, Any] = json.loads(path.read_text())
    return loaded
