"""Issue 30 item 1: one vocabulary. Every command's options are walked against the one table of shared options
(`cli.options.SHARED`): a shared name declared by hand or differently, a `-o` that is not the output, an option two
commands declare outside the table, or a hidden option that is no listed alias is a drift, and fails here.
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from magcal_cli.cli.main import cli
from magcal_cli.cli.options import ALIASES, SHARED, SharedOption

ROOT = Path(__file__).resolve().parents[2]
#: the spellings of `-o`: every one is the command's output
OUTPUT_KEYS = ("outdir", "output", "log-output")


def names(param: click.Option) -> list[str]:
    """Every spelling of an option (--external/--internal has two)."""
    return [*param.opts, *param.secondary_opts]


def metavar(param: click.Option, ctx: click.Context) -> str | None:
    """The value as --help shows it; None for a flag."""
    return None if param.is_flag else param.make_metavar(ctx)


def type_info(value: object) -> dict[str, object]:
    """A click type as comparable data (click's own description of it)."""
    return click.types.convert_type(value).to_info_dict()


def drifts(group: click.Group) -> list[str]:
    """Every way `group`'s commands depart from the shared table, one line each (empty: none)."""
    found: list[str] = []
    by_name = defaultdict(list)
    for key, entry in SHARED.items():
        for n in entry.names:
            by_name[n].append(key)
    users: dict[str, set[str]] = defaultdict(set)
    for cmd_name, cmd in group.commands.items():
        ctx = click.Context(cmd, info_name=cmd_name)
        declared = {p.shared for p in cmd.params if isinstance(p, SharedOption)}
        for key, entry in SHARED.items():
            if (cmd_name in entry.commands) != (key in declared):
                found.append(f"{cmd_name}: {'lacks' if key not in declared else 'is not listed for'} the shared "
                             f"option {key} ({'/'.join(entry.names)})")
        for p in cmd.params:
            if not isinstance(p, click.Option):
                continue
            spelled = names(p)
            if p.hidden:
                if not any(n in ALIASES and cmd_name in ALIASES[n].commands for n in spelled):
                    found.append(f"{cmd_name}: hidden option {'/'.join(spelled)} is not an alias listed in ALIASES")
                continue
            for n in spelled:
                users[n].add(cmd_name)
            keys = {k for n in spelled for k in by_name.get(n, [])}
            if "-o" in spelled and not (isinstance(p, SharedOption) and p.shared in OUTPUT_KEYS):
                found.append(f"{cmd_name}: -o is {'/'.join(spelled)} ({p.name}), not the command's output")
                continue
            if not keys:
                continue
            if not isinstance(p, SharedOption) or p.shared not in keys:
                found.append(f"{cmd_name}: {'/'.join(spelled)} is declared by hand, not from the table "
                             f"({' or '.join(sorted(keys))})")
                continue
            entry = SHARED[p.shared]
            want_type = entry.settings.get("type", bool if entry.metavar is None else str)
            checks = {"names": (tuple(p.opts), entry.names), "dest": (p.name, entry.dest),
                      "metavar": (metavar(p, ctx), entry.metavar), "multiple": (p.multiple, entry.multiple),
                      "type": (type_info(p.type), type_info(want_type))}
            found += [f"{cmd_name}: {'/'.join(spelled)} has {what} {got!r}, the table says {want!r}"
                      for what, (got, want) in checks.items() if got != want]
    shared_names = set(by_name)
    found += [f"{'/'.join(sorted(cmds))} all declare {n}, which is not in the shared table"
              for n, cmds in sorted(users.items()) if len(cmds) > 1 and n not in shared_names and n not in
              ("-h", "--help")]
    return found


def test_every_command_speaks_the_table() -> None:
    """The must-show test of issue 30: magcal's commands against SHARED, no drift."""
    assert drifts(cli) == []


def test_a_drift_is_found() -> None:
    """The walk catches a --mag declared by hand, a -o that is not the output, a shared option missing where the
    table says it applies, and a hidden option that is no alias."""
    group = click.Group("magcal")

    @group.command("fit")
    @click.option("--mag", "mags", multiple=True, help="Magnetometers.")
    @click.option("-o", "--outfile", help="Not the output folder.")
    @click.option("--sneaky", hidden=True, help="Hidden.")
    def fit(mags: tuple[str, ...], outfile: str | None, sneaky: str | None) -> None:
        """A command that drifted."""

    found = drifts(group)
    assert "fit: --mag is declared by hand, not from the table (mag)" in found
    assert "fit: -o is -o/--outfile (outfile), not the command's output" in found
    assert "fit: lacks the shared option format (--format)" in found
    assert "fit: hidden option --sneaky is not an alias listed in ALIASES" in found


def test_the_table_names_real_commands_and_meanings() -> None:
    """Each shared entry says what it means, and only names commands magcal has; -o is always an output."""
    for key, entry in SHARED.items():
        assert entry.meaning and entry.kind, key
        assert set(entry.commands) <= set(cli.commands), key
        if "-o" in entry.names:
            assert key in OUTPUT_KEYS and entry.meaning.startswith("the output"), key
    assert {k for k, e in SHARED.items() if "-o" in e.names} == set(OUTPUT_KEYS)


def test_every_command_writing_a_file_takes_o() -> None:
    """-o on every command that writes (fit, diagnose, batch: a folder; apply, export: a file or '-'; simulate: the
    log), and --force with it."""
    for name, cmd in cli.commands.items():
        has_o = any("-o" in p.opts for p in cmd.params if isinstance(p, click.Option))
        has_force = any("--force" in p.opts for p in cmd.params if isinstance(p, click.Option))
        assert has_o == has_force == (name not in ("check", "inspect")), name


@pytest.mark.parametrize(("args", "note"), [
    (["simulate", "{tmp}/a.csv", "--duration", "12", "--scenario", "paper"],
     "magcal: the positional OUT is deprecated: write magcal simulate -o {tmp}/a.csv"),
    (["simulate", "-o", "{tmp}/b.csv", "--duration", "12", "--scenario", "paper", "--effect", "time_offset"],
     "magcal: --effect is deprecated: use --effects (the same ID[:key=value,...], repeatable)"),
    (["fit", str(ROOT / "sample_logs" / "handheld.bin"), "-o", "{tmp}/f", "--effects", "none", "--outputs", "json",
      "--allow-truncated"],
     "magcal: --allow-truncated is deprecated: use nothing: a cut log is read up to its last complete record by "
     "default (--strict refuses it)"),
    (["fit", str(ROOT / "sample_logs" / "handheld.bin"), "-o", "{tmp}/g", "--effects", "none", "--outputs",
      "json,plots"], "magcal: --outputs plots is deprecated: it is called html now (it writes report.html)"),
])
def test_old_spellings_work_with_one_note(tmp_path: Path, args: list[str], note: str) -> None:
    """Scripts keep working: the old spelling does what it did, and stderr says once what to write now."""
    result = CliRunner().invoke(cli, [a.format(tmp=tmp_path) for a in args])
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    assert lines.count(note.format(tmp=tmp_path)) == 1, lines
    assert result.stderr.count("deprecated") == 1
    (tmp_path / "q").mkdir()
    quiet = CliRunner().invoke(cli, [a.format(tmp=tmp_path / "q") for a in args] + ["-q"])
    assert (quiet.exit_code, quiet.stderr) == (0, "")                        # -q silences it, wherever it stands


def test_old_spellings_are_hidden_from_help() -> None:
    """--help shows today's names only."""
    for name, alias in ALIASES.items():
        for command in alias.commands:
            shown = CliRunner().invoke(cli, [command, "--help"]).stdout
            assert not re.search(rf"{name}\b(?!s)", shown), (command, name)
    sim = CliRunner().invoke(cli, ["simulate", "--help"]).stdout
    assert "Usage: magcal simulate [OPTIONS]\n" in sim.replace("cli simulate", "magcal simulate")
    fit = " ".join(CliRunner().invoke(cli, ["fit", "--help"]).stdout.split())
    assert "html (report.html with plots)" in fit and "plots" not in fit.replace("report.html with plots", "")


def test_docs_cli_states_the_table_and_the_aliases() -> None:
    """docs/cli.md, the contract as implemented, lists every shared option and every old spelling kept."""
    doc = (ROOT / "docs" / "cli.md").read_text()
    vocabulary = doc.split("## One vocabulary", 1)[1].split("\n## ", 1)[0]
    changes = doc.split("## Changes from the shared spec", 1)[1]
    for key, entry in SHARED.items():
        assert f"`{', '.join(entry.names)}`" in vocabulary or all(f"`{n}`" in vocabulary for n in entry.names), key
        plain = vocabulary.replace("`", "").replace("'", "")
        assert entry.meaning.replace("'", "") in plain or key in ("start", "end", "mag-timing", "imu-timing"), key
    for name in ALIASES:
        assert f"`{name}" in changes or f"--{name.lstrip('-')}" in changes, name
