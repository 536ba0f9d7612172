"""Issue 13 items 3-6: no user mistake exits 123, one meaning per --mag, documents that work from any directory,
and `check`'s "not measured". Each test pins the exact message and exit code (spec/cli.md).

Modules it covers (the mirrored test file aside): magcal_cli.atomic, magcal_cli.cli.common, magcal_cli.cli.options,
magcal_cli.cli.simulate, magcal_cli.errors.
"""

from __future__ import annotations

import errno
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from magcal_cli.calibration.document import dumps_json, load
from magcal_cli.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]


def run(*args: object) -> Result:
    """`magcal ARGS` in-process (stdout and stderr apart)."""
    return CliRunner().invoke(cli, [str(a) for a in args])


def last_error(result: Result) -> str:
    """The `Error: ...` line (click's usage errors print the usage above it)."""
    return result.stderr.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 20 s simulated ArduPilot log (s.bin), a CSV log (s.csv) and the .bin's calibration (out/calibration.json,
    fitted with --effects none), all in one folder; fit ran from inside it with relative paths."""
    folder = tmp_path_factory.mktemp("logs")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(folder)
        for name in ("s.bin", "s.csv"):
            assert run("simulate", name, "--duration", "20", "-q").exit_code == 0
        result = run("fit", "s.bin", "-o", "out", "--effects", "none", "--outputs", "json", "-q")
        assert result.exit_code == 0, result.output
    return folder


def never(*args: object, **kwargs: object) -> None:
    """Stands in for the long work that a refused command must not start."""
    raise AssertionError("the work started before the arguments were checked")


# --- item 3: exit codes and errors ---------------------------------------------------------------------------

def test_swapped_apply_arguments_are_a_usage_error(logs: Path, tmp_path: Path) -> None:
    """`apply LOG CAL.json` was a UnicodeDecodeError (exit 123)."""
    result = run("apply", logs / "s.bin", logs / "out" / "calibration.json", "-o", tmp_path / "f.csv")
    assert result.exit_code == 2
    assert last_error(result) == (f"Error: {logs / 's.bin'}: a dataflash log where CALIBRATION (a calibration .json "
                                  "or .yaml from magcal fit) belongs. The arguments look swapped; run: magcal apply "
                                  "CAL.json LOG -o OUT.csv")
    assert not (tmp_path / "f.csv").exists()


def test_a_log_given_as_calibration_elsewhere_and_binary_junk(logs: Path, tmp_path: Path) -> None:
    """export LOG, check --calibration LOG: usage errors; a binary file that is no log: one line, exit 1."""
    result = run("export", logs / "s.bin", "--ardupilot", tmp_path / "a.param")
    assert result.exit_code == 2
    assert last_error(result) == (f"Error: {logs / 's.bin'}: a dataflash log where CALIBRATION (a calibration .json "
                                  "or .yaml from magcal fit) belongs. Run: magcal export CAL.json -o OUT.param (or "
                                  "--ardupilot OUT.param, --px4 OUT.params); a log with the vehicle's parameters goes "
                                  "to --params")
    result = run("check", logs / "s.bin", "--calibration", logs / "s.bin", "--no-refit")
    assert result.exit_code == 2
    assert last_error(result).endswith("belongs. A log or parameter file the vehicle flew with goes to --params")
    junk = tmp_path / "junk.json"
    junk.write_bytes(b"\xa3\x00\xff" * 10)
    result = run("apply", junk, logs / "s.bin", "-o", tmp_path / "f.csv")
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {junk}: not a calibration document (binary data, not JSON or YAML). Give the "
                             "file magcal fit wrote\n")


def test_a_read_only_output_folder_is_refused_before_the_fit(logs: Path, tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only disk (errno 30, simulated: tests run as root) is one line naming the folder, exit 1, and the fit
    never starts."""
    import magcal_cli.pipeline

    def read_only(*args: object, **kwargs: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr("magcal_cli.atomic.tempfile.mkstemp", read_only)
    monkeypatch.setattr(magcal_cli.pipeline, "calibrate", never)
    out = tmp_path / "out"
    result = run("fit", logs / "s.bin", "-o", out, "--effects", "none", "--outputs", "json")
    assert result.exit_code == 1
    assert result.stderr == f"Error: {out}: cannot write here (Read-only file system). Choose another -o\n"


def test_an_output_under_a_regular_file_is_refused_before_the_fit(logs: Path, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    import magcal_cli.pipeline

    monkeypatch.setattr(magcal_cli.pipeline, "calibrate", never)
    (tmp_path / "file").write_text("")
    result = run("fit", logs / "s.bin", "-o", tmp_path / "file" / "out", "--outputs", "json")
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {tmp_path / 'file' / 'out'}: cannot create the output directory (Not a "
                             "directory). Choose another -o\n")
    result = run("apply", logs / "out" / "calibration.json", logs / "s.bin", "-o", tmp_path / "file" / "f.csv")
    assert result.exit_code == 1
    assert result.stderr == f"Error: {tmp_path / 'file'}: is a file, not a folder. Choose another -o\n"
    result = run("apply", logs / "out" / "calibration.json", logs / "s.bin", "-o", tmp_path / "nodir" / "f.csv")
    assert result.exit_code == 1
    assert result.stderr == f"Error: {tmp_path / 'nodir'}: no such folder. Create it, or choose another -o\n"


def test_a_full_disk_while_writing_is_one_line_and_leaves_nothing(logs: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """ENOSPC (errno 28) in the middle of writing: exit 1 naming the output, no partial or temporary file."""

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    out = tmp_path / "f.csv"
    result = run("apply", logs / "out" / "calibration.json", logs / "s.bin", "-o", out, "-q")
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {out}: cannot write here (No space left on device). Free some space or choose "
                             "another output location\n")
    assert list(tmp_path.iterdir()) == []


def test_permission_denied_anywhere_is_not_a_bug(logs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An OSError the file system raises (errno 13) in a writer: exit 1 with its file, not 123."""

    def denied(*args: object, **kwargs: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", "/mnt/ro/report.html")

    monkeypatch.setattr("magcal_cli.writers.write_outputs", denied)
    result = run("fit", logs / "s.bin", "-o", tmp_path / "o", "--effects", "none", "--outputs", "json", "-q")
    assert result.exit_code == 1
    assert result.stderr == ("Error: /mnt/ro/report.html: Permission denied. Check the path, its permissions and "
                             "free space\n")


def test_a_closed_pipe_exits_quietly(logs: Path, tmp_path: Path) -> None:
    """`magcal fit LOG --json | head -1` with the reader gone before the document is printed: exit 1 (Python's
    and click's convention), nothing on stderr; it was a BrokenPipeError reported as a bug (123)."""
    args = [sys.executable, "-m", "magcal_cli", "fit", str(logs / "s.bin"), "--json", "--effects", "none",
            "--outputs", "json", "-o", str(tmp_path / "o"), "-q"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()
    err = proc.stderr.read()
    assert (proc.wait(timeout=120), err) == (1, b"")
    assert (tmp_path / "o" / "calibration.json").is_file()


def test_existing_outputs_are_usage_errors_before_the_work(logs: Path, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """fit, apply, export, simulate: an output that exists without --force is exit 2, checked first."""
    import magcal_cli.pipeline

    monkeypatch.setattr(magcal_cli.pipeline, "calibrate", never)
    cal = logs / "out" / "calibration.json"
    result = run("fit", logs / "s.bin", "-o", logs / "out", "--outputs", "json")
    assert result.exit_code == 2
    assert last_error(result) == f"Error: {cal}: exists already. Pass --force to overwrite it, or choose another -o"
    (tmp_path / "f.csv").write_text("keep")
    result = run("apply", cal, logs / "s.bin", "-o", tmp_path / "f.csv")
    assert result.exit_code == 2
    assert last_error(result) == (f"Error: {tmp_path / 'f.csv'}: exists already. Pass --force to overwrite it, or "
                                  "choose another -o")
    assert (tmp_path / "f.csv").read_text() == "keep"
    result = run("export", cal, "--ardupilot", tmp_path / "f.csv")
    assert result.exit_code == 2
    assert last_error(result) == f"Error: {tmp_path / 'f.csv'}: exists already. Pass --force to overwrite it"
    result = run("simulate", logs / "s.bin")
    assert result.exit_code == 2
    assert last_error(result) == f"Error: {logs / 's.bin'}: exists already. Pass --force to overwrite it"


def test_unknown_format_and_extension_are_usage_errors(logs: Path, tmp_path: Path) -> None:
    result = run("fit", logs / "s.bin", "--format", "ulgg")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: Invalid value for '--format': 'ulgg' is not a log format; choose from "
                                  "broad, csv, dataflash, mcap, px4log, rosbag, rosbag2, ulog, or leave --format out")
    assert run("inspect", logs / "s.bin", "--format", "ulgg").exit_code == 2
    result = run("simulate", tmp_path / "x.foo")
    assert result.exit_code == 2 and "simulating" not in result.stderr          # refused before simulating
    assert last_error(result) == (f"Error: Invalid value for OUT: {tmp_path / 'x.foo'}: cannot write a log with "
                                  "extension '.foo'; use one of (none: a ROS 2 bag directory), .bag, .bin, .csv, "
                                  ".mcap, .ulg")


def test_ranges_are_in_the_message(logs: Path) -> None:
    """--location and --start/--end: exit 2 naming the value and the range (or both options)."""
    result = run("fit", logs / "s.bin", "--location", "95,10")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: Invalid value for '--location': '95,10': latitude 95 is out of range "
                                  "[-90, 90]; expected LAT,LON[,ALT] in degrees and metres, e.g. 52.52,13.40,35")
    result = run("fit", logs / "s.bin", "--location", "45,-200")
    assert result.exit_code == 2 and "longitude -200 is out of range [-180, 180]" in last_error(result)
    result = run("fit", logs / "s.bin", "--start", "50", "--end", "10")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: --start 50 is not before --end 10; give --start S --end E with S < E "
                                  "(seconds from the log start)")
    result = run("fit", logs / "s.bin", "--start", "nan")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: Invalid value for '--start': nan: expected a finite number of "
                                  "seconds from the log start")


def test_help_documents_every_exit_code() -> None:
    for name in ("fit", "check", "apply"):
        out = " ".join(run(name, "--help").stdout.split())
        assert "123 internal error (a bug); 130 interrupted (Ctrl-C), nothing half-written left." in out


# --- item 4: one meaning per --mag ---------------------------------------------------------------------------

def two_mag_document(logs: Path, tmp_path: Path) -> Path:
    """The .bin's calibration with a second magnetometer MAG[1] (a copy; the log has only MAG[0])."""
    cal = load(logs / "out" / "calibration.json")
    doc = tmp_path / "two.json"
    doc.write_text(dumps_json(replace(cal, magnetometers=(*cal.magnetometers,
                                                          replace(cal.magnetometers[0], id="MAG[1]")))))
    return doc


@pytest.mark.parametrize("mags", [["--mag", "MAG[0]", "--mag", "MAG[1]"], ["--mag", "MAG[0],MAG[1]"],
                                  ["--mag", "MAG[0], MAG[1]", "--mag", "MAG[0]"]])
def test_fit_keeps_every_mag(logs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mags: list[str]) -> None:
    """Repeated and comma-listed --mag mean the same; `fit --mag A --mag B` used to keep only B."""
    import magcal_cli.pipeline
    from magcal_cli.errors import MagcalError

    def seen(path: Path, cfg: object, *args: object) -> None:
        raise MagcalError(f"cfg.mag={cfg.mag}")  # type: ignore[attr-defined]

    monkeypatch.setattr(magcal_cli.pipeline, "calibrate", seen)
    result = run("fit", logs / "s.bin", "-o", tmp_path / "o", "--outputs", "json", *mags)
    assert (result.exit_code, result.stderr) == (1, "Error: cfg.mag=MAG[0],MAG[1]\n")


def test_apply_takes_a_comma_list(logs: Path, tmp_path: Path) -> None:
    """`apply --mag A,B` failed as one id 'A,B'; now each is applied (MAG[1], not in the log, is skipped)."""
    doc = two_mag_document(logs, tmp_path)
    for i, mags in enumerate((["--mag", "MAG[0],MAG[1]"], ["--mag", "MAG[0]", "--mag", "MAG[1]"])):
        out = tmp_path / f"f{i}.csv"
        result = run("apply", doc, logs / "s.bin", "-o", out, *mags)
        assert result.exit_code == 0, result.output
        assert result.stderr == "magcal: MAG[1]: not in the log, skipped\n"
    assert (tmp_path / "f0.csv").read_text() == (tmp_path / "f1.csv").read_text()


def test_mag_usage_errors(logs: Path, tmp_path: Path) -> None:
    """An empty id, 'all' with ids, and export's --slot with several magnetometers: exit 2."""
    result = run("fit", logs / "s.bin", "--mag", "MAG[0],")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: Invalid value for '--mag': 'MAG[0],' has an empty id; give stream ids as "
                                  "magcal inspect lists them, e.g. --mag 'MAG[0]'")
    result = run("check", logs / "s.bin", "--mag", "all", "--mag", "MAG[0]")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: Invalid value for '--mag': 'all' cannot be combined with ids (MAG[0]); "
                                  "give one or the other")
    doc = two_mag_document(logs, tmp_path)
    result = run("export", doc, "--ardupilot", tmp_path / "a.param", "--mag", "MAG[0],MAG[1]", "--slot", "2")
    assert result.exit_code == 2
    assert last_error(result) == ("Error: --slot applies to one magnetometer, but --mag gives 2 (MAG[0], MAG[1]); "
                                  "give one --mag")


# --- item 5: documents work from any directory ----------------------------------------------------------------

def test_the_document_stores_the_absolute_source_and_export_finds_it(logs: Path, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """fit ran in the logs' folder with `s.bin`; export from elsewhere still reads the log's parameters."""
    doc = json.loads((logs / "out" / "calibration.json").read_text())
    assert doc["source"]["path"] == str(logs / "s.bin")
    monkeypatch.chdir(tmp_path)
    result = run("export", logs / "out" / "calibration.json", "--ardupilot", "a.param")
    assert result.exit_code == 0, result.output
    assert "magcal: vehicle parameters from the document's source log s.bin" in result.stderr


def test_export_says_when_the_source_log_is_missing(logs: Path, tmp_path: Path) -> None:
    """It used to export without the vehicle's parameters (other slots and orientations) and say nothing."""
    cal = load(logs / "out" / "calibration.json")
    doc = tmp_path / "moved.json"
    gone = tmp_path / "gone.bin"
    doc.write_text(dumps_json(replace(cal, source=replace(cal.source, path=str(gone)))))
    result = run("export", doc, "--ardupilot", tmp_path / "a.param")
    assert result.exit_code == 1
    assert result.stderr == (f"Error: {doc}: the source log {gone} is missing, so the vehicle's parameters (compass "
                             "slots, orientations, device ids) are unknown and the parameters would differ. Restore "
                             "the log, or pass --params with the log or the vehicle's parameter file\n")
    assert not (tmp_path / "a.param").exists()
    again = run("export", doc, "--ardupilot", tmp_path / "a.param", "--params", logs / "s.bin", "-q")
    assert again.exit_code == 0, again.output


# --- item 6: check --------------------------------------------------------------------------------------------

def test_check_reports_a_gate_it_cannot_measure_as_not_measured(logs: Path) -> None:
    """No current or throttle in the log: interference_pct>30 is not measured (exit 0), and --require-measured
    fails on it (exit 3). The header names the calibration file used, not the document's source log."""
    cal = logs / "out" / "calibration.json"
    args = ["check", logs / "s.bin", "--calibration", cal, "--no-refit", "--fail-on", "interference_pct>30", "-q"]
    result = run(*args)
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0] == (f"{logs / 's.bin'}: calibration from the calibration document {cal}; levelled with roll and "
                        "pitch of ATT")
    assert lines[2] == "MAG[0] (document): NOT MEASURED"
    assert lines[-2:] == ["  gate not measured: interference_pct>30 (not measured: no battery current or throttle "
                          "that varies in the log)",
                          "PASSED, but 1 gate not measured (--require-measured fails on them)"]
    strict = run(*args, "--require-measured")
    assert strict.exit_code == 3
    assert strict.stderr == ("Error: check: MAG[0]: interference_pct>30 (not measured: no battery current or "
                             "throttle that varies in the log)\n")
    assert strict.stdout.splitlines()[-1] == "FAILED"


def test_check_names_the_parameter_file(logs: Path, tmp_path: Path) -> None:
    from magcal_cli.firmware.paramfile import render
    from magcal_cli.readers import open_recording

    params = tmp_path / "vehicle.param"
    params.write_text(render(dict(open_recording(logs / "s.bin").params), "mission-planner"))
    result = run("check", logs / "s.bin", "--params", params, "--no-refit", "--max-heading-error-deg", "inf", "-q")
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines()[0] == (f"{logs / 's.bin'}: calibration from the parameter file {params}; "
                                             "levelled with roll and pitch of ATT")


def test_check_refuses_a_log_without_parameters_before_the_refit(logs: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A CSV log has no flown calibration: exit 1 at once, not after fitting a new calibration for nothing."""
    import magcal_cli.pipeline

    monkeypatch.setattr(magcal_cli.pipeline, "calibrate", never)
    result = run("check", logs / "s.csv", "-q")
    assert result.exit_code == 1
    assert result.stderr == ("Error: s.csv: no compass calibration known (the log's parameters (csv) hold no "
                             "COMPASS_* or CAL_MAGn_* parameters). Pass --params with the vehicle's parameter file "
                             "or --calibration with the calibration it used\n")
