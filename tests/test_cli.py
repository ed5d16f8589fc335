"""The CLI's error boundary prints user text literally: rich markup in paths and messages is not interpreted."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app, lit

runner = CliRunner()


@pytest.mark.parametrize("name", ["[/bad]", "[word]", "[bold red]x[/]"])
def test_markup_in_a_path_is_printed_literally(tmp_path, name):
    missing = tmp_path / name / "seq"
    res = runner.invoke(app, ["run", "--robot", f"car1={missing}", "--rerun", "off", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    assert name in res.output.replace("\n", "")


def test_lit_keeps_brackets():
    from rich.console import Console

    console = Console(record=True, width=200)
    console.print(lit("position must be three finite numbers, got [nan] [/x]"))
    assert "got [nan] [/x]" in console.export_text()
