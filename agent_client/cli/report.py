"""``agent-client report``: one report from several evaluations (e.g. `cf` and `cflc`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from agent_client.cli.common import Commands, existing_folder
from agent_client.errors import UsageError


def add_parser(commands: Commands) -> None:
    report = commands.add_parser(
        "report",
        help="combine the reports of several `evaluate` runs into one",
        description="Write OUT/report.md from the report.md of each evaluation folder, in order, "
        "with their figures linked where they are.",
    )
    report.add_argument("folders", nargs="+", type=Path, help="evaluation folders (evaluate --out)")
    report.add_argument("--out", type=Path, required=True, help="folder of the combined report")
    report.add_argument("--title", default="Evaluation", help="title of the combined report")
    report.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from agent_client.evaluation.report import combine_reports

    for folder in args.folders:
        if not (existing_folder(folder, "report") / "report.md").is_file():
            raise UsageError(f"report {folder}: no report.md (run agent-client evaluate --out)")
    path = combine_reports(args.out, args.folders, args.title)
    print(f"report: {path}")
    return 0
