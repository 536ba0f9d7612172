"""The calibration document as calibration.json and calibration.yaml."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from magcal_cli.atomic import write_text
from magcal_cli.calibration.document import dumps_json, dumps_yaml

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult


class JsonWriter:
    """calibration.json (the machine-readable document)."""

    name: ClassVar[str] = "json"
    files: ClassVar[tuple[str, ...]] = ("calibration.json",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Write the document as JSON."""
        return [write_text(outdir / self.files[0], dumps_json(result.calibration))]


class YamlWriter:
    """calibration.yaml (the same content as the JSON, for people and ROS parameter tooling)."""

    name: ClassVar[str] = "yaml"
    files: ClassVar[tuple[str, ...]] = ("calibration.yaml",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Write the document as YAML."""
        return [write_text(outdir / self.files[0], dumps_yaml(result.calibration))]
