"""A simulated vehicle's compass for one flight, from a vehicle file (`magcal simulate --vehicle FILE`).

A fleet simulation writes one small JSON file per flight, so a vehicle's hard iron, soft iron, orientation and
interference can step between flights (benchmarks/fleet.py). Every key is optional:

    {"sysid": 7,                              SYSID_THISMAV in a .bin's parameter dump
     "serial": 0,                             BRD_SERIAL_NUM there
     "board_id": "fmuv3 002F001F 33375111 37353832",   the board's boot message: name and processor unique id
     "start_utc": 1763700000.0,               the log's start (Unix s): flights are ordered by it
     "hard_iron_uT": [1.2, -0.5, 0.3],        o
     "soft_iron": [[1.02, 0.01, 0], ...],     the symmetric factor of D over the field strength (3x3)
     "orientation_deg": [0.5, -1.0, 2.0],     the compass's rotation from the IMU frame (roll, pitch, yaw)
     "interference_uT_per_A": [0.3, 0, -0.1]} current interference c (the current_interference effect)

The truth is D = R(orientation) S F with F the World Magnetic Model's field strength at the simulated place,
as the calibration document decomposes it (D = U P: U the misalignment, P / F the soft iron); keys left out
keep the values the seed draws.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from magcal_cli import so3
from magcal_cli.errors import MagcalError
from magcal_cli.readers.dataflash.ardupilot import board_info
from magcal_cli.streams import FloatArray
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.truth import PAPER_FIELD, Truth, at_home, draw_truth

KEYS = ("sysid", "serial", "board_id", "start_utc", "hard_iron_uT", "soft_iron", "orientation_deg",
        "interference_uT_per_A")


class VehicleFileError(MagcalError):
    """A vehicle file that cannot be used."""


@dataclass(frozen=True, eq=False)
class Vehicle:
    """One flight's compass truth and identity; None: the seed's draw (or nothing written)."""

    sysid: int | None = None
    start_utc: float | None = None
    hard_iron_t: FloatArray | None = None          # (3,) tesla
    soft_iron: FloatArray | None = None            # (3, 3) symmetric, unitless
    orientation_rad: FloatArray | None = None      # (3,) roll, pitch, yaw
    interference_t_per_a: FloatArray | None = None  # (3,) tesla per ampere
    serial: int | None = None                      # BRD_SERIAL_NUM
    board_id: str | None = None                    # a MSG line "NAME XXXXXXXX XXXXXXXX XXXXXXXX"

    def truth(self, seed: int, rate: float, mag_rate: float) -> Truth | None:
        """The seed's vehicle truth (as simulate draws it) with this file's D and o; None when it sets neither."""
        if self.hard_iron_t is None and self.soft_iron is None and self.orientation_rad is None:
            return None
        raw = draw_truth(np.random.default_rng(seed), rate, mag_rate)
        drawn = at_home(raw)
        u, p = so3.polar(drawn.D)
        field = PAPER_FIELD * float(np.linalg.norm(drawn.D) / np.linalg.norm(raw.D))   # the WMM's, as at_home sets it
        if self.orientation_rad is not None:
            u = so3.from_rpy(self.orientation_rad)
        if self.soft_iron is not None:
            p = self.soft_iron * field
        o = drawn.o if self.hard_iron_t is None else self.hard_iron_t
        return replace(drawn, D=u @ p, o=np.array(o, dtype=np.float64))

    def effects(self) -> tuple[EffectSpec, ...]:
        """The current_interference effect this file sets, if any."""
        if self.interference_t_per_a is None:
            return ()
        return (EffectSpec("current_interference", {"c": tuple(float(v) for v in self.interference_t_per_a)}),)

    def params(self) -> dict[str, float]:
        """Firmware parameters the written log carries (SYSID_THISMAV, BRD_SERIAL_NUM)."""
        return ({} if self.sysid is None else {"SYSID_THISMAV": float(self.sysid)}) | (
            {} if self.serial is None else {"BRD_SERIAL_NUM": float(self.serial)})


def _vector(doc: dict[str, Any], key: str, where: str, scale: float = 1.0) -> FloatArray | None:
    """A 3-vector of finite numbers, times `scale`."""
    if key not in doc:
        return None
    v = np.asarray(doc[key], dtype=np.float64) if _numbers(doc[key], 3) else None
    if v is None or v.shape != (3,) or not np.all(np.isfinite(v)):
        msg = f"{where}: {key} must be a list of 3 numbers, got {doc[key]!r}"
        raise VehicleFileError(msg)
    return v * scale


def _numbers(value: Any, n: int) -> bool:
    """A flat list of n numbers."""
    return isinstance(value, list) and len(value) == n and all(isinstance(x, int | float) for x in value)


def _soft(doc: dict[str, Any], where: str) -> FloatArray | None:
    """The soft-iron matrix: 3x3, symmetric, positive definite."""
    if "soft_iron" not in doc:
        return None
    raw = doc["soft_iron"]
    if not (isinstance(raw, list) and len(raw) == 3 and all(_numbers(row, 3) for row in raw)):
        msg = f"{where}: soft_iron must be a 3x3 list of numbers, got {raw!r}"
        raise VehicleFileError(msg)
    s = np.asarray(raw, dtype=np.float64)
    if not np.allclose(s, s.T, atol=1e-12) or np.any(np.linalg.eigvalsh(s) <= 0):
        msg = f"{where}: soft_iron must be symmetric positive definite (the factor P of D = U P over the field)"
        raise VehicleFileError(msg)
    return s


def load(path: Path) -> Vehicle:
    """Read a vehicle file; a VehicleFileError says which key is wrong."""
    where = str(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        msg = f"{where}: cannot read the vehicle file ({exc}). Give a JSON object, see docs/fleet.md"
        raise VehicleFileError(msg) from None
    if not isinstance(doc, dict):
        msg = f"{where}: a vehicle file is a JSON object with the keys {', '.join(KEYS)}"
        raise VehicleFileError(msg)
    unknown = sorted(set(doc) - set(KEYS))
    if unknown:
        msg = f"{where}: unknown key {unknown[0]!r}; valid keys: {', '.join(KEYS)}"
        raise VehicleFileError(msg)
    sysid = doc.get("sysid")
    if sysid is not None and not (isinstance(sysid, int) and 1 <= sysid <= 255):
        msg = f"{where}: sysid must be an integer 1..255 (SYSID_THISMAV), got {sysid!r}"
        raise VehicleFileError(msg)
    serial, board = doc.get("serial"), doc.get("board_id")
    if serial is not None and not (isinstance(serial, int) and 0 <= serial < 2**31):
        msg = f"{where}: serial must be an integer 0..2147483647 (BRD_SERIAL_NUM), got {serial!r}"
        raise VehicleFileError(msg)
    if board is not None and not (isinstance(board, str) and board_info([board])):
        msg = (f"{where}: board_id must be a board's boot message, a name and three 8-digit hex words such as "
               f"'fmuv3 002F001F 33375111 37353832', got {board!r}")
        raise VehicleFileError(msg)
    start = doc.get("start_utc")
    if start is not None and not (isinstance(start, int | float) and np.isfinite(start) and start > 0):
        msg = f"{where}: start_utc must be a Unix time in seconds, got {start!r}"
        raise VehicleFileError(msg)
    orient = _vector(doc, "orientation_deg", where)
    return Vehicle(sysid, None if start is None else float(start), _vector(doc, "hard_iron_uT", where, 1e-6),
                   _soft(doc, where), None if orient is None else np.deg2rad(orient),
                   _vector(doc, "interference_uT_per_A", where, 1e-6), serial, board)


def flight(sim: Any, vehicle: Vehicle) -> Any:
    """The Simulation as this vehicle logs it: its SYSID_THISMAV and BRD_SERIAL_NUM in the parameter dump, its
    board's boot message, its start time."""
    from magcal_cli.synth.firmware import PreviousCalibration

    boot = (vehicle.board_id,) if vehicle.board_id else ()
    if vehicle.params() or boot:
        prev = sim.previous or PreviousCalibration()
        sim = replace(sim, previous=replace(prev, extra_params={**prev.extra_params, **vehicle.params()},
                                            messages=prev.messages + boot))
    if vehicle.start_utc is not None:
        sim = replace(sim, recording=replace(sim.recording, t0=vehicle.start_utc))
    return sim
