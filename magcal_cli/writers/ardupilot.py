"""ardupilot.param: COMPASS_* parameters in Mission Planner's NAME,VALUE layout (firmware.ardupilot)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from magcal_cli.atomic import write_text
from magcal_cli.firmware.common import Options
from magcal_cli.firmware.export import export
from magcal_cli.firmware.paramfile import render

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult


class ArduPilotWriter:
    """ardupilot.param, for the vehicle whose log was calibrated (its parameters pick slots and rotations)."""

    name: ClassVar[str] = "ardupilot"
    files: ClassVar[tuple[str, ...]] = ("ardupilot.param",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Export every magnetometer and write the file."""
        exp = export(result.calibration, "ardupilot", dict(result.recording.params), Options(skip_refused=True))
        text = render(exp.params, "mission-planner", exp.header(), exp.integers)
        return [write_text(outdir / self.files[0], text)]
