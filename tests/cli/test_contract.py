"""The command line contract: help everywhere, exit codes, one-line errors, nothing half-written.

Modules it covers (the mirrored test file aside): magcal_cli.cli.fit, magcal_cli.cli.main,
magcal_cli.methods.table.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from magcal_cli import __version__
from magcal_cli.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_logs" / "handheld.mcap"



def test_every_command_and_option_has_help(runner: CliRunner) -> None:
    """`magcal X --help` works for every command and no option lacks a help text."""
    assert cli.help
    for name, cmd in cli.commands.items():
        result = runner.invoke(cli, [name, "--help"])
        assert result.exit_code == 0, name
        assert cmd.help, name
        assert "Exit codes" in result.output, name
        for param in cmd.params:
            if isinstance(param, click.Option):
                assert param.help, f"{name} {param.opts}"


def test_version(runner: CliRunner) -> None:
    result = runner.invoke(cli, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"magcal {__version__}"


def test_fit_writes_the_outputs_and_prints_the_document(runner: CliRunner, tmp_path: Path) -> None:
    """fit --json: the document on stdout (parseable), the four files in the output directory."""
    out = tmp_path / "out"
    result = runner.invoke(cli, ["fit", str(SAMPLE), "-o", str(out), "--json", "-q"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["schema"] == "magcal.calibration/1"
    assert doc["magnetometers"][0]["id"] == "/imu/mag" and doc["magnetometers"][0]["units"] == "tesla"
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "calibration.yaml", "report.html",
                                                     "report.txt"]
    assert json.loads((out / "calibration.json").read_text()) == doc
    assert result.stderr == ""                                   # -q: nothing on stderr


def test_fit_recovers_the_sample_truth(runner: CliRunner, tmp_path: Path) -> None:
    """The shipped sample log calibrates to its truth file (D within 5 %, hard iron within 0.5 % of |F|)."""
    import numpy as np

    from magcal_cli.calibration.document import load

    out = tmp_path / "o"
    assert runner.invoke(cli, ["fit", str(SAMPLE), "-o", str(out), "-q", "--outputs", "json"]).exit_code == 0
    est = load(out / "calibration.json").magnetometers[0]
    truth = load(SAMPLE.with_name(SAMPLE.name + ".truth.json")).magnetometers[0]
    assert np.linalg.norm(est.D - truth.D) / np.linalg.norm(truth.D) < 0.05
    assert np.linalg.norm(est.o - truth.o) / truth.field_strength < 0.005


def test_truncated_log_is_one_error_line_and_nothing_written(runner: CliRunner, tmp_path: Path) -> None:
    """A cut-off copy with --strict: exit 1, a single 'Error:' line that says what and how to fix, no output."""
    cut = tmp_path / "cut.mcap"
    data = SAMPLE.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    result = runner.invoke(cli, ["fit", str(cut), "-o", str(out), "--strict"])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert lines[-1].startswith("Error: ") and "the log is cut" in lines[-1] and "--strict" in lines[-1]
    assert "Traceback" not in result.output
    assert not out.exists()


def test_cut_log_uses_the_complete_part(runner: CliRunner, tmp_path: Path) -> None:
    """By default a cut log calibrates from its complete records and says so in the report (issue 12)."""
    cut = tmp_path / "cut.mcap"
    data = SAMPLE.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.8)])
    out = tmp_path / "out"
    result = runner.invoke(cli, ["fit", str(cut), "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    assert "the log is cut" in (out / "report.txt").read_text()


def test_outputs_are_not_overwritten_without_force(runner: CliRunner, tmp_path: Path) -> None:
    """A second run into the same directory refuses (a usage error, exit 2) until --force is given."""
    out = tmp_path / "out"
    args = ["fit", str(SAMPLE), "-o", str(out), "-q", "--outputs", "json"]
    assert runner.invoke(cli, args).exit_code == 0
    before = (out / "calibration.json").read_bytes()
    again = runner.invoke(cli, args)
    assert again.exit_code == 2
    assert again.stderr.strip().splitlines()[-1] == f"Error: {out / 'calibration.json'}: exists already. Pass " \
                                                    "--force to overwrite it, or choose another -o"
    assert (out / "calibration.json").read_bytes() == before
    assert runner.invoke(cli, [*args, "--force"]).exit_code == 0


def test_unrecognised_file_and_usage_errors(runner: CliRunner, tmp_path: Path) -> None:
    """Random bytes: exit 1 naming the problem; a missing file or bad option: click's usage error, exit 2."""
    junk = tmp_path / "junk.dat"
    junk.write_bytes(b"\x00\x01garbage" * 100)
    result = runner.invoke(cli, ["fit", str(junk), "-o", str(tmp_path / "o")])
    assert result.exit_code == 1
    assert "unrecognised log format" in result.stderr and "--format" in result.stderr
    assert runner.invoke(cli, ["fit", str(tmp_path / "missing.mcap")]).exit_code == 2
    assert runner.invoke(cli, ["fit", str(SAMPLE), "--outputs", "bogus"]).exit_code == 2


def test_a_bug_is_exit_123_without_traceback(runner: CliRunner, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """An unexpected exception is reported as an internal error (exit 123); -v adds the traceback."""
    import magcal_cli.pipeline as pipeline

    def boom(*args: object, **kwargs: object) -> None:
        raise RuntimeError("kaboom")

    monkeypatch.setattr(pipeline, "calibrate", boom)
    result = runner.invoke(cli, ["fit", str(SAMPLE), "-o", str(tmp_path / "o")])
    assert result.exit_code == 123
    assert "internal error (RuntimeError: kaboom)" in result.stderr and "Traceback" not in result.stderr
    verbose = runner.invoke(cli, ["fit", str(SAMPLE), "-o", str(tmp_path / "o"), "-v"])
    assert verbose.exit_code == 123 and "Traceback" in verbose.stderr


def test_simulate_writes_log_and_truth(runner: CliRunner, tmp_path: Path) -> None:
    """simulate OUT.mcap writes the log and OUT.mcap.truth.json; a second run refuses without --force."""
    out = tmp_path / "sim.mcap"
    args = ["simulate", str(out), "--seed", "3", "--duration", "40", "-q"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    truth = json.loads((tmp_path / "sim.mcap.truth.json").read_text())
    assert truth["method"] == "truth" and truth["simulation"]["seed"] == 3
    assert runner.invoke(cli, args).exit_code == 2
