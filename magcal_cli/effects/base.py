"""What an effect plug-in is: its id, parameter blocks, channels, the term it adds to a factor, and its tests.

An effect extends the base model y = D R^T m_n + o (plus the accelerometer and gyro models) by a term that is
exactly zero at parameter zero (calibration-file.md "Effects"; mismatch.md section 1). The joint MAP adds the
term and its Jacobians to the magnetometer, accelerometer or gyro factor (`models/map/effects.py`).
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from magcal_cli.align import columns
from magcal_cli.effects.spline import cubic
from magcal_cli.params import ParamBlock
from magcal_cli.streams import FloatArray, Kind, Stream


class Target(Enum):
    """The factor an effect's term enters."""

    MAG = "mag"          # added to the predicted reading, in (scaled) field units
    ACCEL = "accel"      # added to the predicted specific force, m/s^2
    GYRO = "gyro"        # added to the preintegrated rotation's right-perturbation vector, rad


class NotTestable(Exception):  # noqa: N818 -- a finding, not an error
    """The log cannot test this effect (channel missing or not excited); the message says why, in plain words."""


@dataclass(frozen=True, eq=False)
class Kinematics:
    """The motion at one magnetometer's K epochs t (s): body rate omega (K, 3) rad/s with the start gyro bias
    removed and its derivative omega_dot (K, 3) rad/s^2; the gyro samples themselves for effects that integrate
    between epochs: gyr_t (N,) s, gyr (N, 3) rad/s as logged (the problem's own arrays, not copied), each held over
    [t_j, t_j+1), and `gyr_bias` (3,) the start bias to remove from them; `still` (K,): the epoch lies in a segment
    where the gyro and accelerometer show only noise (detect.py)."""

    t: FloatArray
    omega: FloatArray
    omega_dot: FloatArray
    gyr_t: FloatArray
    gyr: FloatArray
    still: npt.NDArray[np.bool_] | None = None
    gyr_bias: FloatArray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, eq=False)
class Inputs:
    """What a term is evaluated from, at one magnetometer's K epochs: times (s), the gyro rate with the start
    bias removed and its derivative there (rad/s, rad/s^2), the channels the effect asked for (K,) or (K, w),
    the ids of the streams they came from, and effect-specific constants (e.g. a reference temperature)."""

    t: FloatArray
    omega: FloatArray
    omega_dot: FloatArray
    channels: dict[str, FloatArray] = field(default_factory=dict)
    channel_ids: tuple[str, ...] = ()
    constants: dict[str, Any] = field(default_factory=dict)

    def rows(self, sel: slice) -> Inputs:
        """The inputs at a run of epochs (a filter evaluates a term one epoch at a time)."""
        return Inputs(self.t[sel], self.omega[sel], self.omega_dot[sel],
                      {k: v[sel] for k, v in self.channels.items()}, self.channel_ids, self.constants)


@dataclass(frozen=True, eq=False)
class Point:
    """The model at the current iterate: rotations (K, 3, 3) body->NED, predicted unit body field m_b (K, 3),
    its derivative by the dip (K, 3), gravity in the body frame g_b = R^T g_n (K, 3), D (3, 3) in scaled field
    units, and the gyro preintegration (for gyro terms)."""

    rot: FloatArray
    m_b: FloatArray
    dm_b_ddip: FloatArray
    g_b: FloatArray
    D: FloatArray
    pre: Any = None

    @classmethod
    def unknown(cls, k: int) -> Point:
        """K epochs whose model quantities are not known (NaN): an additive term (`Effect.additive`) reads none of
        them, so a filter evaluates it once over all epochs before the orientations exist
        (models/ekf/effects.py)."""
        vec = np.full((k, 3), np.nan)
        return cls(np.full((k, 3, 3), np.nan), vec, vec, vec, np.full((3, 3), np.nan))


@dataclass(frozen=True, eq=False)
class Term:
    """value (M, 3) added to the prediction; d_beta (M, 3, p) its derivative by the effect's parameters;
    d_state (M, 3, 3) by the right perturbation of R_k (None: independent of the orientation); d_base: by base
    blocks, name -> (M, 3, size) (e.g. a time offset scales with D)."""

    value: FloatArray
    d_beta: FloatArray
    d_state: FloatArray | None = None
    d_base: dict[str, FloatArray] = field(default_factory=dict)


class Effect:
    """Base class of the effect plug-ins: class attributes declare, methods compute. One module per effect."""

    id: ClassVar[str]
    target: ClassVar[Target]
    params: ClassVar[tuple[ParamBlock, ...]]
    #: param -> unit; "{field}" stands for the magnetometer's unit
    units: ClassVar[dict[str, str]]
    #: the `inspect` kinds of the log channels it needs (empty: only the IMU and magnetometer)
    channels: ClassVar[tuple[Kind, ...]] = ()
    physics_left_out: ClassVar[str]
    #: largest physically plausible |entry| of each parameter (SI); a fit beyond it stands in for other physics
    limits: ClassVar[dict[str, float]] = {}
    #: the recording that tells this effect apart from a rival the log could not separate it from
    separating_experiment: ClassVar[str] = ("a recording in which the two effects' channels change "
                                            "independently of each other")
    #: firmware parameters that hold it, where a firmware has a knob
    firmware: ClassVar[dict[str, str]] = {}
    #: the signal the firmware's interference compensation multiplies ("current" or "throttle"), if any:
    #: `export` writes COMPASS_MOT* / CAL_MAGn_*COMP from the accepted effect (firmware/effects.py)
    compensates: ClassVar[str | None] = None
    #: the term is an offset added to the magnetometer reading that depends only on the effect's own channels and
    #: parameters -- not on the orientation, the base parameters or row weights (Term.d_state None, no d_base):
    #: the EKF baselines carry such a term as extra parameters or states (models/ekf/effects.py)
    additive: ClassVar[bool] = False
    #: the term vanishes with the vehicle at rest (motors off: no current, no throttle), so the offsets it leaves are
    #: the hard iron itself; of an ambiguous pair the diagnosis carries such a one (diagnose/select.py)
    zero_at_rest: ClassVar[bool] = False
    #: effects whose term this one contains as a special case (per-motor fields: throttle and current, when the
    #: motors move together); the diagnosis calls such a pair rivals only when this one explains nothing beyond the
    #: other (diagnose/select.py)
    nests: ClassVar[tuple[str, ...]] = ()

    def applies(self, aux: tuple[Stream, ...]) -> bool:
        """Whether the diagnosis screens it on a log with these channels (False: it is left out, not listed as
        not testable; an effect added after logs were diagnosed without it keeps their documents unchanged)."""
        return True

    def inputs(self, aux: tuple[Stream, ...], mag: Stream, kin: Kinematics,
               declination: float = 0.0) -> Inputs:
        """The inputs at the epochs; raises NotTestable when the log lacks a channel or its excitation.

        `declination` (rad, from the WMM where the log's position is known) turns true-north vectors into the
        model's navigation frame, whose x axis points to magnetic north.
        """
        return Inputs(kin.t, kin.omega, kin.omega_dot)

    def prior(self) -> tuple[FloatArray, FloatArray] | None:
        """A Gaussian prior (mean, std) per parameter entry where a parameter only exists under the alternative
        (None: no prior)."""
        return None

    def weights(self, inp: Inputs) -> FloatArray | None:
        """Per-epoch weights (K,) of the rows of the factor the effect enters (`target`), 0 = excluded (None: all
        rows count)."""
        return None

    def start(self) -> FloatArray:
        """The parameter values to start from: the base model."""
        return np.zeros(sum(b.size for b in self.params))

    def term(self, inp: Inputs, beta: FloatArray, at: Point) -> Term:
        """The term and its Jacobians at parameters beta."""
        raise NotImplementedError

    def correct(self, params: dict[str, Any], t: FloatArray, y: FloatArray,
                channels: dict[str, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """`apply`: remove the effect from readings y (N, 3) in the document's unit stamped t (N,) with the
        document entry's params; `channels` maps each of `self.channels`' kind values (e.g. "battery_current")
        to that channel at t. Effects of the IMU leave the field alone."""
        return t, y


#: neighbouring channel samples further apart than this many median periods are a dropout: bridged by a line
BRIDGE_PERIODS = 4.0

Owner = TypeVar("Owner")
K = TypeVar("K")
V = TypeVar("V")


class Recent(Generic[Owner, K, V]):
    """Values computed from an owner (a problem, a stream), kept while the owner lives: the `keep` most recently used
    of each group of keys (`group`; default one group). Thread-safe: the diagnosis binds from worker threads."""

    def __init__(self, keep: int, group: Callable[[K], object] = lambda _: None) -> None:
        self.keep, self.group = keep, group
        self._by: weakref.WeakKeyDictionary[Owner, dict[K, V]] = weakref.WeakKeyDictionary()
        self._lock = threading.Lock()

    def get(self, owner: Owner, key: K) -> V | None:
        """The value kept under `key`, now the most recently used of its group; None when not kept."""
        with self._lock:
            known = self._by.setdefault(owner, {})
            got = known.pop(key, None)
            if got is not None:
                known[key] = got
            return got

    def put(self, owner: Owner, key: K, value: V) -> None:
        """Keep `value` under `key`, dropping the least recently used of its group beyond `keep`."""
        with self._lock:
            known = self._by.setdefault(owner, {})
            known[key] = value
            g = self.group(key)
            for k in [k for k in known if self.group(k) == g][:-self.keep]:
                del known[k]

    def drop(self, owner: Owner, which: Callable[[K], bool]) -> None:
        """Forget the values kept for `owner` under the keys `which` names."""
        with self._lock:
            try:
                known = self._by.get(owner, {})
            except TypeError:            # an owner no weak reference can name (a test's stand-in) holds nothing
                return
            for k in [k for k in known if which(k)]:
                del known[k]

    def keys(self, owner: Owner) -> list[K]:
        """The keys kept for `owner`, least recently used first."""
        with self._lock:
            return list(self._by.get(owner, {}))


#: resampled channels kept per stream (the most recently used sets of times): the diagnosis resamples a channel at
#: the same epochs for every training fold, and a 400 Hz temperature's spline through a two-hour log's 2.9 M samples
#: was the process peak (180 MB of work arrays) each time (issue 39)
RESAMPLED_KEEP = 4
_RESAMPLED: Recent[Stream, bytes, FloatArray] = Recent(RESAMPLED_KEEP)


def resample(stream: Stream, t: FloatArray) -> FloatArray:
    """`resampled`, read-only, computed once per stream and times (the same digits: it is deterministic)."""
    key = hashlib.blake2b(np.ascontiguousarray(t, dtype=np.float64).tobytes(), digest_size=16).digest()
    got = _RESAMPLED.get(stream, key)
    if got is None:
        got = resampled(stream, t)
        got.flags.writeable = False
        _RESAMPLED.put(stream, key, got)
    return got


def resampled(stream: Stream, t: FloatArray) -> FloatArray:
    """A channel at times t: the not-a-knot cubic spline through its samples, held at its first/last value outside
    its span; samples that are not finite (dropouts) are skipped, never interpolated through as NaN.

    Not a line between samples: a channel logged slower than the magnetometer, or at other instants (ArduPilot's
    BAT at 10 Hz beside MAG), loses its fast content to a line (a sinc^2 response), and the effect's fit then
    reads that loss as a larger coefficient. On the independent simulator's hand-held logs with a 10 Hz current
    the 95 % intervals of c covered 78-82 % of 60 components (93 % with the current at the readings' stamps);
    the spline gives 92 % (issue 38, docs/effects.md "Coverage"). Across a dropout (BRIDGE_PERIODS) it is a line,
    so a gap never swings; at a sample's own stamp both give the sample."""
    ok = np.all(np.isfinite(stream.values), axis=1)
    if ok.sum() < 2:
        msg = f"the {stream.kind.value} channel {stream.id} has fewer than two valid samples"
        raise NotTestable(msg)
    # the stream's own arrays when they serve as they are (a 400 Hz channel of a long log: no copies, issue 39)
    ts, v = (stream.t, stream.values) if ok.all() else (stream.t[ok], stream.values[ok])
    gaps = np.diff(ts)
    if not np.all(gaps > 0):
        ts, first = np.unique(ts, return_index=True)       # a repeated stamp keeps its first sample
        v, gaps = v[first], np.diff(ts)
    line = columns(t, ts, v)
    if ts.size < 4:
        return line
    inside = (t > ts[0]) & (t < ts[-1])
    j = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 2)
    smooth = inside & (ts[j + 1] - ts[j] <= BRIDGE_PERIODS * float(np.median(gaps)))
    del gaps
    if not smooth.any():
        return line
    out: FloatArray = line.copy()
    out[smooth] = cubic(ts, v)(t[smooth])
    return out


def pick(aux: tuple[Stream, ...], kind: Kind, prefer: tuple[str, ...] = ()) -> Stream:
    """The channel of `kind` whose id contains one of `prefer` (the first such stream otherwise)."""
    found = [s for s in aux if s.kind is kind and len(s) >= 2]
    if not found:
        msg = f"this log has no {kind.value} channel"
        raise NotTestable(msg)
    for p in prefer:
        for s in found:
            if p and p.lower() in s.id.lower():
                return s
    return found[0]
