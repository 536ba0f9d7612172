"""Parameter files: Mission Planner `.param`, MAVProxy, QGroundControl `.params` and PX4 `param set` lines.

Layouts compared with (docs/firmware-export.md): Mission Planner `ParamFile.cs` (`NAME,VALUE`, sorted by name,
`#` lines skipped on load), WebTools MAGFit.param (`NAME,VALUE`), MAVProxy (`NAME VALUE`), the QGroundControl
"Parameters File Format" page (`# Vehicle-Id Component-Id Name Value Type`, tab-separated, MAV_PARAM_TYPE),
PX4 mag_compensation.py (`param set NAME VALUE`). Values are float32 in both firmwares, so floats are written
with the fewest digits that read back as the same float32 (as WebTools' param_to_string does).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from magcal_cli.firmware import FirmwareError

#: MAV_PARAM_TYPE values written in QGC files
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
STYLES = ("mission-planner", "mavproxy", "qgc", "nsh")
_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,15}$")


def value_text(value: float, integer: bool = False) -> str:
    """The value as written: an integer, or the shortest decimal that reads back as the same float32."""
    if integer:
        return str(int(round(value)))
    text = np.format_float_positional(np.float32(value), unique=True, trim="-")
    return "0" if text in ("-0", "0") else text


def as_float32(value: float) -> float:
    """The value the firmware stores (float32), as a Python float."""
    return float(np.float32(value))


def render(params: Mapping[str, float], style: str, header: Iterable[str] = (),
           integers: Iterable[str] = ()) -> str:
    """The parameters in one of STYLES, sorted by name, after `#` header lines."""
    ints = set(integers)
    names = sorted(params)
    head = [f"# {h}".rstrip() for h in header]
    if style == "mission-planner":
        body = [f"{n},{value_text(params[n], n in ints)}" for n in names]
    elif style == "mavproxy":
        body = [f"{n:<16} {value_text(params[n], n in ints)}" for n in names]
    elif style == "qgc":
        head = ["# Onboard parameters for Vehicle 1", "#", *head, "#", "# Vehicle-Id Component-Id Name Value Type"]
        body = [f"1\t1\t{n}\t{value_text(params[n], n in ints)}\t"
                f"{MAV_PARAM_TYPE_INT32 if n in ints else MAV_PARAM_TYPE_REAL32}" for n in names]
    elif style == "nsh":
        body = [f"param set {n} {value_text(params[n], n in ints)}" for n in names]
    else:
        msg = f"parameter file style {style!r} is not known; use one of {', '.join(STYLES)}"
        raise FirmwareError(msg)
    return "\n".join(head + body) + "\n"


def parse(text: str, where: str) -> dict[str, float]:
    """Parameters from any of STYLES (the style is recognised per line); `#` lines and blank lines are skipped."""
    out: dict[str, float] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f for f in re.split(r"[\s,]+", line) if f]
        if fields[:2] == ["param", "set"]:
            fields = fields[2:]
        elif len(fields) == 5 and fields[0].isdigit() and fields[1].isdigit():
            fields = fields[2:4]                        # QGC: vehicle, component, name, value, type
        name = fields[0] if fields else ""
        try:
            if len(fields) != 2 or not _NAME.match(name):
                raise ValueError
            out[name] = float(fields[1])
        except ValueError:
            msg = (f"{where}: line {number} is not a parameter ({line[:60]!r}); expected NAME,VALUE (Mission "
                   "Planner), NAME VALUE (MAVProxy), QGroundControl's five tab-separated columns or 'param set "
                   "NAME VALUE'")
            raise FirmwareError(msg) from None
    return out


def load(path: Path) -> dict[str, float]:
    """Read a parameter file (any of STYLES)."""
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        msg = f"{path}: cannot read the parameter file ({exc.strerror or exc}). Check the path"
        raise FirmwareError(msg) from None
    params = parse(text, str(path))
    if not params:
        msg = f"{path}: no parameters in the file. Save the vehicle's parameters from the ground station again"
        raise FirmwareError(msg)
    return params
