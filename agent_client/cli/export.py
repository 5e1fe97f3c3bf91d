"""``agent-client export-recording``: a recording's trajectories as a CSV table (pandas reads it).

One row per observation, the columns of docs/recording.md ("Export"). The recording is read
with the protocol's own checks; nothing is connected.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from agent_client.cli.common import Commands
from agent_client.errors import UsageError

DEFAULT_TABLE = "trajectories.csv"


def add_parser(commands: Commands) -> None:
    export = commands.add_parser(
        "export-recording",
        help="write a recording's trajectories as a CSV table, one row per observation",
        description="Read a folder written by `drive --record` or `evaluate --record` and write "
        "one row per observation (columns: docs/recording.md).",
    )
    export.add_argument("recording", type=Path, metavar="DIR", help="the recording folder")
    export.add_argument(
        "--out", type=Path, metavar="FILE.csv", help=f"the table (default DIR/{DEFAULT_TABLE})"
    )
    export.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from agent_client.evaluation.export import write_csv
    from protocol.recording import RecordingError, load

    out: Path = args.out if args.out is not None else args.recording / DEFAULT_TABLE
    if out.suffix.lower() != ".csv":
        raise UsageError(f"--out {out}: the table is written as CSV; name it FILE.csv")
    if not out.parent.is_dir():
        raise UsageError(f"--out {out}: no such folder {out.parent}")
    try:
        recording = load(args.recording)
    except RecordingError as exc:  # its message starts with the folder or file at fault
        raise UsageError(str(exc)) from exc
    count = write_csv(recording, out)
    print(f"{count} observations of {len(recording.episodes)} episodes: {out}")
    return 0
