"""What the driver exports share: the one magnetometer to write, the correction in the driver's unit, the YAML and
the header that says what the driver cannot hold."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from magcal_cli import so3
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.firmware import FirmwareError
from magcal_cli.firmware.common import correction
from magcal_cli.streams import FloatArray


@dataclass(frozen=True)
class DriverFile:
    """A driver's parameter file: its text and the lines `export` also prints."""

    driver: str
    mag_id: str
    text: str
    not_held: tuple[str, ...] = ()


def pick(cal: Calibration, mag_ids: Sequence[str], driver: str) -> MagCalibration:
    """The one magnetometer to export: --mag's, or the document's only one; a refused compass is an error."""
    refused = {str(r.get("id")): r for r in cal.refused}
    ids = [m.id for m in cal.magnetometers]
    if len(mag_ids) > 1:
        msg = (f"export --driver {driver}: a driver file holds one magnetometer, but --mag gives {len(mag_ids)} "
               f"({', '.join(mag_ids)}); export them one at a time")
        raise FirmwareError(msg)
    if mag_ids and mag_ids[0] in refused:
        why = refused[mag_ids[0]].get("reason") or "no method could calibrate it"
        msg = (f"export --driver {driver}: {mag_ids[0]} was refused ({why}), so it has no calibration to export; "
               f"choose --mag {' or '.join(ids) if ids else 'another compass'}, or record it again")
        raise FirmwareError(msg)
    if mag_ids:
        return cal.magnetometer(mag_ids[0])
    if not ids:
        names = ", ".join(refused) or "none"
        msg = (f"export --driver {driver}: the document has no calibrated magnetometer (refused: {names}); "
               "record the compass again and run magcal fit")
        raise FirmwareError(msg)
    if len(ids) > 1:
        msg = (f"export --driver {driver}: the document has {len(ids)} magnetometers ({', '.join(ids)}); "
               f"choose one with --mag {ids[0]}")
        raise FirmwareError(msg)
    return cal.magnetometers[0]


def in_unit(mag: MagCalibration, unit: str) -> tuple[FloatArray, FloatArray, float]:
    """(S, h, F) in `unit` with S (y - h) the body-frame field of strength F for readings y in `unit`.

    From m_b = A (y_doc - o) and y = k y_doc: F m_b = (F A) (y - k o), F in `unit` = k field_strength.
    """
    s, h, k = correction(mag, unit)
    return s, h, k * mag.field_strength


def held_line(mag: MagCalibration) -> str:
    """The header line for a driver that holds a full 3x3 and the offset: nothing of D or o is lost."""
    angle = float(np.degrees(np.linalg.norm(so3.log(so3.polar(mag.D)[0]))))
    return (f"held exactly: the full 3x3 (iron, scale and the {angle:.2f} deg misalignment to the IMU) and the "
            "offset; nothing of D or o is lost")


def num(x: float) -> str:
    """A float as YAML reads it back exactly (shortest repr), always with a '.': YAML 1.1 (PyYAML, ROS 1) reads
    1e-05 as a string."""
    text = repr(float(x))
    mantissa, e, exponent = text.partition("e")
    return text if "." in mantissa or not e else f"{mantissa}.0e{exponent}"


def vector(xs: FloatArray) -> str:
    """A YAML flow sequence of floats."""
    return "[" + ", ".join(num(x) for x in np.ravel(xs)) + "]"


def not_held(cal: Calibration, mag: MagCalibration, driver: str) -> list[str]:
    """What `driver` cannot hold of this calibration: the effects it carries, the IMU's own calibration and the
    parameters a partial calibration held at a prior."""
    from magcal_cli.effects.correct import terms

    lines = [f"effect {eff.id} ({entry.get('status')}) is not held: {driver} has no parameter for it; "
             "`magcal apply` removes it from logged readings" for entry, eff in terms(cal.effects, mag.id)]
    lines.append("the gyroscope and accelerometer calibration (document's imu) is not written: this file holds the "
                 "magnetometer correction only")
    held = [str(h.get("parameter")) for h in mag.held]
    if held:
        lines.append(f"the log did not determine {', '.join(held)}: written at the prior magcal held them at")
    return lines


def header(cal: Calibration, mag: MagCalibration, driver: str, formula: list[str], notes: list[str]) -> str:
    """The file's comment block: origin, the driver's formula, then what it cannot hold."""
    lines = [f"magcal {driver} parameters for {mag.id} from {cal.source.path or 'a calibration document'}",
             *formula, *notes, *(f"NOT HELD: {line}" for line in not_held(cal, mag, driver))]
    return "".join(f"# {line}\n" for line in lines)


def ros2_params(values: dict[str, str], node: str = "/**") -> str:
    """A ROS 2 parameter file (`--ros-args --params-file`): `node: ros__parameters: name: value`."""
    body = "".join(f"    {name}: {value}\n" for name, value in values.items())
    return f"{node}:\n  ros__parameters:\n{body}"

