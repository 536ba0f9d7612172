"""Calibration results as frozen dataclasses, in the log's native magnetometer unit.

Convention (calibration-file.md): y = D R^T m_n(dip) + o + e with m_n = [cos dip, 0, sin dip] (NED, unit);
the calibrated unit field in the IMU body frame is m_b = A (y - b), A = D^-1, b = o.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.params import MAG
from magcal_cli.streams import FloatArray

#: the layout of `MagCalibration.cov`: vec(D) column-major, o (both in the magnetometer unit), dip in degrees
MAG_PARAMS = MAG


def _frozen(a: npt.ArrayLike | None, shape: tuple[int, ...]) -> FloatArray:
    """A read-only float copy of `a` with the expected shape (NaNs when None)."""
    out = np.full(shape, np.nan) if a is None else np.array(a, dtype=np.float64).reshape(shape)
    out.flags.writeable = False
    return out


def _eq(a: Any, b: Any) -> bool:
    """Field equality that treats arrays by value and NaN == NaN."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True))
    return bool(a == b)


@dataclass(frozen=True, eq=False)
class Quality:
    """How well the model explains the data; residuals in the magnetometer's unit."""

    samples: int
    residual_rms: float
    field_norm_rms_pct: float
    coverage_pct: float
    converged: bool
    iterations: int

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Quality) and self.__dict__ == other.__dict__


@dataclass(frozen=True, eq=False)
class MagCalibration:
    """One magnetometer: D (3x3) and o (3) in `unit`, dip in degrees, covariance in MAG_PARAMS order."""

    kind: ClassVar[str] = "magnetometer"
    FORMAT_VERSION: ClassVar[int] = 1

    id: str
    unit: str
    D: FloatArray
    o: FloatArray
    dip_deg: float
    cov: FloatArray
    field_strength: float
    field_strength_source: str = "data"
    quality: Quality | None = None
    #: parameters the log could not determine, held at a prior (partial calibration): document entries
    #: {"parameter", "held", "prior", "prior_std", "source"} in this magnetometer's unit (dip in degrees)
    held: tuple[dict[str, Any], ...] = ()
    #: what fixed the orientation: "motion" (the log's accelerometer, gyro and magnetometer) or the vehicle's
    #: attitude estimate and the World Magnetic Model ("vehicle attitude (ATT) + WMM2025")
    reference: str = "motion"
    #: the method that calibrated this magnetometer (each compass gets the strongest its data support)
    method: str = ""
    #: heading against the vehicle's attitude, magcal's vs the flown calibration (firmware/heading.py); None: not
    #: measured (no attitude or no flown calibration in the log)
    heading_check: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "held", tuple(self.held))
        object.__setattr__(self, "D", _frozen(self.D, (3, 3)))
        object.__setattr__(self, "o", _frozen(self.o, (3,)))
        object.__setattr__(self, "cov", _frozen(self.cov, (MAG_PARAMS.size, MAG_PARAMS.size)))
        object.__setattr__(self, "dip_deg", float(self.dip_deg))
        object.__setattr__(self, "field_strength", float(self.field_strength))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, MagCalibration):
            return NotImplemented
        return all(_eq(getattr(self, k), getattr(other, k)) for k in self.__dataclass_fields__)

    __hash__ = None  # type: ignore[assignment]

    @property
    def A(self) -> FloatArray:
        """The correction matrix D^-1."""
        a: FloatArray = np.linalg.inv(self.D).astype(np.float64)
        return a

    @property
    def b(self) -> FloatArray:
        """The hard-iron offset subtracted before A."""
        return self.o

    def apply(self, y: npt.ArrayLike) -> FloatArray:
        """Calibrated unit field in the IMU body frame, m_b = A (y - b), of (N, 3) raw readings in `unit`."""
        return (np.asarray(y, dtype=np.float64) - self.o) @ self.A.T

    def distort(self, m_b: npt.ArrayLike) -> FloatArray:
        """The raw reading D m_b + o that a body-frame unit field m_b (N, 3) produces."""
        return np.asarray(m_b, dtype=np.float64) @ self.D.T + self.o

    @property
    def dip(self) -> float:
        """Dip angle in radians (positive down)."""
        return float(np.deg2rad(self.dip_deg))

    @property
    def m_n(self) -> FloatArray:
        """Unit field in the nav frame (NED): [cos dip, 0, sin dip]."""
        return np.array([np.cos(self.dip), 0.0, np.sin(self.dip)])

    @property
    def misalignment(self) -> FloatArray:
        """The rotation factor U of the polar decomposition D = U P."""
        return so3.polar(self.D)[0]

    @property
    def soft_iron(self) -> FloatArray:
        """P / field_strength, with P the symmetric factor of D = U P."""
        return so3.polar(self.D)[1] / self.field_strength

    @property
    def std(self) -> FloatArray:
        """Marginal standard deviations of theta_m (MAG_PARAMS order)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def std_of(self, name: str) -> FloatArray:
        """Marginal standard deviations of block `name` in its shape: D (3, 3), o (3,), dip () in degrees."""
        return MAG_PARAMS.value(self.std, name)

    def cov_of(self, *names: str) -> FloatArray:
        """The joint covariance of the named blocks (MAG_PARAMS names: "D", "o", "dip"), in the order given."""
        cols = MAG_PARAMS.cols(*names)
        out: FloatArray = self.cov[np.ix_(cols, cols)]
        return out

    def misalignment_cov(self) -> FloatArray:
        """Covariance (rad^2) of the right perturbation w of U (U <- U Exp(w)), propagated from cov of D.

        With X = U^T dD, the skew part of D = U P gives [w]x P + P [w]x = X - X^T, i.e.
        (tr(P) I - P) w = vee(X - X^T) (first-order polar-decomposition sensitivity).
        """
        u, p = so3.polar(self.D)
        m = np.linalg.inv(np.trace(p) * np.eye(3) - p)
        d_block = MAG_PARAMS.block("D")
        jac = np.zeros((3, d_block.size))
        for col in range(d_block.size):
            dd = np.zeros(d_block.size)
            dd[col] = 1.0
            x = u.T @ d_block.unflatten(dd)
            jac[:, col] = m @ (2.0 * so3.vee(x))
        return jac @ self.cov_of("D") @ jac.T


@dataclass(frozen=True, eq=False)
class ImuCalibration:
    """Accelerometer (m/s^2) and gyroscope (rad/s) biases; None where the method does not estimate them."""

    kind: ClassVar[str] = "imu"

    id: str
    accelerometer_bias: FloatArray | None = None
    gyroscope_bias: FloatArray | None = None
    accelerometer_bias_std: FloatArray | None = None
    gyroscope_bias_std: FloatArray | None = None

    def __post_init__(self) -> None:
        for name in ("accelerometer_bias", "gyroscope_bias", "accelerometer_bias_std", "gyroscope_bias_std"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _frozen(value, (3,)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ImuCalibration):
            return NotImplemented
        return all(_eq(getattr(self, k), getattr(other, k)) for k in self.__dataclass_fields__)

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Source:
    """Where the calibration came from: the log, its format and hash, the time span used (s)."""

    path: str
    format: str
    sha256: str
    start_s: float
    end_s: float
    #: what each sample was taken to stand for: {"imu", "magnetometer": "instant|preceding|following", "set_by"}
    timing: dict[str, str] = field(default_factory=dict)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Source) and self.__dict__ == other.__dict__


@dataclass(frozen=True, eq=False)
class Calibration:
    """A whole calibration document (`magcal.calibration/1`): one IMU and its magnetometers."""

    SCHEMA: ClassVar[str] = "magcal.calibration/1"

    source: Source
    method: str
    imu: ImuCalibration
    magnetometers: tuple[MagCalibration, ...]
    magcal_version: str
    created_utc: str
    noise: dict[str, Any] = field(default_factory=dict)
    effects: tuple[dict[str, Any], ...] = ()
    diagnosis: dict[str, Any] | None = None
    notes: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)   # further top-level keys, kept on round trips
    #: the magnetometers of the log no method could calibrate: {"id", "status": "refused", "reason", "advice"}
    refused: tuple[dict[str, str], ...] = ()

    def __post_init__(self) -> None:
        # a magnetometer without its own method was calibrated by the document's
        object.__setattr__(self, "magnetometers", tuple(m if m.method else replace(m, method=self.method)
                                                        for m in self.magnetometers))
        object.__setattr__(self, "refused", tuple(self.refused))
        object.__setattr__(self, "effects", tuple(self.effects))
        object.__setattr__(self, "notes", tuple(self.notes))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return all(_eq(getattr(self, k), getattr(other, k)) for k in self.__dataclass_fields__)

    __hash__ = None  # type: ignore[assignment]

    def magnetometer(self, mag_id: str | None = None) -> MagCalibration:
        """The magnetometer with `mag_id` (the first when None)."""
        from magcal_cli.errors import CalibrationFileError

        for mag in self.magnetometers:
            if mag_id is None or mag.id == mag_id:
                return mag
        msg = (f"calibration: no magnetometer {mag_id!r}; it has "
               f"{', '.join(m.id for m in self.magnetometers) or 'none'}. Use --mag with one of them.")
        raise CalibrationFileError(msg)
