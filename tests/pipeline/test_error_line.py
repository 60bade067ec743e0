"""An ``error:`` is one line however the message came: a library's text quoting a whole message definition (a
flipped lz4 ROS 1 bag did) is folded onto one line and cut."""

from __future__ import annotations

import typer
from typer.testing import CliRunner

from cli.app import handled
from pipeline.errors import ERROR_LINE_MAX, InputError, one_line


def test_one_line_folds_and_cuts() -> None:
    assert one_line("a\n  b\tc\r\n") == "a b c"
    long = one_line("x " * 2000)
    assert len(long) == ERROR_LINE_MAX and long.endswith("…") and "\n" not in long


def test_a_multi_line_message_is_one_error_line() -> None:
    app = typer.Typer()

    @app.command()
    @handled
    def fail() -> None:
        raise InputError("cannot decode (definition:\nstring data\nuint32 seq\n); copy it again")

    result = CliRunner().invoke(app, [])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert lines == ["error: cannot decode (definition: string data uint32 seq ); copy it again"]
