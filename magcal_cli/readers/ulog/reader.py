"""PX4 ULog reader: raw `sensor_mag` per instance, the IMU, attitude, battery, throttle, GPS and parameters.

Which topic is raw and which calibrated, frames, time stamps, ids and the truncation policy are in
docs/readers-px4.md; field meanings follow PX4's msg/*.msg definitions.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from magcal_cli import units
from magcal_cli.align import clean_time, onto
from magcal_cli.errors import LogReadError, StreamError
from magcal_cli.readers import ReadOptions
from magcal_cli.readers.checks import nan_throughout, normalised_field, normalised_note, sensor_checks
from magcal_cli.readers.cut import mark_cut, refuse_if_strict
from magcal_cli.readers.ulog.load import Loaded, load_ulog
from magcal_cli.readers.ulog.sensors import imu_pieces, mag_pieces
from magcal_cli.readers.ulog.topics import ImuPiece, Piece, Topics
from magcal_cli.readers.ulog.vehicle import motor_pieces, other_pieces, utc_of_boot
from magcal_cli.streams import Cut, Kind, Recording, Stream

#: the topics magcal reads; pyulog skips the others while parsing
TOPICS = ["sensor_mag", "sensor_combined", "sensor_accel", "sensor_gyro", "vehicle_attitude",
          "battery_status", "vehicle_gps_position", "sensor_gps", "vehicle_magnetometer",
          "vehicle_thrust_setpoint", "actuator_controls_0", "actuator_motors", "actuator_outputs"]


def _number(value: Any) -> float | None:
    """A parameter value as a float, or None when it is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        return None


def _params(ulog: Any, notes: list[str]) -> dict[str, float]:
    """Initial parameters updated by every change logged during the flight (last value wins)."""
    params = {str(k): v for k, v in ((k, _number(v)) for k, v in ulog.initial_parameters.items()) if v is not None}
    changed: set[str] = set()
    bad = len(ulog.initial_parameters) - len(params)
    for _, name, raw in ulog.changed_parameters:
        value = _number(raw)
        if value is None:                     # a parameter message found while resynchronising on corrupt bytes
            bad += 1
            continue
        if str(name).startswith("CAL_MAG") and params.get(str(name)) != value:
            changed.add(str(name))
        params[str(name)] = value
    if bad:
        notes.append(f"ignored {bad} parameter values that are not numbers (corrupt data)")
    if changed:
        names = ", ".join(sorted(changed))
        notes.append(f"magnetometer calibration parameters changed during the log ({names}); params hold the "
                     "last values")
    return params


class UlogReader:
    """Reads PX4 ULog (`.ulg`) files with pyulog into SI streams; see docs/readers-px4.md."""

    name: ClassVar[str] = "ulog"

    def read(self, path: Path, options: ReadOptions) -> Recording:
        """Every stream magcal uses; a cut file up to its last complete message (--strict refuses it)."""
        loaded = load_ulog(path, TOPICS)
        ulog = loaded.ulog
        tp = Topics(loaded, path, options)
        self._check_damage(path, loaded, options, tp.notes)
        params = _params(ulog, tp.notes)
        mags = mag_pieces(tp, params)
        imus, temps = imu_pieces(tp, params)
        pieces = mags + temps + other_pieces(tp) + motor_pieces(tp, params)
        if not imus and not pieces:
            have = ", ".join(loaded.topics[:25]) + (", ..." if len(loaded.topics) > 25 else "")
            msg = (f"{path}: no topic magcal reads ({', '.join(TOPICS)}); the log has: "
                   f"{have or 'no topics'}. Log sensor_mag and sensor_combined (PX4's default profile does)")
            raise StreamError(msg)
        if not mags:
            tp.notes.append("no magnetometer topic (sensor_mag, sensor_combined.magnetometer_ga or "
                            f"vehicle_magnetometer); the log has: {', '.join(loaded.topics)}")
        firsts = [int(p.t_us[0]) for p in pieces if len(p.t_us)]
        firsts += [int(p.t_us[0]) for imu in imus for p in (imu.gyr, imu.acc) if len(p.t_us)]
        t0_us = min([int(ulog.start_timestamp), *firsts])
        streams = [s for imu in imus for s in _imu_streams(imu, t0_us, tp.notes)]
        for p in pieces:
            stream = _stream(p, t0_us, tp.notes)
            if stream is not None:
                streams.append(stream)
        if ulog.dropouts:
            lost = sum(int(d.duration) for d in ulog.dropouts)
            times = "once" if len(ulog.dropouts) == 1 else f"{len(ulog.dropouts)} times"
            tp.notes.append(f"the logger dropped data {times} ({lost} ms in total); samples are missing "
                            "there")
        boot = utc_of_boot(tp)
        return mark_cut(Recording(path, "ulog", tuple(streams), t0=t0_us * 1e-6, params=params,
                                  notes=tuple(tp.notes), utc0=None if boot is None else boot + t0_us * 1e-6),
                        _cut(loaded))

    @staticmethod
    def _check_damage(path: Path, loaded: Loaded, options: ReadOptions, notes: list[str]) -> None:
        """Raise for a file without decodable data, and for a cut one with --strict; note corrupt data."""
        ulog = loaded.ulog
        kept = sum(len(d.data["timestamp"]) for d in ulog.data_list if "timestamp" in d.data)
        if not ulog.data_list and not loaded.topics:
            if loaded.cut_at is not None and ulog.message_formats:      # definitions were read, then it ends
                msg = (f"{path}: the ULog is truncated at byte {loaded.cut_at} of {loaded.size}, before any "
                       "data message. Re-copy the log from the vehicle")
            else:
                msg = (f"{path}: no data messages could be decoded after the ULog header (the file is "
                       "corrupt or not a PX4 log). Re-copy the log from the vehicle")
            raise LogReadError(msg)
        refuse_if_strict(path, options, _cut(loaded))
        if ulog.file_corruption:          # corrupt bytes in the middle: skipped, as pymavlink does (issue 6)
            notes.append(f"corrupt data: pyulog skipped damaged bytes and resynchronised on the next message; "
                         f"read {kept} complete samples")
        notes.extend(f"pyulog: {line}" for line in loaded.printed[:3])


def _cut(loaded: Loaded) -> Cut | None:
    """Where a ULog ends inside a message (pyulog stops at the last complete one), or None."""
    if loaded.cut_at is None:
        return None
    return Cut(loaded.cut_at, loaded.size, f"a message, {loaded.size - loaded.cut_at} bytes present")


def _stream(p: Piece, t0_us: int, notes: list[str]) -> Stream | None:
    """Sort, de-duplicate and clean one piece into a Stream relative to t0; None when nothing is left."""
    label = p.source.split("#", 1)[-1].split(":", 1)[0]
    dead = nan_throughout((p.t_us - t0_us) * 1e-6, p.values, label) if p.kind is Kind.MAGNETOMETER else None
    if dead is not None:
        notes.extend(dead[2])
        return Stream(p.kind, p.id, dead[0], dead[1], p.source, p.unit, sampling=p.sampling, window_s=p.window_s)
    t, values, cleaned = clean_time((p.t_us - t0_us) * 1e-6, p.values, label)
    t, values, checked = sensor_checks((p.kind,), t, values, label)
    notes.extend(cleaned + checked)
    if not len(t):
        notes.append(f"{label}: no valid {p.kind.value} samples")
        return None
    if p.kind is Kind.MAGNETOMETER and normalised_field(values):
        notes.append(normalised_note(p.id, values / units.to_si(p.unit), p.unit))
    return Stream(p.kind, p.id, t, values, p.source, p.unit, sampling=p.sampling, window_s=p.window_s)


def _imu_streams(imu: ImuPiece, t0_us: int, notes: list[str]) -> list[Stream]:
    """Accelerometer and gyro on the gyro's time stamps: the accelerometer is interpolated onto them when
    its own stamps differ (align.onto never extrapolates or bridges dropouts)."""
    gyr, acc = _stream(imu.gyr, t0_us, notes), _stream(imu.acc, t0_us, notes)
    if gyr is None or acc is None:
        return []
    if len(gyr) == len(acc) and np.array_equal(gyr.t, acc.t):
        return [acc, gyr]
    mask, values = onto(acc, gyr.t)
    if not mask.any():
        notes.append(f"{imu.id}: accelerometer and gyro samples do not overlap in time; not usable as an "
                     "IMU")
        return []
    notes.append(f"{imu.id}: accelerometer interpolated onto the gyro's time stamps")
    if not mask.all():
        notes.append(f"{imu.id}: {int((~mask).sum())} of {len(gyr)} gyro epochs have no accelerometer "
                     "samples on both sides and were dropped")
    t = gyr.t[mask]
    return [replace(acc, t=t, values=values), replace(gyr, t=t, values=gyr.values[mask])]
