"""Issue 30 items 1 and 3: the same option means the same thing on every command, usage mistakes exit 2, a closed
pipe exits 1 and '-' means standard output wherever a file is written. Each test failed on the code before it,
but test_a_forced_format_that_fits_still_reads, which guards what worked.

Modules it covers (the mirrored test file aside): magcal_cli.cli.apply, magcal_cli.cli.batch, magcal_cli.cli.check,
magcal_cli.cli.diagnose, magcal_cli.cli.export, magcal_cli.cli.guards, magcal_cli.cli.simulate, magcal_cli.readers,
magcal_cli.writers.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from magcal_cli.cli.main import cli
from magcal_cli.config import Config
from magcal_cli.errors import MagcalError

from .test_export import write_doc

ROOT = Path(__file__).resolve().parents[2]
BIN = ROOT / "sample_logs" / "handheld.bin"
CSV = ROOT / "sample_logs" / "handheld.csv"
#: a quick fit: the base model, one output
QUICK = ("--effects", "none", "--outputs", "json", "-q")


def run(*args: object) -> Result:
    """`magcal ARGS` in-process (stdout and stderr apart)."""
    return CliRunner().invoke(cli, [str(a) for a in args])


def last_error(result: Result) -> str:
    """The `Error: ...` line (click's usage errors print the usage above it)."""
    return result.stderr.strip().splitlines()[-1]


class StopError(MagcalError):
    """Ends a command at the fit, once its Config is seen."""


@pytest.fixture
def configs(monkeypatch: pytest.MonkeyPatch) -> list[Config]:
    """The Configs commands hand the pipeline (the fit itself is skipped: the command exits 1 there)."""
    import magcal_cli.pipeline

    seen: list[Config] = []

    def calibrate(path: Path, cfg: Config, *args: object, **kwargs: object) -> None:
        seen.append(cfg)
        raise StopError("stop")

    monkeypatch.setattr(magcal_cli.pipeline, "calibrate", calibrate)
    return seen


# --- -o, '-' and the shared names --------------------------------------------------------------------------------

def test_simulate_takes_o_and_effects(tmp_path: Path) -> None:
    """simulate -o LOG and --effects (repeatable, comma-separated, ID[:key=value,...]) as in the other commands."""
    out = tmp_path / "s.bin"
    result = run("simulate", "-o", out, "--scenario", "paper", "--duration", "12", "-q",
                 "--effects", "current_interference,time_offset:tau_s=0.01", "--effects", "gyro_scale")
    assert result.exit_code == 0, result.output
    assert result.stdout == f"wrote {out}\nwrote {out}.truth.json\n"
    truth = json.loads((tmp_path / "s.bin.truth.json").read_text())
    assert {e["id"]: e["params"] for e in truth["effects"]}["time_offset"] == {"tau_s": 0.01}
    assert sorted(e["id"] for e in truth["effects"]) == ["current_interference", "gyro_scale", "time_offset"]


def test_simulate_log_is_given_once_and_never_to_stdout(tmp_path: Path) -> None:
    result = run("simulate", "-o", "-")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: Invalid value for '-o' / '--output': simulate writes a log whose format "
                                  "follows its extension (and a truth file next to it), so it cannot go to standard "
                                  "output; give a file name, e.g. -o sim.bin")
    result = run("simulate")
    assert (result.exit_code, last_error(result)) == (2, "Error: give the log to write with -o LOG, e.g. magcal "
                                                         "simulate -o sim.bin")
    result = run("simulate", tmp_path / "a.bin", "-o", tmp_path / "b.bin")
    assert result.exit_code == 2 and not list(tmp_path.iterdir())


def test_export_dash_is_stdout(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`export --px4 -` printed a file named '-'; now '-' is standard output with --px4, --ardupilot and -o, and
    the remarks that were results go to stderr."""
    monkeypatch.chdir(tmp_path)
    doc = write_doc(tmp_path / "cal.json")                       # a DataFlash log's calibration
    result = run("export", doc, "--px4", "-")
    assert result.exit_code == 0, result.output
    assert "CAL_MAG0_XOFF" in result.stdout and "wrote" not in result.stdout
    assert "CAL_MAG0_*: exported exactly" in result.stderr
    assert not (tmp_path / "-").exists()
    result = run("export", doc, "-o", "-")                       # the vehicle's firmware: ArduPilot
    assert result.exit_code == 0 and "COMPASS_OFS_X,-100" in result.stdout and not (tmp_path / "-").exists()
    result = run("export", doc, "-o", tmp_path / "v.param", "-q")
    assert result.exit_code == 0 and result.stdout.endswith(f"wrote {tmp_path / 'v.param'}\n")
    assert "COMPASS_OFS_X,-100" in (tmp_path / "v.param").read_text()
    result = run("export", doc, "--px4", "-", "--ardupilot", "-")
    assert (result.exit_code, last_error(result)) == (2, "Error: only one of --ardupilot and --px4 can write to "
                                                         "standard output ('-')")


def test_export_o_needs_a_flight_controller_log(tmp_path: Path) -> None:
    """-o writes the firmware of the log the calibration came from; a ROS/CSV calibration has none."""
    doc = tmp_path / "ros.json"
    doc.write_text(write_doc(tmp_path / "c.json").read_text().replace('"format": "dataflash"', '"format": "mcap"'))
    result = run("export", doc, "-o", tmp_path / "x.param")
    assert result.exit_code == 2
    assert last_error(result) == (f"Error: {doc}: its log (mcap) was not written by a flight controller, so -o does "
                                  "not know which firmware's parameters to write; give --ardupilot FILE or --px4 FILE "
                                  "instead")


def test_outputs_html_writes_report_html(tmp_path: Path) -> None:
    """--outputs html writes report.html (it was rejected; plots, its old name, still works)."""
    result = run("fit", BIN, "-o", tmp_path / "o", "--effects", "none", "--outputs", "json,html", "-q")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["calibration.json", "report.html"]


def test_fit_effects_is_repeatable(tmp_path: Path) -> None:
    """--effects a --effects b is --effects a,b, as --mag is."""
    result = run("fit", BIN, "-o", tmp_path / "o", "--effects", "time_offset", "--effects", "gyro_scale",
                 "--outputs", "json", "--json", "-q")
    assert result.exit_code == 0, result.output
    assert sorted(e["id"] for e in json.loads(result.stdout)["effects"]) == ["gyro_scale", "time_offset"]


# --- --format -------------------------------------------------------------------------------------------------------

def test_format_takes_the_names_inspect_prints(realdata: Path) -> None:
    """--format px4log was refused although inspect prints px4log."""
    result = run("inspect", realdata / "px4" / "01_07_59.px4log", "--format", "px4log", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["format"] == "px4log"


@pytest.mark.parametrize(("fmt", "log", "message"), [
    ("mcap", BIN, "{log}: not an MCAP file: its first bytes are those of an ArduPilot DataFlash log. Leave --format "
                  "out, or give --format dataflash"),
    ("px4log", BIN, "{log}: not a PX4 sdlog2 log (.px4log): it is an ArduPilot DataFlash log. Leave --format out, or "
                    "give --format dataflash"),
    ("ulog", CSV, "{log}: not a PX4 ULog: it does not start with the magic bytes of one; by its extension it looks "
                  "like a CSV log. Leave --format out, or give --format csv"),
])
def test_a_forced_format_the_log_is_not_is_an_error(fmt: str, log: Path, message: str) -> None:
    """`inspect --format mcap log.bin` listed 0 streams and exited 0: now exit 1 saying what the file is."""
    for command in (["inspect", log], ["fit", log, "-o", "/nonexistent/never"]):
        result = run(*command, "--format", fmt)
        assert result.exit_code == 1, (command, result.output)
        assert result.stderr.splitlines()[-1] == "Error: " + message.format(log=log)


def test_a_forced_format_that_fits_still_reads(tmp_path: Path) -> None:
    for fmt, log in (("csv", CSV), ("dataflash", BIN)):
        result = run("inspect", log, "--format", fmt, "--json")
        assert result.exit_code == 0, result.output
        assert json.loads(result.stdout)["format"] == fmt and json.loads(result.stdout)["streams"]


# --- --mag, --start/--end wherever they apply ------------------------------------------------------------------------

def test_diagnose_takes_mag_and_a_window(configs: list[Config]) -> None:
    result = run("diagnose", BIN, "--mag", "MAG[0]", "--start", "5", "--end", "60")
    assert result.exit_code == 1 and result.stderr == "Error: stop\n"
    assert (configs[0].mag, configs[0].start_s, configs[0].end_s) == ("MAG[0]", 5.0, 60.0)


def test_check_refits_the_same_window(configs: list[Config]) -> None:
    """check --start/--end: the new calibration is fitted on the window (and the flight judged on it, below)."""
    result = run("check", BIN, "--start", "5", "--end", "60", "--json", "-q")
    assert (configs[0].start_s, configs[0].end_s) == (5.0, 60.0)
    assert json.loads(result.stdout)["compasses"][0]["not_measured"]["heading_change_deg"] == (
        "the new calibration failed: stop")


def test_check_judges_the_window() -> None:
    whole = json.loads(run("check", BIN, "--no-refit", "--json", "-q").stdout)["compasses"][0]
    part = json.loads(run("check", BIN, "--no-refit", "--json", "-q", "--start", "10", "--end", "60").stdout)
    assert 0 < part["compasses"][0]["samples"] < whole["samples"] * 0.6


def test_apply_writes_the_window(tmp_path: Path) -> None:
    cal = tmp_path / "o" / "calibration.json"
    assert run("fit", BIN, "-o", tmp_path / "o", *QUICK).exit_code == 0
    result = run("apply", cal, BIN, "-o", "-", "--start", "10", "--end", "10.2")
    assert result.exit_code == 0, result.output
    times = [float(line.split(",")[0]) for line in result.stdout.splitlines()[1:]]
    assert times and min(times) >= 10 and max(times) <= 10.2


def test_batch_fits_the_window(tmp_path: Path) -> None:
    result = run("batch", BIN, "-o", tmp_path / "b", "--start", "5", "--end", "60", "-j", "1", *QUICK)
    assert result.exit_code == 0, result.output
    source = json.loads((tmp_path / "b" / "handheld" / "calibration.json").read_text())["source"]
    assert 5 <= source["start_s"] < source["end_s"] <= 60


# --- exit codes ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["fit", "diagnose", "batch"])
def test_a_file_where_a_folder_belongs_is_exit_2(tmp_path: Path, command: str) -> None:
    (tmp_path / "file").write_text("keep")
    result = run(command, BIN, "-o", tmp_path / "file")
    assert result.exit_code == 2
    assert last_error(result) == (f"Error: Invalid value for '-o' / '--outdir': {tmp_path / 'file'}: exists and is "
                                  "not a folder; this command writes a folder of outputs. Choose another -o")
    assert (tmp_path / "file").read_text() == "keep"


@pytest.mark.parametrize(("args", "message"), [
    (["fit", BIN, "--mag", "MAG[5]"], "handheld.bin: no magnetometer stream 'MAG[5]'; available: MAG[0]. Use --mag "
                                      "with one of them."),
    (["diagnose", BIN, "--mag", "MAG[5]"], "handheld.bin: no magnetometer stream 'MAG[5]'; available: MAG[0]. Use "
                                           "--mag with one of them."),
    (["check", BIN, "--mag", "MAG[5]", "--no-refit"], "handheld.bin: no magnetometer stream 'MAG[5]'; available: "
                                                      "MAG[0]. Use --mag with one of them."),
    (["fit", BIN, "--imu", "IMU[3]"], "handheld.bin: no accelerometer stream 'IMU[3]'; available: IMU[0]. Use --imu "
                                      "with one of them."),
    (["fit", BIN, "--method", "kok2012", "--effects", "time_offset"],
     "--effects time_offset cannot be modelled by --method kok2012; the joint MAP method models every effect (the "
     "EKFs current_interference and temperature_drift, ekf-ml also throttle_interference): use --method map, or "
     "--effects none"),
    (["simulate", "-o", "{tmp}/x.bin", "--seed", "-1"], "Invalid value for '--seed': -1 is not in the range x>=0."),
    (["simulate", "-o", "{tmp}/x.bin", "--scenario", "rover", "--duration", "10"],
     "Invalid value for '--duration': the rover scenario needs --duration >= 60 s (its still, start and stop phases "
     "alone take most of that), got 10"),
    (["simulate", "-o", "{tmp}/x.bin", "--rate", "-3"], "Invalid value for '--rate': expected a finite number > 0, "
                                                        "got -3"),
])
def test_usage_mistakes_are_exit_2(tmp_path: Path, args: list[object], message: str) -> None:
    """A stream id the log does not have, options that contradict each other, values out of range: exit 2 (they
    were 1, or 123 for --seed -1), nothing written."""
    out = tmp_path / "out"
    result = run(*[str(a).format(tmp=out) for a in args], *(["-o", out] if args[0] in ("fit", "diagnose") else []))
    assert result.exit_code == 2, result.output
    assert last_error(result) == f"Error: {message}"
    assert not out.exists()


def test_export_mag_and_slot_mistakes_are_exit_2(tmp_path: Path) -> None:
    doc = write_doc(tmp_path / "cal.json")
    result = run("export", doc, "-o", tmp_path / "a.param", "--mag", "MAG[3]")
    assert (result.exit_code, last_error(result)) == (2, f"Error: Invalid value for '--mag': MAG[3]: not in the "
                                                         f"calibration {doc}, which has MAG[0]; give --mag with some "
                                                         "of them")
    result = run("export", doc, "--ardupilot", tmp_path / "a.param", "--slot", "0")
    assert (result.exit_code, last_error(result)) == (2, "Error: Invalid value for '--slot': ardupilot has no slot 0; "
                                                         "give --slot 1 to 3 (or leave it out: the device ids decide)")
    assert not (tmp_path / "a.param").exists()


def pipeline_exit(command: str, cwd: Path) -> tuple[int, str]:
    """`magcal ...` in a shell pipeline: (magcal's exit code, its stderr)."""
    shell = f"{sys.executable} -m magcal_cli {command} 2>err.txt; exit ${{PIPESTATUS[0]}}"
    code = subprocess.run(["bash", "-c", shell], cwd=cwd, check=False).returncode
    return code, (cwd / "err.txt").read_text()


def test_a_reader_that_stops_early_is_exit_1(tmp_path: Path) -> None:
    """`magcal fit LOG --json | head -c 10` and `magcal inspect LOG | head -c 10` exited 0 (the output fitted in the
    pipe, so no write failed): now 1, quietly, as the help promises; a reader that takes everything: 0."""
    fit = f"fit {BIN} --json -o out {' '.join(QUICK)}"
    assert pipeline_exit(f"{fit} | head -c 10 >/dev/null", tmp_path) == (1, "")
    assert (tmp_path / "out" / "calibration.json").is_file()           # the files were written all the same
    assert pipeline_exit(f"inspect {BIN} | head -c 10 >/dev/null", tmp_path) == (1, "")
    assert pipeline_exit(f"inspect {BIN} | cat >/dev/null", tmp_path) == (0, "")
