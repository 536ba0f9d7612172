"""The batch's lines on stderr: one per log that ends, with the batch's time left, and Ctrl-C's summary."""

from __future__ import annotations

from magcal_cli.batch.plan import LogReport
from magcal_cli.batch.report import Tally, interrupted_line


def _report(name: str, status: str = "ok", seconds: float = 4.0) -> LogReport:
    """A log's report as a worker returns it."""
    return LogReport(f"/logs/{name}.bin", name, f"/out/{name}", status, 130 if status == "interrupted" else 0,
                     seconds=seconds)


def test_progress_lines_give_the_time_left_once_a_log_was_fitted() -> None:
    """Issue 30 item 5: '[3/10, about 35 s left]': the logs left at the rate logs were fitted (skipped ones aside,
    on all workers together); nothing to estimate before the first fit ends or after the last."""
    clock = [100.0]
    tally = Tally(10, clock=lambda: clock[0])
    assert tally.line(_report("a", "skipped")) == "[1/10] a: skipped (up to date)"
    clock[0] += 5.0
    assert tally.line(_report("b")) == "[2/10, about 40 s left] b: ok in 4.0 s"
    clock[0] += 5.0
    assert tally.line(_report("c")) == "[3/10, about 35 s left] c: ok in 4.0 s"
    tally.ended = 9
    assert tally.line(_report("j")) == "[10/10] j: ok in 4.0 s"


def test_interrupted_line_says_what_was_done_and_how_to_go_on() -> None:
    """Issue 30 item 5: Ctrl-C's one line counts the logs done, stopped (nothing of theirs written) and not started,
    and says that running the command again goes on where it stopped."""
    reports = [_report("a", "skipped"), _report("b"), _report("c", "interrupted"), _report("d", "interrupted")]
    assert interrupted_line(reports, 10) == (
        "interrupted: 2 of 10 logs done, 2 stopped with nothing of theirs written, 6 not started; run the same "
        "command again to fit the other 8 (the 2 done are skipped)")
    assert interrupted_line(reports[1:3], 4).endswith("fit the other 3 (the one done is skipped)")
    assert interrupted_line([], 3) == ("interrupted: 0 of 3 logs done, 0 stopped with nothing of theirs written, 3 "
                                       "not started; run the same command again to fit them")
