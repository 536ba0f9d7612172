"""The options the commands share, declared once: `SHARED` is the table (name, meaning, value, commands) and
`option(key)` the one way a command declares one of them; `ALIASES` lists the old spellings kept for scripts.

A bad value is click's usage error (exit 2) naming the option, the value and what it accepts. An old spelling
works as before and leaves a one-line deprecation note (`deprecated`), printed when the command starts.
`tests/cli/test_options.py` walks every command's options against this table and fails on a drift.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from magcal_cli.methods.table import CHOICES

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling

F = TypeVar("F", bound=Callable[..., Any])

#: latitude and longitude ranges of --location (deg)
LAT_RANGE, LON_RANGE = (-90.0, 90.0), (-180.0, 180.0)
LOCATION_FORM = "LAT,LON[,ALT] in degrees and metres, e.g. 52.52,13.40,35"
#: what --effects auto parses to: the diagnosis chooses the effects
AUTO = ("auto",)
#: the outputs fit writes by default (the firmware file of the log's vehicle is added to them)
DEFAULT_OUTPUTS = "json,yaml,report,html"


# --- deprecation notes -------------------------------------------------------------------------------------------

def deprecated(ctx: click.Context, note: str) -> None:
    """Keep a one-line note about an old spelling; `cli.common.handle_errors` prints it (unless -q) when the
    command starts, after every option (-q included) has been read."""
    ctx.ensure_object(dict)
    notes = ctx.obj.setdefault("deprecated", [])
    if note not in notes:
        notes.append(note)


# --- value checks (click callbacks) --------------------------------------------------------------------------------

def mag_ids(_: click.Context, __: click.Parameter, values: tuple[str, ...]) -> tuple[str, ...]:
    """--mag: repeatable and a comma list, in every command; () means every magnetometer ('all')."""
    ids: list[str] = []
    for value in values:
        parts = [p.strip() for p in value.split(",")]
        if any(not p for p in parts):
            msg = f"{value!r} has an empty id; give stream ids as magcal inspect lists them, e.g. --mag 'MAG[0]'"
            raise click.BadParameter(msg)
        ids += [p for p in parts if p not in ids]
    if "all" in ids and len(ids) > 1:
        msg = f"'all' cannot be combined with ids ({', '.join(i for i in ids if i != 'all')}); give one or the other"
        raise click.BadParameter(msg)
    return () if ids == ["all"] else tuple(ids)


def log_format(_: click.Context, __: click.Parameter, value: str | None) -> str | None:
    """--format: a name `magcal inspect` prints or a reader's name, or None to sniff the log."""
    from magcal_cli.readers import format_names

    if value is None or value in format_names():
        return value
    msg = f"{value!r} is not a log format; choose from {', '.join(format_names())}, or leave --format out"
    raise click.BadParameter(msg)


def location(_: click.Context, __: click.Parameter, value: str | None) -> tuple[float, float, float] | None:
    """--location LAT,LON[,ALT] with latitude and longitude in range, or a usage error saying the range."""
    from magcal_cli.errors import MagcalError
    from magcal_cli.wmm import parse_location

    if value is None:
        return None
    try:
        numbers = [float(p) for p in value.split(",")]
    except ValueError:
        numbers = []
    if len(numbers) in (2, 3):
        for name, x, (lo, hi) in (("latitude", numbers[0], LAT_RANGE), ("longitude", numbers[1], LON_RANGE)):
            if not lo <= x <= hi:
                msg = f"{value!r}: {name} {x:g} is out of range [{lo:g}, {hi:g}]; expected {LOCATION_FORM}"
                raise click.BadParameter(msg)
    try:
        return parse_location(value)
    except MagcalError as exc:
        raise click.BadParameter(str(exc).removeprefix("--location ")) from None


def seconds(_: click.Context, param: click.Parameter, value: float | None) -> float | None:
    """--start/--end: a finite number of seconds from the log start."""
    if value is not None and not math.isfinite(value):
        msg = f"{value:g}: expected a finite number of seconds from the log start"
        raise click.BadParameter(msg)
    return value


def output_folder(_: click.Context, __: click.Parameter, value: Path | None) -> Path | None:
    """-o DIR: a folder, or a usage error (exit 2) when a file is there already."""
    if value is not None and value.exists() and not value.is_dir():
        msg = f"{value}: exists and is not a folder; this command writes a folder of outputs. Choose another -o"
        raise click.BadParameter(msg)
    return value


def log_output(ctx: click.Context, _: click.Parameter, value: Path | None) -> Path | None:
    """simulate -o LOG: a log is written to a file or folder named by its extension, never to standard output."""
    if value is not None and str(value) == "-":
        msg = ("simulate writes a log whose format follows its extension (and a truth file next to it), so it "
               "cannot go to standard output; give a file name, e.g. -o sim.bin")
        raise click.BadParameter(msg)
    return value


def effects_option(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[str, ...]:
    """--effects (repeatable, each a comma list) parsed into effect ids, or AUTO."""
    from magcal_cli.effects import EffectError, parse

    words = [w.strip() for v in values for w in v.split(",") if w.strip()]
    if words == ["auto"]:
        return AUTO
    if "auto" in words:
        msg = f"'auto' cannot be combined with effect ids ({', '.join(w for w in words if w != 'auto')}); give one"
        raise click.BadParameter(msg)
    if "none" in words and len(words) > 1:
        msg = f"'none' cannot be combined with effect ids ({', '.join(w for w in words if w != 'none')}); give one"
        raise click.BadParameter(msg)
    try:
        return parse(",".join(words))
    except EffectError as exc:
        raise click.BadParameter(str(exc).removeprefix("--effects: ")) from None


def effect_specs(values: Iterable[str]) -> list[str]:
    """simulate's --effects values split into one `ID[:key=value,...]` each: a comma starts another effect when
    the piece after it has no '=' (so `--effects a,b` means two effects, as in fit)."""
    specs: list[str] = []
    for value in values:
        for piece in value.split(","):
            if specs and ("=" in piece or not piece.strip()) and ":" not in piece:
                specs[-1] += "," + piece
            else:
                specs.append(piece)
    return [s for s in (p.strip().rstrip(",") for p in specs) if s]


def injected_effects(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[Any, ...]:
    """simulate --effects (and the old --effect) as EffectSpecs (SI), each id once; a bad one is exit 2."""
    from magcal_cli.synth.effects import EffectSpecError, check_unique, parse_effect

    try:
        specs = tuple(parse_effect(v) for v in effect_specs(values))
        check_unique(specs)
    except EffectSpecError as exc:
        raise click.BadParameter(str(exc), ctx, param) from None
    return specs


def outputs_option(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[str, ...] | None:
    """--outputs: output names checked against the writer registry; an old name is translated with a note."""
    from magcal_cli.writers import OUTPUT_ALIASES, WRITERS

    if value is None:
        return None
    names: list[str] = []
    for n in (v.strip() for v in value.split(",")):
        if n in OUTPUT_ALIASES:
            deprecated(ctx, f"--outputs {n} is deprecated: it is called {OUTPUT_ALIASES[n]} now (it writes "
                            f"{', '.join(_files(OUTPUT_ALIASES[n]))})")
            n = OUTPUT_ALIASES[n]
        if n and n not in names:
            names.append(n)
    bad = [n for n in names if n not in WRITERS]
    if bad or not names:
        msg = f"unknown output(s) {', '.join(bad) or '(none)'}; choose from {', '.join(WRITERS)}"
        raise click.BadParameter(msg)
    return tuple(names)


def _files(name: str) -> tuple[str, ...]:
    from magcal_cli.writers import get_writer

    return get_writer(name).files


def fail_on(command: str) -> Callable[[click.Context, click.Parameter, str | None], tuple[Any, ...]]:
    """--fail-on parsed against the metrics `command` measures (fit and batch: the fit's; check: its own)."""

    def parse(_: click.Context, __: click.Parameter, value: str | None) -> tuple[Any, ...]:
        from magcal_cli.errors import MagcalError
        from magcal_cli.firmware import gates

        if value is None:
            return ()
        if command == "check":
            from magcal_cli.firmware.check import METRICS
        else:
            from magcal_cli.firmware.metrics import METRICS
        try:
            return gates.parse(value, METRICS)
        except MagcalError as exc:
            raise click.BadParameter(str(exc).split(": ", 1)[-1], param_hint="--fail-on") from None

    return parse


def sampling(_: click.Context, __: click.Parameter, value: str | None) -> Sampling | None:
    """--imu-timing/--mag-timing as a Sampling, None to take the log format's own."""
    from magcal_cli.streams import Sampling

    return None if value is None else Sampling.parse(value)


def wmm_date(_: click.Context, __: click.Parameter, value: str | None) -> str | None:
    """--date YYYY-MM-DD checked, or a usage error."""
    from magcal_cli.errors import MagcalError
    from magcal_cli.wmm import parse_date

    try:
        return None if value is None else parse_date(value).isoformat()
    except MagcalError as exc:
        raise click.BadParameter(str(exc)) from None


# --- the table -----------------------------------------------------------------------------------------------------

#: what --imu-timing and --mag-timing take: Sampling's values (timing.CHOICES), spelled out so that the command line
#: starts without importing numpy (tests/test_timing.py checks they agree)
TIMING_CHOICES = ("instant", "preceding", "following")
TIMING_HELP = ("What each {what} sample stands for: instant (the value at its stamp), preceding (the mean over the "
               "interval that ends at its stamp{example}) or following (the mean over the interval that starts at "
               "it) [default: what the log's format defines, docs/timing.md].")
EFFECTS_HELP = ("Physics beyond the base model, repeatable and comma-separated (joint MAP; ekf-ml and ekf-aug carry "
                "current_interference and temperature_drift, ekf-ml also throttle_interference). auto: the mismatch "
                "diagnosis tests every effect the log can test and adds what it proves on held-out data; none: the "
                "base model only; or effect ids to model exactly (current_interference, throttle_interference, "
                "temperature_drift, time_offset, gyro_scale, accel_scale, lever_arm, nongravity_acceleration, "
                "transient_disturbance), each reported with its estimate, uncertainty, test and status.")


@dataclass(frozen=True)
class Shared:
    """One option several commands take: its spelling, its value and its meaning are the same in each of them.

    `names` and `dest` are click's declaration, `metavar` the value as --help shows it (None: a flag), `kind` the
    value's type in words, `meaning` one line for docs/cli.md, `commands` every command that takes it (the table
    test checks each of them declares it through `option`, and no other command does). `help` is the default help
    text; `{what}` in it is filled per command.
    """

    names: tuple[str, ...]
    dest: str
    metavar: str | None
    kind: str
    meaning: str
    commands: tuple[str, ...]
    help: str
    multiple: bool = False
    settings: dict[str, Any] = field(default_factory=dict)        # click's type, callback, default, ...


class SharedOption(click.Option):
    """A click option declared from `SHARED` (the table test recognises it by its `shared` key)."""

    def __init__(self, *args: Any, shared: str = "", **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.shared = shared


READS = ("fit", "diagnose", "check", "apply", "inspect")            # commands that read one log given by path
FITS = ("fit", "diagnose", "batch")                                   # commands that fit (timing options)
WINDOWED = ("fit", "diagnose", "check", "batch", "apply")             # commands that use a part of a log

SHARED: dict[str, Shared] = {
    "outdir": Shared(("-o", "--outdir"), "outdir", "DIR", "folder",
                     "the output: a folder, for commands that write several files",
                     ("fit", "diagnose", "batch"), "Output folder{what}.",
                     settings={"type": click.Path(path_type=Path), "callback": output_folder}),
    "output": Shared(("-o", "--output"), "out", "FILE|-", "file or '-'",
                     "the output: a file, for commands that write one; '-' is standard output",
                     ("apply", "export", "fleet"), "File to write{what} ('-': standard output).",
                     settings={"type": click.Path(dir_okay=False, allow_dash=True, path_type=Path)}),
    "log-output": Shared(("-o", "--output"), "out", "LOG", "file or ROS 2 bag folder",
                         "the output: the log simulate writes (its extension picks the format)", ("simulate",),
                         "The log to write; its extension picks the format{what}.",
                         settings={"type": click.Path(path_type=Path), "callback": log_output}),
    "mag": Shared(("--mag",), "mags", "ID[,ID...]|all", "stream ids",
                  "magnetometer stream ids as inspect prints them; repeatable and comma-separated",
                  ("fit", "diagnose", "check", "batch", "export", "apply"),
                  "Magnetometer stream id(s) to {what}; repeatable and comma-separated (e.g. --mag 'MAG[0],MAG[1]'), "
                  "or 'all' [default: all].", multiple=True, settings={"callback": mag_ids}),
    "format": Shared(("--format",), "fmt", "FORMAT", "format name",
                     "read the log as this format (a name inspect prints) instead of recognising it", READS,
                     "Read the log as this format instead of recognising it: a name magcal inspect prints (mcap, "
                     "rosbag, rosbag2, dataflash, px4log, ulog, csv, broad). A log that is not that format is an "
                     "error.", settings={"callback": log_format}),
    "start": Shared(("--start",), "start_s", "S", "seconds", "use the log from this time on (s from its start)",
                    WINDOWED, "Use {what} from this time on (s from its start).",
                    settings={"type": float, "callback": seconds}),
    "end": Shared(("--end",), "end_s", "S", "seconds", "use the log up to this time (s from its start)",
                  WINDOWED, "Use {what} up to this time (s from its start).",
                  settings={"type": float, "callback": seconds}),
    "effects": Shared(("--effects",), "effects", "auto|none|ID[,ID...]", "effect ids",
                      "the physics beyond the base model to fit; repeatable and comma-separated", ("fit", "batch"),
                      EFFECTS_HELP, multiple=True,
                      settings={"callback": effects_option, "default": AUTO}),
    "inject": Shared(("--effects",), "effects", "ID[:key=value,...]", "effect specs",
                     "the physics beyond the base model to simulate; repeatable and comma-separated", ("simulate",),
                     "{what}", multiple=True, settings={"callback": injected_effects}),
    "force": Shared(("--force",), "force", None, "flag", "overwrite existing outputs (refused without it, exit 2)",
                    ("fit", "diagnose", "batch", "simulate", "export", "apply", "fleet"),
                    "Overwrite existing outputs{what}.",
                    settings={"is_flag": True}),
    "json": Shared(("--json",), "as_json", None, "flag", "print one JSON document on stdout instead of text",
                   ("fit", "diagnose", "check", "batch", "inspect", "fleet"), "{what}", settings={"is_flag": True}),
    "strict": Shared(("--strict",), "strict", None, "flag",
                     "refuse a cut log instead of reading it up to its last complete record", ("fit", "batch"),
                     "Refuse a cut log (one that ends inside a record) instead of reading it up to its last complete "
                     "record with a warning.", settings={"is_flag": True}),
    "method": Shared(("--method",), "method", f"[{'|'.join(CHOICES)}]", "method name",
                     "the calibration method (auto: the best one the log allows)", ("fit", "batch"),
                     "Calibration method{what}.",
                     settings={"type": click.Choice(CHOICES), "default": "auto", "show_default": True}),
    "outputs": Shared(("--outputs",), "outputs", "NAME[,NAME...]", "output names",
                      "the files to write: json, yaml, report (report.txt), html (report.html), ardupilot, px4",
                      ("fit", "batch"),
                      "Comma-separated outputs{what}: json (calibration.json), yaml (calibration.yaml), report "
                      "(report.txt), html (report.html with plots), ardupilot (ardupilot.param), px4 (px4.params).",
                      settings={"callback": outputs_option}),
    "fail-on": Shared(("--fail-on",), "fail_on", "EXPR", "conditions",
                      "exit 3 when a magnetometer meets a condition (METRIC OP NUMBER, comma-separated; fleet: "
                      "compass states changed, settled, new)", ("fit", "check", "batch", "fleet"), "{what}"),
    "history": Shared(("--history",), "history", "DB", "SQLite file",
                      "record every result in this history store (created if absent; magcal fleet reads it)",
                      ("fit", "batch"), "Record every magnetometer's result in the history store DB (SQLite, "
                      "created if absent){what}; a log already recorded (same content) changes nothing. magcal "
                      "fleet DB reads it.", settings={"type": click.Path(dir_okay=False, path_type=Path)}),
    "vehicle": Shared(("--vehicle",), "vehicle", "NAME", "vehicle name",
                      "the vehicle the log comes from, instead of the one the log names", ("fit", "batch"),
                      "With --history: the vehicle{what} comes from, instead of the one the log names "
                      "(SYSID_THISMAV, PX4 sys_uuid, the ROS namespace or the log's folder)."),
    "calibration": Shared(("--calibration",), "cal_path", "CAL.json", "calibration document",
                          "a calibration document from magcal fit", ("diagnose", "check"), "{what}",
                          settings={"type": click.Path(exists=True, dir_okay=False, path_type=Path)}),
    "params": Shared(("--params",), "params_path", "FILE", "parameter file or log",
                     "the vehicle's parameters: a .param/.params file or a log", ("check", "export"), "{what}",
                     settings={"type": click.Path(exists=True, path_type=Path)}),
    "mag-timing": Shared(("--mag-timing",), "mag_timing", "[instant|preceding|following]", "sampling",
                         "what each magnetometer sample stands for", FITS,
                         TIMING_HELP.format(what="magnetometer", example=""),
                         settings={"type": click.Choice(TIMING_CHOICES), "callback": sampling}),
    "imu-timing": Shared(("--imu-timing",), "imu_timing", "[instant|preceding|following]", "sampling",
                         "what each gyro and accelerometer sample stands for", FITS,
                         TIMING_HELP.format(what="gyro and accelerometer",
                                            example=": PX4 sensor_combined, delta-angle IMUs"),
                         settings={"type": click.Choice(TIMING_CHOICES), "callback": sampling}),
    "quiet": Shared(("-q", "--quiet"), "quiet", None, "flag", "print nothing on stderr but errors",
                    ("fit", "diagnose", "check", "batch", "simulate", "inspect", "export", "apply", "fleet"),
                    "Print nothing on stderr but errors.", settings={"is_flag": True, "expose_value": False}),
    "verbose": Shared(("-v", "--verbose"), "verbose", None, "flag", "more detail on stderr; tracebacks of bugs",
                      ("fit", "diagnose", "check", "batch", "simulate", "inspect", "export", "apply", "fleet"),
                      "More detail on stderr; a traceback for internal errors.",
                      settings={"is_flag": True, "expose_value": False}),
}


@dataclass(frozen=True)
class Alias:
    """An old spelling kept working for scripts: hidden from --help, it leaves a one-line deprecation note."""

    name: str                  # the old option, e.g. --effect
    now: str                   # what to write instead
    commands: tuple[str, ...]


ALIASES: dict[str, Alias] = {
    "--effect": Alias("--effect", "--effects (the same ID[:key=value,...], repeatable)", ("simulate",)),
    "--allow-truncated": Alias("--allow-truncated", "nothing: a cut log is read up to its last complete record by "
                                                    "default (--strict refuses it)", ("fit",)),
}


def option(key: str, what: str = "", default_text: str = "", **settings: Any) -> Callable[[F], F]:
    """Declare the shared option `key` of `SHARED` on a command; `what` fills the help text's `{what}`,
    `default_text` says the default, and `settings` (help, default, callback, ...) adds to or replaces the table's
    click settings for this command."""
    entry = SHARED[key]
    text = entry.help.format(what=what) + (f" [default: {default_text}]." if default_text else "")
    kwargs: dict[str, Any] = {"help": text.replace(". [default", " [default"), "multiple": entry.multiple,
                              **entry.settings, **settings}
    if entry.metavar is not None and not isinstance(kwargs.get("type"), click.Choice):
        kwargs["metavar"] = entry.metavar
    return click.option(*entry.names, entry.dest, cls=SharedOption, shared=key, **kwargs)


def alias(name: str, dest: str, help_text: str, **settings: Any) -> Callable[[F], F]:
    """Declare the old spelling `name` of `ALIASES`: hidden, and it notes its deprecation when given."""
    entry = ALIASES[name]
    user = settings.pop("callback", None)

    def note(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        if value not in (None, False, ()):
            deprecated(ctx, f"{entry.name} is deprecated: use {entry.now}")
        return user(ctx, param, value) if user is not None else value

    return click.option(name, dest, hidden=True, callback=note, help=f"Deprecated: {help_text}", **settings)


def mag(what: str) -> Callable[[F], F]:
    """--mag ID[,ID...]|all on a command that selects magnetometers."""
    return option("mag", what)


def fmt(func: F) -> F:
    """--format on a command that reads a log."""
    return option("format")(func)


def force(help_text: str = "") -> Callable[[F], F]:
    """--force on a command that writes files; `help_text` replaces the table's help."""
    return option("force", **({"help": help_text} if help_text else {}))


def as_json(help_text: str) -> Callable[[F], F]:
    """--json on a command that can print a machine-readable document."""
    return option("json", what=help_text)


def window(what: str = "the log") -> Callable[[F], F]:
    """--start S and --end S on a command that uses a part of a log (`what`: the part's noun in the help)."""

    def decorate(func: F) -> F:
        return option("start", what)(option("end", what)(func))

    return decorate


def timing(func: F) -> F:
    """The --imu-timing and --mag-timing options of every command that fits."""
    return option("mag-timing")(option("imu-timing")(func))
