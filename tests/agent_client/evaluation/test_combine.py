"""Several evaluations in one report: headings one level down, figures still found."""

from __future__ import annotations

from pathlib import Path

from agent_client.evaluation.report import combine_reports


def test_reports_are_combined_in_order_with_their_figures(tmp_path: Path) -> None:
    for name in ("cf", "cflc"):
        part = tmp_path / "eval" / name
        part.mkdir(parents=True)
        (part / "report.md").write_text(
            f"# Evaluation on `{name}`\n\n## Tables\n\n![Fig. 9](speed_distribution.png)\n"
        )
        (part / "speed_distribution.png").write_bytes(b"png")
    out = tmp_path / "main"
    path = combine_reports(out, [tmp_path / "eval" / "cf", tmp_path / "eval" / "cflc"], "Main job")
    text = path.read_text()
    assert text.startswith("# Main job\n")
    assert text.index("## Evaluation on `cf`") < text.index("## Evaluation on `cflc`")
    assert "### Tables" in text
    links = [line[line.index("(") + 1 : -1] for line in text.splitlines() if line.startswith("![")]
    assert links == ["../eval/cf/speed_distribution.png", "../eval/cflc/speed_distribution.png"]
    assert all((out / link).is_file() for link in links)
