"""ArduPilot's compass correction, forward and inverse, with the parameters in force at each sample.

The firmware logs the *corrected* field (design/firmware-export.md section 1; AP_Compass_Backend.cpp
`correct_field`), in the body frame after `rotate_field` (COMPASS_ORIENTn / AHRS_ORIENTATION):

    x = raw + OFS;  x = x * SCALE (only if 0.85 <= SCALE <= 1.4);  x = M x;  x = x + MO

with M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]] (DIA = 0 means ones) and MO the
motor offset the MAG record logs (MOfsX.. / MOX..). Firmware 3.5 and older added MO before M (versions of
`correct_field` without per-motor compensation); 3.6 and newer add it after M.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal_cli.align import columns
from magcal_cli.streams import FloatArray

#: COMPASS_MIN_SCALE_FACTOR / COMPASS_MAX_SCALE_FACTOR (CompassCalibrator.h); outside, SCALE is ignored
SCALE_RANGE = (0.85, 1.4)
AXES = ("X", "Y", "Z")
#: samples per batched 3x3 solve when undoing the correction (bounds the solver's copies)
SOLVE_BLOCK = 1 << 16


class ParamHistory:
    """Every PARM record of a log: the value of each parameter over time (s, the log's clock)."""

    def __init__(self, names: list[str], times: FloatArray, values: FloatArray) -> None:
        order = np.argsort(times, kind="stable")
        self._series: dict[str, tuple[FloatArray, FloatArray]] = {}
        grouped: dict[str, list[int]] = {}
        for i in order.tolist():                  # PARM records: a few hundred to a few thousand
            grouped.setdefault(names[i], []).append(i)
        for name, idx in grouped.items():
            self._series[name] = (np.asarray(times)[idx], np.asarray(values, dtype=np.float64)[idx])

    def __contains__(self, name: str) -> bool:
        return name in self._series

    def last(self) -> dict[str, float]:
        """Each parameter's last logged value."""
        return {k: float(v[-1]) for k, (_, v) in self._series.items()}

    def at(self, name: str, t: FloatArray, default: float) -> FloatArray:
        """The value in force at each time: the latest record at or before t, else the first record."""
        if name not in self._series:
            return np.full(np.shape(t), default, dtype=np.float64)
        times, values = self._series[name]
        i = np.searchsorted(times, t, side="right") - 1
        return values[np.clip(i, 0, None)]

    def changes(self, name: str) -> int:
        """How many times the value changed after its first record."""
        if name not in self._series:
            return 0
        v = self._series[name][1]
        return int(np.count_nonzero(np.diff(v) != 0))


@dataclass(frozen=True, eq=False)
class Correction:
    """Per-sample correction: offsets (N, 3) mG, iron matrix (N, 3, 3), scale (N,), motor offset (N, 3) mG."""

    ofs: FloatArray
    matrix: FloatArray
    scale: FloatArray
    motor: FloatArray
    motor_after_matrix: bool = True


def iron_matrix(dia: FloatArray, odi: FloatArray) -> FloatArray:
    """(N, 3, 3) symmetric matrices from COMPASS_DIA/ODI rows; an all-zero DIA means ones (correct_field)."""
    dia = np.where(np.all(dia == 0, axis=1, keepdims=True), 1.0, dia)
    m = np.empty(dia.shape[:1] + (3, 3))
    m[:, 0, 0], m[:, 1, 1], m[:, 2, 2] = dia[:, 0], dia[:, 1], dia[:, 2]
    m[:, 0, 1] = m[:, 1, 0] = odi[:, 0]
    m[:, 0, 2] = m[:, 2, 0] = odi[:, 1]
    m[:, 1, 2] = m[:, 2, 1] = odi[:, 2]
    return m


def effective_scale(scale: FloatArray) -> FloatArray:
    """COMPASS_SCALE as applied: the value inside [0.85, 1.4], else 1 (have_scale_factor)."""
    return np.where((scale >= SCALE_RANGE[0]) & (scale <= SCALE_RANGE[1]), scale, 1.0)


def correct_field(raw: FloatArray, ofs: FloatArray, scale: FloatArray | float, matrix: FloatArray,
                  motor: FloatArray | None = None, motor_after_matrix: bool = True) -> FloatArray:
    """correct_field of body-frame raw readings (N, 3) mG: the one copy of the formula in the module docstring.

    `ofs`, `scale`, `matrix` and `motor` hold one value for all samples ((1, 3), float, (3, 3), (N, 3)) or one per
    sample ((N, 3), (N, 1), (N, 3, 3), (N, 3)); `motor` None adds nothing.
    """
    x = (raw + ofs) * scale
    if motor is not None and not motor_after_matrix:
        x = x + motor
    # one matrix: a BLAS product (as `check` has always computed it); one per sample: einsum. The two round the
    # last bit differently, and both callers' outputs are pinned
    x = x @ matrix.T if matrix.ndim == 2 else np.einsum("nij,nj->ni", matrix, x)
    out: FloatArray = x + motor if motor is not None and motor_after_matrix else x
    return out


def apply_correction(raw: FloatArray, c: Correction) -> FloatArray:
    """The field the firmware logs for body-frame raw readings (N, 3) mG (before int16 truncation)."""
    return correct_field(raw, c.ofs, c.scale[:, None], c.matrix, c.motor, c.motor_after_matrix)


def undo_correction(logged: FloatArray, c: Correction) -> FloatArray:
    """The body-frame raw readings (N, 3) mG behind a logged corrected field (apply_correction's inverse)."""
    x = logged - c.motor if c.motor_after_matrix else logged
    y: FloatArray = np.empty(x.shape, dtype=np.float64)
    for i in range(0, len(x), SOLVE_BLOCK):           # blocks: the batched solve copies its inputs
        y[i:i + SOLVE_BLOCK] = np.linalg.solve(c.matrix[i:i + SOLVE_BLOCK], x[i:i + SOLVE_BLOCK, :, None])[:, :, 0]
    if not c.motor_after_matrix:
        y = y - c.motor
    return y / c.scale[:, None] - c.ofs


#: a log's integer field counts as rounded (no half count added back) only when its zero bin favours rounding over
#: the firmware's truncating cast by at least this likelihood ratio; with less evidence the firmware's cast stands
ROUNDED_EVIDENCE = 1000.0
#: bins either side of zero the test compares the zero bin with, and the fewest counts it needs there
ZERO_TEST_BINS, ZERO_TEST_MIN = 3, 30
#: a value counts as in motion when its axis changes by more than this many counts over this long (s) around it:
#: a sweep of 40 counts/s (0.1 rad/s on a 400-count field) is motion, a still pose's noise (2-3 counts) is not
MOVING_COUNTS, MOVING_S = 10.0, 0.25


def _in_motion(counts: FloatArray, t: FloatArray) -> FloatArray:
    """The values (flat) of an (N, 3) integer field at times t (N,) s whose axis moves by more than MOVING_COUNTS over
    the MOVING_S around them: a still pose parks an axis near one value and would put a bump beside the zero bin."""
    x = np.asarray(counts, dtype=np.float64).reshape(len(counts), -1)
    if len(x) < 3:
        return np.zeros(0)
    later = columns(t + MOVING_S / 2, t, x)
    earlier = columns(t - MOVING_S / 2, t, x)
    out: FloatArray = x[np.abs(later - earlier) > MOVING_COUNTS]
    return out


def truncation_evidence(counts: list[FloatArray], times: list[FloatArray]) -> float:
    """ln P(zero bin | truncated) - ln P(zero bin | rounded) for integer logged fields (N, 3) at times (N,) s.

    AP_Compass logs `(int16_t)field`: the cast truncates toward zero, so bin 0 holds (-1, 1), twice the width of
    any other bin, and bin k > 0 holds [k, k + 1). A log rounded to the nearest count (another firmware, a
    converter, a simulator) has no such dead zone. Only values in motion count (`_in_motion`): there the field
    sweeps smoothly through zero. A quadratic density is fitted to the bins +-1..+-3 at each hypothesis' bin centres
    and the zero bin's count scored as Poisson; 0 when there are too few counts to judge.
    """
    v = np.rint(np.concatenate([_in_motion(c, t) for c, t in zip(counts, times, strict=True)])) if counts else \
        np.zeros(0)
    ks = np.concatenate([-np.arange(ZERO_TEST_BINS, 0, -1), np.arange(1, ZERO_TEST_BINS + 1)]).astype(np.float64)
    near = np.array([np.count_nonzero(v == k) for k in ks], dtype=np.float64)
    if near.sum() < ZERO_TEST_MIN:
        return 0.0
    zero = float(np.count_nonzero(v == 0))
    score = []
    for centres, width in ((ks + 0.5 * np.sign(ks), 2.0), (ks, 1.0)):
        a, _, c = np.linalg.lstsq(np.stack([np.ones_like(ks), centres, centres**2], axis=1), near, rcond=None)[0]
        expected = max(width * a + c * width**3 / 12.0, 1e-9)      # the quadratic integrated over the zero bin
        score.append(zero * np.log(expected) - expected)
    return float(score[0] - score[1])


def param_suffix(instance: int, params: dict[str, float]) -> tuple[str, str | None]:
    """Parameter suffix of a logged MAG instance ("" , "2", "3"), checked against COMPASS_PRIOn_ID.

    Log instance I is priority I; `_reorder_compass_params` puts priority I in slot I, i.e. suffix I+1.
    When COMPASS_DEV_ID{suffix} disagrees with COMPASS_PRIO{I+1}_ID, the slot holding that device is used.
    """
    suffix = "" if instance == 0 else str(instance + 1)
    prio = params.get(f"COMPASS_PRIO{instance + 1}_ID", 0.0)
    if not prio or params.get(f"COMPASS_DEV_ID{suffix}", prio) == prio:
        return suffix, None
    for k in ("", "2", "3"):
        if params.get(f"COMPASS_DEV_ID{k}") == prio:
            return k, (f"MAG[{instance}]: COMPASS_PRIO{instance + 1}_ID={prio:.0f} is COMPASS_DEV_ID{k}, "
                       f"so its calibration was read from the COMPASS_*{k} parameters")
    return suffix, None


def _vec(hist: ParamHistory, stem: str, suffix: str, t: FloatArray, default: float) -> FloatArray:
    """(N, 3) per-sample values of COMPASS_<stem><suffix>_X/Y/Z."""
    return np.stack([hist.at(f"COMPASS_{stem}{suffix}_{a}", t, default) for a in AXES], axis=1)


def _fmt(v: FloatArray) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def motor_product(hist: ParamHistory, suffix: str, t: FloatArray, throttle: FloatArray | None,
                  current: FloatArray | None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """COMPASS_MOT x throttle (MOTCT 1) or x current (MOTCT 2) at the sample times (N, 3) mG, the signal (N,) and
    COMPASS_MOTCT (N,): the motor offset the firmware adds before it logs MO."""
    motct = hist.at("COMPASS_MOTCT", t, 0.0)
    mot = _vec(hist, "MOT", suffix, t, 0.0)
    zero = np.zeros(t.size)
    signal = np.where(motct == 1, zero if throttle is None else throttle,
                      np.where(motct == 2, zero if current is None else current, 0.0))
    return mot * signal[:, None], signal, motct


#: a logged MO count matching the truncated product where rounding would give another (or the reverse) is this
#: strong evidence for the cast (the current's own error makes a mismatch possible, not likely)
CAST_MATCH_LOG_LR = float(np.log(20.0))


def motor_cast_evidence(logged: FloatArray, product: FloatArray) -> float:
    """ln P(MO | truncated) - ln P(MO | rounded) from the logged motor-offset counts (N, 3) and the float product
    the firmware cast (N, 3), in counts: only where the two casts differ and the product is not near a half count."""
    return cast_evidence(logged, product, CAST_MATCH_LOG_LR)


def cast_evidence(logged: FloatArray, exact: FloatArray, per_match: float) -> float:
    """ln P(logged | truncated) - ln P(logged | rounded) for integer counts cast from known floats (same shapes):
    `per_match` for each value that matches one cast where the other differs (its fraction 0.6-0.9 of a count)."""
    frac = np.abs(exact) - np.floor(np.abs(exact))
    telling = (np.abs(exact) >= 1.0) & (frac > 0.6) & (frac < 0.9)
    if not telling.any():
        return 0.0
    by_trunc = np.count_nonzero(logged[telling] == np.trunc(exact[telling]))
    by_round = np.count_nonzero(logged[telling] == np.rint(exact[telling]))
    return float((by_trunc - by_round) * per_match)


def offsets_in_force(hist: ParamHistory, suffix: str, t: FloatArray) -> FloatArray | None:
    """COMPASS_OFS{suffix} at the sample times (N, 3) mG, None when the log has no such records."""
    if not all(f"COMPASS_OFS{suffix}_{a}" in hist for a in AXES):
        return None
    return _vec(hist, "OFS", suffix, t, 0.0)


def offset_cast_evidence(logged: FloatArray, params: FloatArray) -> float:
    """The cast evidence of the logged OfsX.. counts (N, 3) against the COMPASS_OFS values in force (N, 3), counting
    each distinct (parameter, logged) pair once: the same offset is logged in every record."""
    rows = np.concatenate([params, logged], axis=1)
    # a row equal to the one before adds no pair: sorting every record's row took 0.5 s of a 60-min log's read
    fresh = np.ones(rows.shape[0], dtype=bool)
    fresh[1:] = np.any(rows[1:] != rows[:-1], axis=1)
    pairs = np.unique(rows[fresh], axis=0)
    return cast_evidence(pairs[:, 3:], pairs[:, :3], float(np.log(ROUNDED_EVIDENCE)))


def compass_correction(hist: ParamHistory, suffix: str, t: FloatArray, logged_ofs: FloatArray | None,
                       logged_motor: FloatArray | None, motor_after_matrix: bool,
                       throttle: FloatArray | None = None,
                       current: FloatArray | None = None) -> tuple[Correction, str]:
    """The correction in force at each sample time t (s) and a description of what it contains.

    Offsets come from the PARM history; where the logged OfsX.. disagree by 1 mG or more (int16 truncation
    aside) the logged ones are used (offsets learned in flight are not written as PARM records).
    Motor offsets are COMPASS_MOT times `throttle` (0..1, MOTCT=1) or `current` (A, MOTCT=2) at the sample times;
    where the log has MO fields, the product is used only where it agrees with them to a count (else MO).
    """
    n = t.size
    parts: list[str] = []
    have_ofs = all(f"COMPASS_OFS{suffix}_{a}" in hist for a in AXES)
    ofs = _vec(hist, "OFS", suffix, t, 0.0)
    if logged_ofs is not None:
        bad = np.any(np.abs(ofs - logged_ofs) >= 1.0, axis=1) if have_ofs else np.ones(n, dtype=bool)
        ofs = np.where(bad[:, None], logged_ofs, ofs)
        if have_ofs and bad.any():
            parts.append(f"logged OfsX.. used at {int(bad.sum())} samples where they differ from the PARM "
                         "records")
    elif not have_ofs:
        parts.append(f"no COMPASS_OFS{suffix} records and no logged offsets; offsets taken as zero")
    dia, odi = _vec(hist, "DIA", suffix, t, 0.0), _vec(hist, "ODI", suffix, t, 0.0)
    scale_raw = hist.at(f"COMPASS_SCALE{suffix}", t, 0.0)
    scale = effective_scale(scale_raw)
    product, signal, motct = motor_product(hist, suffix, t, throttle, current)
    if logged_motor is not None:
        motor, motor_desc = logged_motor, "motor offsets from the logged MO fields"
        # MO is COMPASS_MOT x throttle or current, logged as int16: where the product agrees with it to within a
        # count, the product is what the firmware added (its rounding left in would follow the current)
        exact = np.all(np.abs(product - logged_motor) < 1.0, axis=1) & (signal != 0)
        if exact.any():
            motor = np.where(exact[:, None], product, logged_motor)
            motor_desc = (f"motor offsets COMPASS_MOT{suffix} x {'throttle' if np.all(motct == 1) else 'current'} "
                          f"where the logged MO fields agree to a count ({int(exact.sum())} of {n} samples), else "
                          "the logged MO")
        if np.any(logged_motor != 0):
            motor_desc += f" (up to {np.abs(logged_motor).max():.0f} mG)"
        else:
            motor_desc += " (all zero)"
    else:
        motor = product
        motor_desc = ("motor offsets COMPASS_MOT x throttle/current per COMPASS_MOTCT" if np.any(motor != 0)
                      else "no motor offsets (COMPASS_MOTCT=0 or MOT=0)")
    corr = Correction(ofs, iron_matrix(dia, odi), scale, motor, motor_after_matrix)
    s0 = scale[0] if n else 1.0
    def first(a: FloatArray) -> FloatArray:
        return a[0] if n else np.zeros(3)

    desc = (f"COMPASS_OFS{suffix}={_fmt(first(ofs))}, DIA{suffix}={_fmt(first(dia))}, "
            f"ODI{suffix}={_fmt(first(odi))}, "
            + (f"SCALE{suffix}={s0:.4g}" if s0 != 1.0 else f"SCALE{suffix} not applied") + f", {motor_desc}")
    changed = [f"{stem}{suffix}" for stem in ("OFS", "DIA", "ODI")
               if any(hist.changes(f"COMPASS_{stem}{suffix}_{a}") for a in AXES)]
    changed += [f"SCALE{suffix}"] if hist.changes(f"COMPASS_SCALE{suffix}") else []
    if changed:
        parts.append(f"{', '.join(changed)} changed during the log; the values in force at each sample were "
                     "used (first values shown)")
    return corr, desc + ("; " + "; ".join(parts) if parts else "")
