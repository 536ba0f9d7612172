"""The numbers the HTML report plots for the IMU's modelled effects: per axis, a residual against its channel.

Magnetometer effects are plotted by `data.effect_views`; an IMU effect changes the accelerometer or the
gyro instead, so its residual is the one that sensor leaves. Each view needs no orientation trajectory (the
report does not keep one): the specific force's magnitude against g (accelerometer effects), and the rotation
between still poses seen by the gyro against the one the accelerometer and the calibrated magnetometer see
(gyro effects). "Before" removes every other modelled IMU term and the other axes of the effect itself, "after"
removes all of it, so a panel shows one axis of one effect.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from magcal_cli import so3
from magcal_cli.detect import Segment, window_means
from magcal_cli.effects import get
from magcal_cli.effects.base import NotTestable, Target
from magcal_cli.effects.correct import MODELLED
from magcal_cli.errors import MagcalError
from magcal_cli.registry import resolve
from magcal_cli.streams import FloatArray, Kind, Stream
from magcal_cli.writers.report.data import EffectView

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult

#: effect id -> "module:function(ImuData, entry) -> list[EffectView]" (one view per axis): plotting another IMU
#: effect is its function and one line here
IMU_VIEWS: dict[str, str] = {
    "accel_scale": "magcal_cli.writers.report.imu:accel_scale",
    "lever_arm": "magcal_cli.writers.report.imu:lever_arm",
    "gyro_scale": "magcal_cli.writers.report.imu:gyro_scale",
}
AXES = "xyz"


@dataclass(frozen=True, eq=False)
class ImuData:
    """The IMU's streams and fitted biases, and the modelled IMU effects' parameters by effect id."""

    result: RunResult
    acc: Stream
    gyr: Stream
    b_a: FloatArray
    b_g: FloatArray
    params: dict[str, dict[str, FloatArray]]

    @property
    def f(self) -> FloatArray:
        """Specific force less the bias (N, 3) m/s^2."""
        out: FloatArray = self.acc.xyz - self.b_a
        return out

    @property
    def w(self) -> FloatArray:
        """Rate less the bias (N, 3) rad/s."""
        out: FloatArray = self.gyr.xyz - self.b_g
        return out

    def one_plus(self, effect_id: str, skip: int | None = None) -> FloatArray:
        """1 + s of a modelled scale effect (ones when not modelled), with axis `skip` left unscaled."""
        s = self.params.get(effect_id, {}).get("s", np.zeros(3)).copy()
        if skip is not None:
            s[skip] = 0.0
        out: FloatArray = 1.0 + s
        return out


def imu_data(result: RunResult) -> ImuData | None:
    """The IMU's data for the views (None without both IMU streams)."""
    cal, rec = result.calibration, result.recording
    try:
        acc, gyr = rec.select(Kind.ACCELEROMETER, cal.imu.id), rec.select(Kind.GYROSCOPE, cal.imu.id)
    except MagcalError:
        return None
    b_a = cal.imu.accelerometer_bias if cal.imu.accelerometer_bias is not None else np.zeros(3)
    b_g = cal.imu.gyroscope_bias if cal.imu.gyroscope_bias is not None else np.zeros(3)
    # the fitted blocks only: an entry's params also carry its documented constants ("source": text)
    params = {str(e["id"]): {b.name: np.asarray(e["params"][b.name], dtype=np.float64)
                             for b in get(str(e["id"])).params if b.name in e["params"]}
              for e in _modelled(result)}
    return ImuData(result, acc, gyr, b_a, b_g, params)


def _modelled(result: RunResult) -> list[dict[str, Any]]:
    """The document entries of the modelled effects of the IMU (accelerometer or gyro target)."""
    from magcal_cli.effects import EFFECTS

    return [e for e in result.calibration.effects if e.get("status") in MODELLED and e.get("params")
            and e.get("id") in EFFECTS and get(str(e["id"])).target in (Target.ACCEL, Target.GYRO)]


def imu_effect_views(result: RunResult) -> list[EffectView]:
    """Per modelled IMU effect with a registered view: one view per axis, residual before and after."""
    entries = [e for e in _modelled(result) if e["id"] in IMU_VIEWS]
    data = imu_data(result) if entries else None
    if data is None:
        return []
    out: list[EffectView] = []
    for e in entries:
        view: Callable[[ImuData, dict[str, Any]], list[EffectView]] = resolve(IMU_VIEWS[str(e["id"])],
                                                                              f"the {e['id']} plot")
        try:
            out += view(data, e)
        except (MagcalError, NotTestable):    # the log lacks what this view needs (still poses, a magnetometer)
            continue
    return out


def _views(e: dict[str, Any], xlabel: str, ylabel: str, x: FloatArray, before: FloatArray,
           after: FloatArray) -> list[EffectView]:
    """One view per axis from (N, 3) channels and residuals (`after` (N,) when the same for every axis)."""
    a = after if after.ndim == 2 else np.repeat(after[:, None], 3, axis=1)
    return [EffectView(str(e["id"]), str(e.get("status")), xlabel.format(ax=ax), ylabel.format(ax=ax), x[:, i],
                       before[:, i], a[:, i], f"{ax} axis") for i, ax in enumerate(AXES)]


def accel_scale(data: ImuData, e: dict[str, Any]) -> list[EffectView]:
    """Each still pose: |f| - g against f on the axis; a scale s shows as s f^2 / g (a parabola)."""
    from magcal_cli.models.accel import G

    segs = data.result.still.segments
    if len(segs) < 2:
        msg = "fewer than two still poses"
        raise NotTestable(msg)
    mean, _ = window_means(data.acc, segs)
    f = mean - data.b_a
    before = np.stack([np.linalg.norm(f / data.one_plus("accel_scale", i), axis=1) - G for i in range(3)], axis=1)
    after = np.linalg.norm(f / data.one_plus("accel_scale"), axis=1) - G
    return _views(e, "specific force f_{ax} [m/s²]", "|f| − g at the still poses [m/s²]", f, before, after)


def lever_arm(data: ImuData, e: dict[str, Any]) -> list[EffectView]:
    """Every sample: |f| - g against the rate term of r's component along f, ([w']x + [w]x^2) e_i . f/|f| (1/s^2);
    a lever arm r shows as r_i times it."""
    from magcal_cli.models.accel import G
    from magcal_cli.models.map.effects import kinematics
    from magcal_cli.models.problem import Problem

    cal = data.result.calibration
    problem = Problem(str(cal.source.path), cal.imu.id, data.acc, data.gyr, (), data.result.still)
    kin = kinematics(problem, data.acc.t, data.b_g)
    k = get("lever_arm").inputs((), data.acc, kin).channels["kinematics"]       # (N, 3, 3): the term is k r
    r = data.params["lever_arm"]["r_m"]
    f = data.f / data.one_plus("accel_scale")
    f_after = f - k @ r
    up = f_after / np.linalg.norm(f_after, axis=1)[:, None]
    x = np.einsum("nj,nji->ni", up, k)
    before = np.stack([np.linalg.norm(f_after + k[:, :, i] * r[i], axis=1) - G for i in range(3)], axis=1)
    after = np.linalg.norm(f_after, axis=1) - G
    return _views(e, "rate term of r_{ax} along f [1/s²]", "|f| − g [m/s²]", x, before, after)


def _pose_means(t: FloatArray, v: FloatArray, segs: tuple[Segment, ...]) -> FloatArray:
    """The mean of v (N, 3) over each still pose, leaving out NaN rows (excluded readings); NaN for a pose without
    any."""
    out = np.full((len(segs), 3), np.nan)
    for k, s in enumerate(segs):                    # one reduction per pose
        rows = v[(t >= s.start) & (t <= s.end)]
        rows = rows[np.all(np.isfinite(rows), axis=1)]
        if len(rows):
            out[k] = rows.mean(axis=0)
    return out


def gyro_scale(data: ImuData, e: dict[str, Any]) -> list[EffectView]:
    """Consecutive still poses: the gyro's rotation between them against the one the accelerometer and the
    calibrated magnetometer see, per axis against the rotation about that axis; a scale s shows as s times it."""
    result = data.result
    segs = result.still.segments
    mag = next((m for m in result.calibration.magnetometers if m.id in result.series), None)
    if len(segs) < 3 or mag is None:
        msg = "fewer than three still poses, or no calibrated magnetometer"
        raise NotTestable(msg)
    series = result.series[mag.id]
    up, _ = window_means(data.acc, segs)
    up = (up - data.b_a) / data.one_plus("accel_scale")
    field = _pose_means(series.t, series.calibrated, segs)
    dip = np.deg2rad(mag.dip_deg)
    body = np.stack([up / np.linalg.norm(up, axis=1)[:, None], field / np.linalg.norm(field, axis=1)[:, None]], axis=1)
    ok = np.all(np.isfinite(body), axis=(1, 2))
    if ok.sum() < 3:
        msg = "fewer than three still poses with magnetometer readings"
        raise NotTestable(msg)
    rot = so3.wahba(body[ok], np.array([[0.0, 0.0, -1.0], [np.cos(dip), 0.0, np.sin(dip)]]))
    seen = np.transpose(rot[:-1], (0, 2, 1)) @ rot[1:]                  # pose k+1 in pose k's frame
    t = data.gyr.t
    at = np.searchsorted(t, [0.5 * (s.start + s.end) for s, good in zip(segs, ok, strict=True) if good])
    dt = np.diff(t, append=t[-1] + float(np.median(np.diff(t))))[:, None]     # a sample holds until the next

    def error(scale: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Rotation error (deg) of the gyro corrected by `scale` from pose to pose, and the rotation per axis (deg):
        the samples' rotations chained by a prefix product (a plot needs no partial first and last pieces)."""
        phi = data.w / scale * dt
        chain = so3.cumulative_product(so3.exp(phi[at[0]:at[-1]]), reproject=False)
        ends = np.concatenate([[np.eye(3)], chain])[at - at[0]]                 # pose k's chain from the first
        gyro = np.transpose(ends[:-1], (0, 2, 1)) @ ends[1:]
        turned = np.diff(np.concatenate([np.zeros((1, 3)), np.cumsum(phi, axis=0)])[at], axis=0)
        return np.rad2deg(so3.log(np.transpose(seen, (0, 2, 1)) @ gyro)), np.rad2deg(turned)

    after, x = error(data.one_plus("gyro_scale"))
    before = np.stack([error(data.one_plus("gyro_scale", i))[0][:, i] for i in range(3)], axis=1)
    return _views(e, "rotation about {ax} between still poses [deg]", "gyro rotation error [deg]", x, before,
                  after)
