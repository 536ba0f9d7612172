"""Write docs/cli-reference.md from the `--help` of magcal and every command: python docs/cli_reference.py"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from magcal_cli.cli.main import cli

OUT = Path(__file__).resolve().parent / "cli-reference.md"
#: a fixed width: the reference must not depend on the terminal it was generated in
WIDTH = 100


def help_text(cmd: click.Command, name: str, parent: click.Context | None = None) -> str:
    """`magcal [COMMAND] --help` as click prints it at WIDTH columns."""
    settings = {**cli.context_settings, **cmd.context_settings, "terminal_width": WIDTH, "max_content_width": WIDTH}
    ctx = click.Context(cmd, info_name=name, parent=parent, **settings)
    return cmd.get_help(ctx)


def render() -> str:
    """The whole reference: the group's help, then each command's in the order `magcal --help` lists them."""
    root = click.Context(cli, info_name="magcal", **{**cli.context_settings, "terminal_width": WIDTH,
                                                     "max_content_width": WIDTH})
    assert isinstance(cli, click.Group)
    names = cli.list_commands(root)
    parts = ["# magcal command-line reference", "",
             "Generated from `--help` by `python docs/cli_reference.py` (tests/test_docs.py fails when it is out of "
             "date). Conventions (stdout, stderr, exit codes) are in the README.", "",
             "Commands: " + ", ".join(f"[`{n}`](#magcal-{n})" for n in names) + ".", "",
             "## magcal", "", "```", help_text(cli, "magcal"), "```", ""]
    for n in names:
        cmd = cli.get_command(root, n)
        assert cmd is not None
        parts += [f"## magcal {n}", "", "```", help_text(cmd, n, root), "```", ""]
    return "\n".join(parts)


if __name__ == "__main__":
    OUT.write_text(render())
    sys.stdout.write(f"wrote {OUT}\n")
