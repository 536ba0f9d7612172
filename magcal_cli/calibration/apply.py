"""`magcal apply`: a calibration applied to a log, the calibrated field over time as CSV.

Each row is one magnetometer sample: time (s, the log's stream time), stream id, the calibrated body-frame
field F A (y - o - terms) in the document's unit and its magnitude. Every magnetometer effect the calibration
carries (accepted, or ambiguous with an estimate: effects/correct.py; interference, temperature drift, time
offset, ...) is removed by its plug-in's `correct` when the log has the channels it needs (calibration-file.md).
"""

from __future__ import annotations

import numpy as np

from magcal_cli import units
from magcal_cli.calibration.types import Calibration
from magcal_cli.effects.correct import remove
from magcal_cli.errors import StreamError
from magcal_cli.streams import Kind, Recording, Sampling
from magcal_cli.timing import CHOICES, as_instants, stated

#: how the CSV header names each document unit (the CSV input contract's spellings)
SHORT = {"tesla": "T", "millitesla": "mT", "microtesla": "uT", "nanotesla": "nT", "gauss": "G",
         "milligauss": "mG"}


def apply_to_recording(cal: Calibration, rec: Recording, mag_ids: list[str] | None = None) -> tuple[str, list[str]]:
    """(CSV text, notes) of the calibrated field of every document magnetometer found in `rec`."""
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
    u = unit_names.pop()
    rows: list[tuple[float, str, np.ndarray]] = []
    told = cal.source.timing.get("magnetometer")
    for mag in (m for m in mags if m.id in have):
        stream = rec.select(Kind.MAGNETOMETER, mag.id)
        if told in CHOICES:                # the fit's time convention, so a time offset means the same here
            stream = as_instants(stated(stream, Sampling(told)))
        y = stream.xyz * units.from_si(mag.unit)
        t, y, done = remove(cal.effects, mag.id, rec, stream.t, y)
        notes += done
        b = mag.field_strength * mag.apply(y)
        rows += [(float(ti), mag.id, v) for ti, v in zip(t, b, strict=True)]
    rows.sort(key=lambda r: (r[0], r[1]))
    lines = [f"t [s],id,mx [{u}],my [{u}],mz [{u}],norm [{u}]"]
    lines += [f"{t:.6f},{i},{v[0]:.7g},{v[1]:.7g},{v[2]:.7g},{np.linalg.norm(v):.7g}" for t, i, v in rows]
    return "\n".join(lines) + "\n", notes

