"""Output writers behind one registry: each turns a RunResult into files in an output directory."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Protocol

from ..errors import OutputError

if TYPE_CHECKING:
    from ..pipeline import RunResult


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
    "report": "magcal_cli.writers.report:TextReport",
    "plots": "magcal_cli.writers.plots:HtmlReport",
    "ardupilot": "magcal_cli.writers.ardupilot:ArduPilotWriter",
    "px4": "magcal_cli.writers.px4:Px4Writer",
}

DEFAULT_OUTPUTS = ("json", "yaml", "report", "plots")
#: Recording.format -> the firmware output fit adds when --outputs is not given (the vehicle takes these)
FIRMWARE_OUTPUTS = {"dataflash": "ardupilot", "ulog": "px4"}


def get_writer(name: str) -> Writer:
    """Instantiate the writer registered as `name`."""
    target = WRITERS.get(name)
    if target is None:
        msg = f"--outputs: unknown output {name!r}; available: {', '.join(WRITERS)}"
        raise OutputError(msg)
    if isinstance(target, str):
        module, cls = target.split(":")
        target = getattr(importlib.import_module(module), cls)
    return target()  # type: ignore[operator,return-value,no-any-return]


def check_targets(outdir: Path, names: list[str], force: bool) -> None:
    """Refuse (OutputError) when an output file exists already and --force was not given."""
    if outdir.exists() and not outdir.is_dir():
        msg = f"{outdir}: exists and is not a directory. Choose another -o"
        raise OutputError(msg)
    if force:
        return
    for name in names:
        cls = WRITERS[name]
        files = cls.files if not isinstance(cls, str) else get_writer(name).files
        for f in files:
            if (outdir / f).exists():
                msg = f"{outdir / f}: exists already. Pass --force to overwrite it, or choose another -o"
                raise OutputError(msg)
