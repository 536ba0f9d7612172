"""Output writers behind one registry: each turns a RunResult into files in an output directory."""

from __future__ import annotations

import contextlib
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Protocol

from magcal_cli.errors import OutputError
from magcal_cli.registry import resolve

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult


class Writer(Protocol):
    """Writes its files (named in `files`) atomically and returns their paths."""

    name: ClassVar[str]
    files: ClassVar[tuple[str, ...]]

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Write this writer's outputs into `outdir`."""
        ...


#: output name (as in --outputs) -> "module:Class" or the class itself
WRITERS: dict[str, str | type[Writer]] = {
    "json": "magcal_cli.writers.calfile:JsonWriter",
    "yaml": "magcal_cli.writers.calfile:YamlWriter",
    "report": "magcal_cli.writers.report.text:TextReport",
    "html": "magcal_cli.writers.report.html:HtmlReport",
    "ardupilot": "magcal_cli.writers.ardupilot:ArduPilotWriter",
    "px4": "magcal_cli.writers.px4:Px4Writer",
}
#: old output names -> today's (still accepted; the command line notes the change): `plots` wrote report.html
OUTPUT_ALIASES: dict[str, str] = {"plots": "html"}

DEFAULT_OUTPUTS = ("json", "yaml", "report", "html")
#: Recording.format -> the firmware output fit adds when --outputs is not given (the vehicle takes these)
FIRMWARE_OUTPUTS = {"dataflash": "ardupilot", "ulog": "px4"}


def get_writer(name: str) -> Writer:
    """Instantiate the writer registered as `name` (or an old name of it, OUTPUT_ALIASES)."""
    target = WRITERS.get(OUTPUT_ALIASES.get(name, name))
    if target is None:
        msg = f"--outputs: unknown output {name!r}; available: {', '.join(WRITERS)}"
        raise OutputError(msg)
    return resolve(target, f"the {name} output")()  # type: ignore[no-any-return]


def check_targets(outdir: Path, names: list[str], force: bool) -> None:
    """Refuse (OutputError) when an output file exists already and --force was not given."""
    if outdir.exists() and not outdir.is_dir():
        msg = f"{outdir}: exists and is not a directory. Choose another -o"
        raise OutputError(msg)
    if force:
        return
    for name in names:
        cls = WRITERS[OUTPUT_ALIASES.get(name, name)]
        files = cls.files if not isinstance(cls, str) else get_writer(name).files
        for f in files:
            if (outdir / f).exists():
                msg = f"{outdir / f}: exists already. Pass --force to overwrite it, or choose another -o"
                raise OutputError(msg)


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) back while the block runs; it is delivered, as KeyboardInterrupt, right after."""
    main = threading.current_thread() is threading.main_thread() and hasattr(signal, "pthread_sigmask")
    if main:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if main:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def write_outputs(result: RunResult, outdir: Path, names: list[str],
                  then: Callable[[list[Path]], None] | None = None) -> list[Path]:
    """Write every output named in `names` to `outdir` all together or not at all.

    Files are written into a staging directory inside `outdir` and renamed into place in one step with Ctrl-C
    held back, so an error or an interrupt leaves `outdir` as it was (a directory created for the run is
    removed again when it stays empty). `then` runs on the final paths in the same step (batch marks the
    outputs complete there: a Ctrl-C cannot fall between them).
    """
    created = not outdir.exists()
    done = False
    stage: Path | None = None
    try:                                  # a Ctrl-C right after mkdtemp still removes the staging directory
        try:
            outdir.mkdir(parents=True, exist_ok=True)
            stage = Path(tempfile.mkdtemp(prefix=".magcal-", suffix=".part", dir=outdir))
        except OSError as exc:
            msg = f"{outdir}: cannot create the output directory ({exc.strerror or exc}). Choose another -o"
            raise OutputError(msg) from None
        writers = [get_writer(name) for name in names]
        # the reports' provenance lists every file of the run, its own among them
        result = replace(result, outputs=tuple(dict.fromkeys(f for w in writers for f in w.files)))
        staged = [p for w in writers for p in w.write(result, stage)]
        with _sigint_deferred():
            final = []
            for p in staged:
                target = outdir / p.relative_to(stage)
                target.parent.mkdir(parents=True, exist_ok=True)
                p.replace(target)
                final.append(target)
            done = True
            if then is not None:
                then(final)
        return final
    except OSError as exc:
        msg = f"{outdir}: cannot write the outputs ({exc.strerror or exc}). Check the directory's permissions"
        raise OutputError(msg) from None
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        if created and not done:
            with contextlib.suppress(OSError):
                outdir.rmdir()                   # only when empty: nothing of ours or anyone else's is lost
