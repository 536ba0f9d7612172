"""stderr: the progress line's text, rate and time left (fake clock, fake terminal), its absence with -q or off a
terminal, and the warnings grouped one line per kind; the whole a stage belongs to ("magnetometer 2 of 3" and the
whole's time left), threaded items and report figures that move their stage (issue 30 item 5).

Modules it covers (the mirrored test file aside): magcal_cli.diagnose.parallel."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import progress as progress_mod
from magcal_cli.cli.main import cli
from magcal_cli.diagnose.parallel import pmap
from magcal_cli.progress import Progress, active, current, duration, noop, within
from magcal_cli.readers import open_recording
from magcal_cli.synth.logs import imu_sampling, write_log
from magcal_cli.synth.simulate import Simulation, simulate

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_logs" / "handheld.csv"


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def live(clock: Clock, width: int = 80) -> tuple[Progress, io.StringIO]:
    """A renderer on a fake terminal of `width` columns."""
    out = io.StringIO()
    return Progress(out, live=True, clock=clock, width=lambda: width), out


def frames(out: io.StringIO) -> list[str]:
    """The live line's successive texts."""
    return [f.removesuffix(progress_mod.CLEAR) for f in out.getvalue().split("\r") if f]


def test_fraction_and_time_left_from_the_stage_rate() -> None:
    """Stage, percentage and the time left extrapolated from the stage's own rate (shown after ETA_AFTER_S)."""
    clock = Clock()
    p, out = live(clock)
    p("fit MAG[0]", 0, 100)
    clock.t += 0.5
    p("fit MAG[0]", 10, 100)
    clock.t += 1.5                         # 20 steps in 2 s: 80 left at 10 per second
    p("fit MAG[0]", 20, 100)
    assert frames(out) == ["magcal: fit MAG[0]:   0 %", "magcal: fit MAG[0]:  10 %", "magcal: fit MAG[0]:  20 %, 8 s left"]


def test_redraws_at_most_rate_hz_in_a_hot_loop() -> None:
    """A thousand calls within 0.1 s draw once; a new stage is drawn at once (up to STAGE_HZ)."""
    clock = Clock()
    p, out = live(clock)
    for i in range(1000):
        clock.t += 1e-4
        p("loop", i, 1000)
    assert len(frames(out)) == 1
    clock.t += 0.06
    p("next stage", 0)
    assert frames(out)[-1] == "magcal: next stage"
    clock.t += 0.06
    p("next stage", 1)                     # same stage within 1/RATE_HZ: not redrawn
    assert len(frames(out)) == 2


def test_messages_are_lines_and_erase_the_live_line() -> None:
    """A message erases the live line and prints a line; close() erases the live line before results."""
    clock = Clock()
    p, out = live(clock)
    p("pass 1", 5, 10)
    p("reading x.bin")
    assert out.getvalue().endswith("\r" + progress_mod.CLEAR + "magcal: reading x.bin\n")
    clock.t += 1.0
    p("pass 1", 6, 10)
    p.close()
    assert out.getvalue().endswith(progress_mod.CLEAR + "\r" + progress_mod.CLEAR)


def test_long_line_is_cut_to_the_terminal_width() -> None:
    """A line that wraps could not be rewritten in place: it is cut to the width minus one."""
    p, out = live(Clock(), width=30)
    p("x" * 100, 1, 2)
    assert len(frames(out)[0]) == 29


def test_not_a_terminal_or_quiet_prints_no_live_line() -> None:
    """Off a terminal: messages only; quiet: nothing."""
    out = io.StringIO()
    p = Progress(out, live=False)
    p("reading x.bin")
    p("pass", 1, 2)
    p.close()
    assert out.getvalue() == "magcal: reading x.bin\n"
    quiet = io.StringIO()
    q = Progress(quiet, live=False, lines=False)
    q("reading x.bin")
    q("pass", 1, 2)
    assert quiet.getvalue() == ""


def test_duration_and_current_hook() -> None:
    """Times read as people say them; active() sets the hook code without an argument finds."""
    assert [duration(s) for s in (8.4, 125, 3780)] == ["8 s", "2 min 05 s", "1 h 03 min"]
    assert current() is noop
    seen: list[tuple[str, float | None, float | None]] = []

    def hook(stage: str, done: float | None = None, total: float | None = None) -> None:
        seen.append((stage, done, total))

    with active(hook):
        assert current() is hook
        pmap(lambda x: x * 2, [1, 2, 3], jobs=2, done=lambda i, n: current()("replicates", i, n))
    assert current() is noop
    assert seen == [("replicates", 1, 3), ("replicates", 2, 3), ("replicates", 3, 3)]


def test_within_maps_a_steps_fractions_into_its_part_of_the_stage() -> None:
    """Parsing 0..0.3 then building 0.3..1 of one "reading" stage; messages and unknown sizes pass unchanged."""
    seen: list[tuple[str, float | None, float | None]] = []

    def hook(stage: str, done: float | None = None, total: float | None = None) -> None:
        seen.append((stage, done, total))

    parse, build = within(hook, 0.0, 0.3), within(hook, 0.3, 1.0)
    parse("reading", 50, 100)
    build("reading", 1, 4)
    build("reading", 3, 2)                 # past the end: held at the part's end
    build("reading x.bin")
    build("reading", 7, None)
    assert seen == [("reading", 0.15, 1.0), ("reading", 0.475, 1.0), ("reading", 1.0, 1.0), ("reading x.bin", None, None),
                    ("reading", 7, None)]


def _as_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the CLI's stderr renderer believe stderr is a terminal."""
    real = Progress.for_stderr.__func__  # type: ignore[attr-defined]

    def fake(cls: type[Progress], quiet: bool) -> Progress:
        p: Progress = real(cls, quiet)
        p.live = not quiet
        return p

    monkeypatch.setattr(Progress, "for_stderr", classmethod(fake))


@pytest.mark.parametrize(("terminal", "quiet"), [(False, False), (True, True), (True, False)])
def test_cli_progress_only_on_a_terminal_without_q(runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     terminal: bool, quiet: bool) -> None:
    """fit --method ekf-aug reports its filter pass on a terminal; with -q, or off a terminal, no live line."""
    if terminal:
        _as_terminal(monkeypatch)
    monkeypatch.setattr(progress_mod, "RATE_HZ", 1e9)          # draw every report: the test is fast
    args = ["fit", str(SAMPLE), "-o", str(tmp_path / "out"), "--method", "ekf-aug", "--outputs", "json"]
    result = runner.invoke(cli, [*args, *(["-q"] if quiet else [])])
    assert result.exit_code == 0, result.output
    shown = "\r" in result.stderr and "ekf-aug filter pass" in result.stderr
    assert shown is (terminal and not quiet)
    assert ("magcal: reading: 100 %" in result.stderr) is (terminal and not quiet)
    if quiet:
        assert result.stderr == ""
    else:
        assert "magcal: reading handheld.csv\n" in result.stderr


def test_warnings_grouped_one_line_per_kind_and_in_full_with_v() -> None:
    """log171's kinds: a long warning repeated per compass is one line naming them; a short single one stays whole."""
    from magcal_cli.cli.common import warning_lines
    from magcal_cli.findings import Finding, Severity

    long_tail = " (quantised readings, unmodelled motion or a disturbance); the uncertainty of D was widened" * 3
    found = (
        Finding(Severity.WARNING, "unmeasured_motion", "IMU[0]: the IMU did not measure the motion at 227.4-228.0 s"),
        *(Finding(Severity.WARNING, "correlated_residuals", f"log.bin: {m}: the residuals are correlated{long_tail}",
                  {"max_factor": f}) for m, f in (("MAG[0]", 3.2), ("MAG[1]", 10.6), ("MAG[2]", 4.0))),
        Finding(Severity.WARNING, "poorly_observable", f"log.bin: MAG[2]: this log leaves the accelerometer bias "
                f"poorly determined{long_tail}", {"parameters": ["accelerometer_bias.x", "accelerometer_bias.y"]}),
        Finding(Severity.INFO, "reader_note", "MAG[0]: undid the firmware correction"),
    )
    mags = ["MAG[0]", "MAG[1]", "MAG[2]"]
    assert warning_lines(found, mags, verbose=False) == [
        "IMU[0]: the IMU did not measure the motion at 227.4-228.0 s",
        "3 magnetometers (MAG[0], MAG[1], MAG[2]): residuals correlated in time beyond the noise model (uncertainty "
        "widened up to 10.6x)",
        "MAG[2]: accelerometer bias poorly determined by the motion in this log (docs/recording-guide.md says which "
        "motion determines it)"]
    assert warning_lines(found, mags, verbose=True) == [f.message for f in found[:5]]


def minute(path: Path) -> Simulation:
    """A minute of hand-held motion to write to `path`: the IMU sampled as its format holds it, the field read on IMU
    stamps (phase 0: a CSV log has one row per IMU sample)."""
    return simulate("handheld", 1, duration=60.0, imu_sampling=imu_sampling(path), mag_phase_s=0.0)


@pytest.fixture(scope="module")
def sim60() -> Simulation:
    """A minute of hand-held motion (instantaneous IMU samples: every format but .ulg)."""
    return minute(Path("r.mcap"))


def _reading(path: Path) -> list[float]:
    """The fractions the reader of `path` reports as the "reading" stage through the active hook."""
    calls: list[tuple[str, float | None, float | None]] = []

    def record(stage: str, done: float | None = None, total: float | None = None) -> None:
        calls.append((stage, done, total))

    with active(record):
        open_recording(path)
    assert all(total and done is not None for stage, done, total in calls if stage == "reading"), calls
    return [done / total for stage, done, total in calls if stage == "reading" and done is not None and total]


@pytest.mark.parametrize("name", ["r.mcap", "r.bag", "r.bin", "r.log", "r.ulg", "r.csv"])
def test_reading_reports_fractions_that_rise_to_one(sim60: Simulation, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                    name: str) -> None:
    """Issue 13 item 2: every reader reports the fraction read (bytes, chunks, then building the streams) through
    the active hook, from 0 up to 1 and never back; ULog and CSV per REPORT_BYTES / CSV_BLOCK (made small here so a
    1 MB log reports several times)."""
    from magcal_cli.readers import csvfile
    from magcal_cli.readers.ulog import load as ulog_load
    from tests.readers.test_dataflash import text_log

    monkeypatch.setattr(ulog_load, "REPORT_BYTES", 1 << 16)
    monkeypatch.setattr(csvfile, "CSV_BLOCK", 1 << 16)
    path = tmp_path / name
    if name == "r.log":                     # a Copter 3.x text DataFlash log: no writer, the reader test's builder
        u = np.random.default_rng(2).standard_normal((400, 3))
        path.write_text(text_log(450.0 * u / np.linalg.norm(u, axis=1, keepdims=True))[0])
    else:
        write_log(sim60 if imu_sampling(path) is sim60.imu_sampling else minute(path), path)
    f = _reading(path)
    assert f[0] < 0.01 and f[-1] == 1.0, f
    assert all(b >= a for a, b in zip(f, f[1:], strict=False)), f
    assert len(set(f)) >= 4, f


def test_the_map_fit_reports_its_noise_rounds(sim60: Simulation, tmp_path: Path) -> None:
    """Issue 13 item 2: the joint MAP's noise rounds report done/total through the active hook."""
    from magcal_cli.config import Config
    from magcal_cli.models.map.fit import fit_map
    from magcal_cli.pipeline import select_problem

    calls: list[tuple[str, float | None, float | None]] = []

    def record(stage: str, done: float | None = None, total: float | None = None) -> None:
        calls.append((stage, done, total))

    write_log(sim60, tmp_path / "r.mcap")
    problem = select_problem(open_recording(tmp_path / "r.mcap"), Config())
    with active(record):
        fit_map(problem, problem.mags[0])
    rounds = [c for c in calls if "joint MAP, noise round" in c[0]]
    assert rounds and rounds[0][1] == 0 and all(c[2] == rounds[0][2] for c in rounds)


def test_parts_name_the_whole_and_its_time_left() -> None:
    """Issue 30 item 5: inside a part the stage names the whole ("magnetometer 2 of 3"); once a part has ended the
    whole's time left follows from the parts' mean duration, and the line then carries that one estimate (the
    stage's own is left out). A whole of one part passes its stages unchanged."""
    clock = Clock()
    p, out = live(clock, width=200)
    parts = progress_mod.Parts(p, "magnetometer", 3, clock=clock)
    with parts.part(0):
        current()("MAG[0]: joint MAP", 0, 4)
        clock.t += 10.0
    with parts.part(1):
        clock.t += 2.0
        current()("MAG[1]: joint MAP", 2, 4)
        clock.t += 1.5                     # the stage's own rate would give a time left: not shown beside the whole's
        current()("MAG[1]: joint MAP", 3, 4)
    assert frames(out) == ["magcal: magnetometer 1 of 3: MAG[0]: joint MAP:   0 %",
                           "magcal: magnetometer 2 of 3, about 18 s left: MAG[1]: joint MAP:  50 %",
                           "magcal: magnetometer 2 of 3, about 16 s left: MAG[1]: joint MAP:  75 %"]
    seen: list[tuple[str, float | None, float | None]] = []
    one = progress_mod.Parts(lambda s, d=None, t=None: seen.append((s, d, t)), "magnetometer", 1, clock=clock)
    for _ in one.each(["MAG[0]"]):
        current()("MAG[0]: joint MAP", 1, 2)
    assert seen == [("MAG[0]: joint MAP", 1, 2)]


def test_a_fit_of_several_magnetometers_names_each(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 30 item 5: the joint MAP method's stages say which magnetometer of how many they belong to, one after
    the other; side by side (diagnose/forked.py), the first one's fit does and the rest is named as the whole."""
    from magcal_cli.config import Config
    from magcal_cli.diagnose import parallel
    from magcal_cli.methods import map_run
    from magcal_cli.pipeline import calibrate

    write_log(simulate("handheld", 4, rate=50.0, mag_rate=25.0, duration=40.0, n_mags=2), tmp_path / "two.mcap")

    def stages() -> list[str]:
        calls: list[str] = []
        with active(lambda stage, done=None, total=None: calls.append(stage)):
            calibrate(tmp_path / "two.mcap", Config(method="map", robust_loss="huber"))
        return calls

    monkeypatch.setattr(parallel, "JOBS", 1)                  # one at a time
    calls = stages()
    assert any(c.startswith("magnetometer 1 of 2: /imu/mag: joint MAP") for c in calls), calls
    assert any(c.startswith("magnetometer 2 of 2") and "/imu/mag1: joint MAP" in c for c in calls), calls
    monkeypatch.setattr(parallel, "JOBS", 2)
    monkeypatch.setattr(map_run, "side_by_side", lambda count: True)
    calls = stages()
    assert any(c.startswith("magnetometer 1 of 2: /imu/mag: joint MAP") for c in calls), calls
    assert "magnetometers 1-2 side by side" in calls, calls


def test_threaded_items_move_their_stage_while_they_run() -> None:
    """Issue 30 item 5: the diagnosis' folds are few and long; their own reports move the stage between their ends
    (up to ITEM_CAP of an item before it ends), the number never goes back and ends at the count."""
    seen: list[float] = []

    def item(x: int) -> int:
        for k in range(4):
            current()(f"fit {x}", k, 4)         # as a fold's fits report through current()
        return x

    assert pmap(item, [1, 2], jobs=1, done=lambda d, n: seen.append(d)) == [1, 2]
    assert seen == pytest.approx([0.25, 0.5, 0.75, 0.9, 1.0, 1.25, 1.5, 1.75, 1.9, 2.0])
    seen.clear()
    pmap(item, list(range(6)), jobs=2, done=lambda d, n: seen.append(d))
    assert seen[0] < 1 and seen[-1] == 6 and all(b >= a for a, b in zip(seen, seen[1:], strict=False)), seen


def test_report_figures_move_the_progress_line(tmp_path: Path) -> None:
    """Issue 30 item 5: report.html's figures took seconds without an update (6 s on log171); each figure now moves
    the "writing report.html" stage, from 0 to 1 and never back."""
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate
    from magcal_cli.writers.report import plots
    from magcal_cli.writers.report.html import STAGE, render_html

    result = calibrate(SAMPLE, Config(effects=()))
    drawn: list[int] = []
    real = plots.embed

    def counted(fig: object) -> str:
        drawn.append(1)
        return real(fig)  # type: ignore[arg-type]

    calls: list[tuple[str, float | None, float | None]] = []
    with active(lambda stage, done=None, total=None: calls.append((stage, done, total))):
        import magcal_cli.writers.report.sections.magnetometer as mag_section
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(plots, "embed", counted)
            mp.setattr(mag_section, "embed", counted)
            render_html(result)
    mine = [d / t for s, d, t in calls if s == STAGE and d is not None and t]
    assert len(drawn) >= 3 and len(set(mine)) > len(drawn), (len(drawn), mine)
    assert mine[0] == 0.0 and mine[-1] == 1.0 and all(b >= a for a, b in zip(mine, mine[1:], strict=False))


def test_fit_shows_its_writing_on_the_terminal(runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                               ) -> None:
    """Issue 30 item 5: fit's live line stays up while the outputs are written (report.html's figures), instead of
    freezing on the last fitting stage."""
    _as_terminal(monkeypatch)
    monkeypatch.setattr(progress_mod, "RATE_HZ", 1e9)
    result = runner.invoke(cli, ["fit", str(SAMPLE), "-o", str(tmp_path / "out"), "--effects", "none"])
    assert result.exit_code == 0, result.output
    assert "magcal: writing report.html: 100 %" in result.stderr
    assert (tmp_path / "out" / "report.html").is_file()
