"""What every command shares: exit codes, error mapping, -q/-v, progress and the terminal's remarks."""

from __future__ import annotations

import functools
import re
import sys
import traceback
from collections.abc import Callable
from typing import Any, TypeVar

import click

from magcal_cli.errors import MagcalError
from magcal_cli.writers import fitrun

F = TypeVar("F", bound=Callable[..., Any])
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}
EXIT_CODES = ("Exit codes: 0 success; 1 the input could not be used (unreadable, truncated or unsupported log, "
              "missing stream, too little motion, no convergence); 2 usage error; 3 a quality gate failed; "
              "123 internal error (a bug); 130 interrupted (Ctrl-C), nothing half-written left. A closed pipe "
              "(e.g. | head) ends the command quietly with 1.")


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


#: finding code -> its one-line form in the terminal ({max_factor} and {what} filled from the group's evidence)
BRIEF = {"correlated_residuals": "residuals correlated in time beyond the noise model (uncertainty widened up to "
                                 "{max_factor:.1f}x)",
         "poorly_observable": "{what} poorly determined by the motion in this log (docs/recording-guide.md says "
                              "which motion determines it)",
         "dip_disagrees_with_wmm": "fitted dip differs from the World Magnetic Model's"}
#: a kind with a single warning no longer than this is printed in full
FULL_CHARS = 240


def warning_lines(findings: tuple[Any, ...], mag_ids: list[str], verbose: bool) -> list[str]:
    """The fit's warnings for the terminal: every one in full with -v, else one line per kind naming the
    magnetometers (report.html and report.txt keep the full text)."""
    from magcal_cli.findings import Severity
    from magcal_cli.writers.report.verdict import groups

    warnings = tuple(f for f in findings if f.severity is Severity.WARNING)
    if verbose:
        return [f.message for f in warnings]
    out = []
    for g in groups(warnings, mag_ids):
        if len(g.messages) == 1 and len(g.messages[0]) <= FULL_CHARS:
            out.append(g.messages[0])
            continue
        mine = [f for f in warnings if f.code == g.code]
        factor = max((float(f.evidence.get("max_factor", 0.0)) for f in mine), default=0.0)
        what = sorted({m.group(1) for f in mine if (m := re.search(r"leaves the (.+?) poorly determined", f.message))})
        text = BRIEF.get(g.code, g.title[:1].lower() + g.title[1:]).format(max_factor=factor,
                                                                           what=", ".join(what) or "parameters")
        who = ", ".join(g.sensors) if len(g.sensors) < 3 else f"{len(g.sensors)} magnetometers ({', '.join(g.sensors)})"
        out.append(f"{who}: {text}" if who else text)
    return out


def handle_errors(func: F) -> F:
    """Map MagcalError to exit 1, quality gates to 3, interrupts to 130 and anything else (a bug) to 123."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        ctx = click.get_current_context()
        try:
            return func(*args, **kwargs)
        except MagcalError as exc:
            raise click.ClickException(str(exc)) from None
        except QualityGateError as exc:
            click.echo(f"Error: {exc}", err=True)
            ctx.exit(3)
        except KeyboardInterrupt:
            click.echo("Error: interrupted; outputs not yet renamed into place were discarded.", err=True)
            ctx.exit(130)
        except (click.ClickException, click.exceptions.Exit, BrokenPipeError):
            raise                       # click's main: a closed stdout (| head) exits 1 quietly
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
    """A bug: one line (the traceback with -v), exit 123."""
    if ctx.obj.get("verbose"):
        traceback.print_exception(exc, file=sys.stderr)
    click.echo(f"Error: internal error ({type(exc).__name__}: {exc}). This is a bug in magcal; please "
               "report it with the command and log" + ("" if ctx.obj.get("verbose") else
                                                         "; run with -v for the traceback") + ".", err=True)
    ctx.exit(123)


def verbosity(func: F) -> F:
    """-q/--quiet and -v/--verbose on a command."""

    def set_quiet(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        ctx.ensure_object(dict)
        ctx.obj["quiet"] = ctx.obj.get("quiet", False) or value

    def set_verbose(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        ctx.ensure_object(dict)
        ctx.obj["verbose"] = ctx.obj.get("verbose", False) or value

    func = click.option("-q", "--quiet", is_flag=True, expose_value=False, callback=set_quiet,
                        help="Print nothing on stderr but errors.")(func)
    return click.option("-v", "--verbose", is_flag=True, expose_value=False, callback=set_verbose,
                        help="More detail on stderr; a traceback for internal errors.")(func)


#: the file system refusing a read or write: the user's environment, not a bug (exit 1, not 123); batch shares it
USER_ERRNOS = fitrun.USER_ERRNOS


#: what --effects auto parses to: the diagnosis chooses the effects
AUTO = ("auto",)


def effects_option(_: click.Context, __: click.Parameter, value: str) -> tuple[str, ...]:
    """--effects parsed into effect ids, or AUTO."""
    from magcal_cli.effects import EffectError, parse

    if value.strip() == "auto":
        return AUTO
    try:
        return parse(value)
    except EffectError as exc:
        raise click.BadParameter(str(exc).removeprefix("--effects: ")) from None


def parse_outputs(value: str) -> list[str]:
    """The --outputs list, validated against the writer registry."""
    from magcal_cli.writers import WRITERS

    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [n for n in names if n not in WRITERS]
    if bad or not names:
        msg = f"unknown output(s) {', '.join(bad) or '(none)'}; choose from {', '.join(WRITERS)}"
        raise click.BadParameter(msg, param_hint="--outputs")
    return names


def gates_option(value: str | None, command: str) -> tuple[Any, ...]:
    """--fail-on parsed against the metrics `command` measures, or a usage error."""
    from magcal_cli.firmware import gates

    if value is None:
        return ()
    if command == "fit":
        from magcal_cli.firmware.metrics import METRICS
    else:
        from magcal_cli.firmware.check import METRICS
    try:
        return gates.parse(value, METRICS)
    except MagcalError as exc:
        raise click.BadParameter(str(exc).split(": ", 1)[-1], param_hint="--fail-on") from None
