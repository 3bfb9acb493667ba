"""Every command's help page renders (argparse expands ``%`` in help strings)."""

from __future__ import annotations

import contextlib
import io

import pytest

from biopsynav.cli import build_parser, main


def _commands() -> list[str]:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sorted(sub.choices)


def _help_of(argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 0
    return out.getvalue()


def test_the_top_level_help_lists_every_command():
    text = _help_of(["--help"])
    for name in _commands():
        assert name in text
    assert "95 % bound" in text


@pytest.mark.parametrize("command", _commands())
def test_each_command_has_a_help_page(command):
    text = _help_of([command, "--help"])
    assert text.startswith("usage: biopsynav " + command)


def test_version_names_the_installed_package():
    from importlib.metadata import version

    assert _help_of(["--version"]).strip() == f"biopsynav {version('biopsynav')}"
