"""What every command shares: exit codes, error mapping, -q/-v, progress and the terminal's remarks."""

from __future__ import annotations

import functools
import re
import sys
import traceback
from collections.abc import Callable
from typing import Any, TypeVar

import click

from magcal_cli.cli.options import option
from magcal_cli.errors import MagcalError, SelectionError
from magcal_cli.writers import fitrun

F = TypeVar("F", bound=Callable[..., Any])
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}
#: the exit code of a run stopped by Ctrl-C (spec/cli.md), and what it says
INTERRUPTED = 130
INTERRUPTED_MESSAGE = "Error: interrupted; outputs not yet renamed into place were discarded."
EXIT_CODES = ("Exit codes: 0 success; 1 the input could not be used (unreadable, truncated or unsupported log, "
              "missing stream, too little motion, no convergence); 2 usage error (a bad option, a stream id the "
              "log does not have, an output that exists or is a file where a folder belongs); 3 a quality gate "
              "failed; 123 internal error (a bug); 130 interrupted (Ctrl-C), nothing half-written left. A reader "
              "that closes the pipe before taking all of the output (e.g. | head -c 10) ends the command quietly "
              "with 1.")
#: how long a finished command waits for a pipe's reader to take (or drop) its output, at most (s)
PIPE_WAIT_S = 1.0


class QualityGateError(Exception):
    """A --fail-on or check threshold failed (exit 3)."""


def say(ctx: click.Context, message: str) -> None:
    """Progress and remarks: stderr, silenced by -q."""
    if not ctx.obj.get("quiet"):
        click.echo(f"magcal: {message}", err=True)


def progress_line(ctx: click.Context) -> Any:
    """The progress renderer on stderr (a context manager and the pipeline's hook): silent with -q, the live
    stage/fraction/time-left line only when stderr is a terminal."""
    from magcal_cli.progress import Progress

    return Progress.for_stderr(bool(ctx.obj.get("quiet")))


#: finding code -> its folded line in the terminal: what happened and what to do, said once for every magnetometer
#: it names; the {fields} come from the group's evidence and messages (`_fields`)
BRIEF = {
    "flown_calibration_better": "the calibration the vehicle flew with is better for heading against its attitude, "
                                "so it is left out of the firmware parameter file (--export-worse writes it); to "
                                "fix: record again turning the vehicle through full circles and tilting it",
    "correlated_residuals": "residuals correlated in time beyond the noise model (uncertainty widened up to "
                            "{max_factor:.1f}x)",
    "poorly_observable": "{what} poorly determined by the motion in this log{fix}",
    "low_coverage": "the field directions cover only {coverage} of the sphere; record again, rolling and pitching "
                    "the vehicle through all orientations",
    "attitude_reference": "calibrated against the vehicle's attitude estimate and the World Magnetic Model, as the "
                          "log's own motion determines too little, so it inherits that estimate's heading errors; "
                          "for a calibration of its own, record again turning the vehicle about all three axes",
    "dip_disagrees_with_wmm": "fitted dip differs from the World Magnetic Model's by up to {dip_off:.1f} deg; "
                              "calibrate from a recording with the vehicle moved by hand, or check the field near "
                              "the vehicle",
    "not_calibrated": "not calibrated{fix}",
    "disturbance_modelled": "the base model could not explain the readings, and a disturbance the log records "
                            "(current, throttle, motors or temperature) does, so it was calibrated with it; to fix: "
                            "route power wiring away from the compass",
    "not_converged": "the solver stopped before converging, so the numbers are not final; do not use this "
                     "calibration, record again with more rotation",
    "normalised_field": "the log holds the field normalised to unit length, so hard iron and field strength are "
                        "lost; log the raw magnetometer readings",
    "method_choice": "the field was normalised upstream, so only the misalignment and dip are meaningful; log the "
                     "raw magnetometer readings for a full calibration",
    "magnetometer_inconsistent": "the magnetometers disagree after calibration; find the disturbance near them "
                                 "(power wiring, motors, steel) before using them for heading",
    "known_physics_dropped": "the acceleration from the GPS was left out, as it disagrees with the accelerometer; "
                             "check the GPS for glitches, lag or an antenna far from the IMU",
    "diagnosis_failed": "the mismatch diagnosis could not run, so the base calibration is reported without it; -v "
                        "prints why",
    "unmeasured_motion": "the IMU did not measure the motion in places (an impact or the gyro at its range), so "
                         "those samples are not used; nothing to do",
}
#: a kind with a single warning no longer than this is printed in full
FULL_CHARS = 240
#: the advice a finding's message ends with
TO_FIX = re.compile(r"To fix: (.+?)\.?$")
#: where a folded line points when its findings' messages give no advice of their own
NO_FIX = {"poorly_observable": " (docs/recording-guide.md says which motion determines it)"}


def _fields(code: str, mine: list[Any]) -> dict[str, str | float]:
    """What a folded line quotes from its findings: the largest widening and dip offset, the coverage, the
    parameters poorly determined and the advice their messages end with."""
    cover = sorted(float(f.evidence["coverage_pct"]) for f in mine if "coverage_pct" in f.evidence)
    what = sorted({m.group(1) for f in mine if (m := re.search(r"leaves the (.+?) poorly determined", f.message))})
    fixes = list(dict.fromkeys(m.group(1) for f in mine if (m := TO_FIX.search(f.message))))
    return {"max_factor": max((float(f.evidence.get("max_factor", 0.0)) for f in mine), default=0.0),
            "dip_off": max((abs(float(f.evidence["dip_deg"]) - float(f.evidence["wmm_dip_deg"])) for f in mine
                            if {"dip_deg", "wmm_dip_deg"} <= f.evidence.keys()), default=0.0),
            "coverage": "?" if not cover else f"{cover[0]:.0f} %" if round(cover[0]) == round(cover[-1]) else
                        f"{cover[0]:.0f}-{cover[-1]:.0f} %",
            "what": ", ".join(what) or "parameters",
            "fix": f"; to fix: {'; '.join(fixes)}" if fixes else NO_FIX.get(code, "; -v prints why")}


def warning_lines(findings: tuple[Any, ...], mag_ids: list[str], verbose: bool) -> list[str]:
    """The fit's warnings for the terminal: every one in full with -v, else one line per kind that names the
    magnetometers once and says what to do (report.html and report.txt keep the full text)."""
    from magcal_cli.findings import Severity
    from magcal_cli.writers.report.verdict import groups

    warnings = tuple(f for f in findings if f.severity is Severity.WARNING)
    if verbose:
        return [f.message for f in warnings]
    out: list[str] = []
    for g in groups(warnings, mag_ids):
        if g.code == "not_calibrated":      # each refused magnetometer by name, with its own reason and advice
            out.extend(f.message if TO_FIX.search(f.message) else f"{f.message}; -v prints why"
                       for f in warnings if f.code == g.code)
            continue
        if len(g.messages) == 1 and len(g.messages[0]) <= FULL_CHARS:
            out.append(g.messages[0])
            continue
        fields = _fields(g.code, [f for f in warnings if f.code == g.code])
        text = BRIEF.get(g.code, g.title[:1].lower() + g.title[1:] + "{fix}").format(**fields)
        who = ", ".join(g.sensors) if len(g.sensors) < 3 else f"{len(g.sensors)} magnetometers ({', '.join(g.sensors)})"
        out.append(f"{who}: {text}" if who else text)
    return out


def output_lost(wait_s: float = PIPE_WAIT_S) -> bool:
    """After a command that succeeded: True when standard output is a pipe whose reader closed it before taking
    all of the output (`| head -c 10`), which the contract calls a closed pipe (exit 1).

    Output that fits in the pipe is accepted at once, so the write itself cannot tell; this waits (up to `wait_s`)
    until the reader has taken every byte (delivered: False) or has gone with bytes unread (lost: True). A reader
    that took everything and stopped later (`| head -1` on a short table) was delivered the whole output.
    """
    import fcntl
    import os
    import select
    import stat
    import struct
    import termios
    import time

    try:
        sys.stdout.flush()
    except BrokenPipeError:
        return True
    except (OSError, ValueError):
        return False
    try:
        fd = sys.stdout.fileno()
        if not stat.S_ISFIFO(os.fstat(fd).st_mode):
            return False
        poller = select.poll()
        poller.register(fd, 0)                  # a pipe's write end reports POLLERR once its reader is gone
        deadline = time.monotonic() + wait_s
        while True:
            unread = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, struct.pack("i", 0)))[0]
            if unread == 0:
                return False
            if any(events & select.POLLERR for _, events in poller.poll(0)):
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
    except (OSError, ValueError, AttributeError):       # not a file, or no FIONREAD here: nothing to tell
        return False


def handle_errors(func: F) -> F:
    """Map MagcalError to exit 1, quality gates to 3, interrupts to 130 and anything else (a bug) to 123."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        ctx = click.get_current_context()
        for note in (ctx.obj or {}).get("deprecated", []):
            say(ctx, note)
        try:
            return func(*args, **kwargs)
        except SelectionError as exc:              # a stream id from the command line the log lacks: a usage mistake
            raise click.UsageError(str(exc), ctx) from None
        except MagcalError as exc:
            raise click.ClickException(str(exc)) from None
        except QualityGateError as exc:
            click.echo(f"Error: {exc}", err=True)
            ctx.exit(3)
        except KeyboardInterrupt:
            click.echo(INTERRUPTED_MESSAGE, err=True)
            ctx.exit(INTERRUPTED)
        except (click.ClickException, click.exceptions.Exit, BrokenPipeError):
            raise                       # click's main: a closed stdout (| head) exits 1 quietly (and main())
        except OSError as exc:
            if exc.errno not in USER_ERRNOS:
                internal_error(ctx, exc)
            where = exc.filename or "magcal"
            msg = f"{where}: {exc.strerror or exc}. Check the path, its permissions and free space"
            raise click.ClickException(msg) from None
        except Exception as exc:  # noqa: BLE001 - the last line of defence: a bug must not print a traceback
            internal_error(ctx, exc)

    return wrapper  # type: ignore[return-value]


def internal_error(ctx: click.Context, exc: BaseException) -> None:
    """A bug: one line (the traceback with -v), exit 123; a Ctrl-C that Python wrapped in another error (one
    landing in a class's `__set_name__` while a module imports on first use) is the interrupt it was, exit 130."""
    if _caused_by_interrupt(exc):
        click.echo(INTERRUPTED_MESSAGE, err=True)
        ctx.exit(INTERRUPTED)
    if ctx.obj.get("verbose"):
        traceback.print_exception(exc, file=sys.stderr)
    click.echo(f"Error: internal error ({type(exc).__name__}: {exc}). This is a bug in magcal; please "
               "report it with the command and log" + ("" if ctx.obj.get("verbose") else
                                                         "; run with -v for the traceback") + ".", err=True)
    ctx.exit(123)


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in `exc`'s chain of causes and contexts."""
    seen: set[int] = set()
    at: BaseException | None = exc
    while at is not None and id(at) not in seen:
        if isinstance(at, KeyboardInterrupt):
            return True
        seen.add(id(at))
        at = at.__cause__ or at.__context__
    return False


def verbosity(func: F) -> F:
    """-q/--quiet and -v/--verbose on a command."""

    def set_quiet(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        ctx.ensure_object(dict)
        ctx.obj["quiet"] = ctx.obj.get("quiet", False) or value

    def set_verbose(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        ctx.ensure_object(dict)
        ctx.obj["verbose"] = ctx.obj.get("verbose", False) or value

    func = option("quiet", callback=set_quiet)(func)
    return option("verbose", callback=set_verbose)(func)


#: the file system refusing a read or write: the user's environment, not a bug (exit 1, not 123); batch shares it
USER_ERRNOS = fitrun.USER_ERRNOS

