"""`magcal apply`: a calibration applied to a log, the calibrated field over time as CSV.

Each row is one magnetometer sample: time (s, the log's stream time), stream id, the calibrated body-frame
field F A (y - o - terms) in the document's unit and its magnitude. Every magnetometer effect the calibration
carries (accepted, or ambiguous with an estimate: effects/correct.py; interference, temperature drift, time
offset, ...) is removed by its plug-in's `correct` when the log has the channels it needs (calibration-file.md).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.types import Calibration, MagCalibration
from magcal_cli.effects.correct import Channels, remove
from magcal_cli.errors import StreamError
from magcal_cli.streams import FloatArray, Kind, Recording, Sampling
from magcal_cli.timing import CHOICES, as_instants, stated

#: how the CSV header names each document unit (the CSV input contract's spellings)
SHORT = {"tesla": "T", "millitesla": "mT", "microtesla": "uT", "nanotesla": "nT", "gauss": "G",
         "milligauss": "mG"}


def calibrated(cal: Calibration, mag: MagCalibration, t: FloatArray, y: FloatArray,
               channels: Channels | Mapping[str, FloatArray]) -> tuple[FloatArray, FloatArray, list[str]]:
    """(stamps, calibrated field F A (y - o - terms) (N, 3) in the document's unit, notes) of `mag`'s readings y
    (N, 3, document unit) at t (N,) s: the one correction `magcal apply` and `magcal_cli.api.apply` share.
    `channels`: where the effects' channels are (`effects.correct.remove`)."""
    t, y, notes = remove(cal.effects, mag.id, channels, t, y)
    return t, mag.field_strength * mag.apply(y), notes


def apply_rows(cal: Calibration, rec: Recording, mag_ids: list[str] | None = None
               ) -> tuple[list[tuple[float, str, FloatArray]], str, list[str]]:
    """(rows (t, id, field) sorted by time then id, the CSV's unit name, notes): the calibrated field of every
    document magnetometer found in `rec`, unrounded."""
    mags = [cal.magnetometer(m) for m in mag_ids] if mag_ids else list(cal.magnetometers)
    have = {s.id for s in rec.of_kind(Kind.MAGNETOMETER)}
    missing = [m.id for m in mags if m.id not in have]
    if len(missing) == len(mags):
        msg = (f"{rec.path.name}: none of the calibration's magnetometers ({', '.join(missing)}) is in the log; "
               f"it has {', '.join(sorted(have)) or 'none'}. Apply the calibration to the log it was made from")
        raise StreamError(msg)
    notes = [f"{m}: not in the log, skipped" for m in missing]
    unit_names = {SHORT.get(m.unit, m.unit) for m in mags if m.id in have}
    if len(unit_names) != 1:
        msg = f"{rec.path.name}: the magnetometers have different units ({', '.join(sorted(unit_names))}); use --mag"
        raise StreamError(msg)
    rows: list[tuple[float, str, FloatArray]] = []
    told = cal.source.timing.get("magnetometer")
    for mag in (m for m in mags if m.id in have):
        stream = rec.select(Kind.MAGNETOMETER, mag.id)
        if told in CHOICES:                # the fit's time convention, so a time offset means the same here
            stream = as_instants(stated(stream, Sampling(told)))
        y = stream.xyz * units.from_si(mag.unit)
        t, b, done = calibrated(cal, mag, stream.t, y, rec)
        notes += done
        rows += [(float(ti), mag.id, v) for ti, v in zip(t, b, strict=True)]
    rows.sort(key=lambda r: (r[0], r[1]))
    return rows, unit_names.pop(), notes


def apply_to_recording(cal: Calibration, rec: Recording, mag_ids: list[str] | None = None) -> tuple[str, list[str]]:
    """(CSV text, notes) of the calibrated field of every document magnetometer found in `rec`."""
    rows, u, notes = apply_rows(cal, rec, mag_ids)
    lines = [f"t [s],id,mx [{u}],my [{u}],mz [{u}],norm [{u}]"]
    # the shortest text that reads back to the same double: the CSV is the field, not a rounding of it (a calibrated
    # topic or a node's correction agrees with it to the last bit, issue 40)
    lines += [f"{t:.6f},{i},{float(v[0])!r},{float(v[1])!r},{float(v[2])!r},{float(np.linalg.norm(v))!r}"
              for t, i, v in rows]
    return "\n".join(lines) + "\n", notes
