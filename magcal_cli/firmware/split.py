"""What firmware can hold of a correction A, what is lost, and the heading error the loss causes.

A maps a raw reading minus its offset to the body-frame field (A = F D^-1, firmware-export.md section 3).
ArduPilot applies a rotation, then a symmetric matrix: A_fw = Ms V (Ms = SCALE x [DIA/ODI]); PX4 applies a
symmetric matrix, then the rotation: A_fw = R S. The rotation is an enum, custom Euler angles, or fixed by the
board (internal compasses). With the rotation fixed, the closest symmetric factor (Frobenius) is sym(A V^T),
respectively sym(R^T A) (section 3). What remains is the residual E = A_fw A^-1: the firmware outputs E b where
magcal's calibration gives b.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from magcal_cli import so3
from magcal_cli.firmware import rotations
from magcal_cli.streams import FloatArray

#: headings (deg) at which the heading error of a level vehicle is evaluated
HEADINGS_DEG = np.arange(0.0, 360.0, 1.0)


def sym(m: FloatArray) -> FloatArray:
    """The symmetric part (m + m^T) / 2."""
    return 0.5 * (m + m.T)


@dataclass(frozen=True, eq=False)
class Rotation:
    """The rotation the firmware will apply: an enum id, custom Euler angles (deg) or fixed by the board."""

    kind: str                                   # "enum", "custom" or "fixed"
    matrix: FloatArray                          # absolute (the parameter's own matrix, sensor to body)
    enum_id: int | None = None
    rpy_deg: tuple[float, float, float] | None = None
    enum_residual_deg: float | None = None      # angle between the wanted rotation and the nearest enum


@dataclass(frozen=True, eq=False)
class Split:
    """A_fw = held, the rotation chosen, the symmetric factor and the residual E = A_fw A^-1."""

    rotation: Rotation
    symmetric: FloatArray
    held: FloatArray
    residual: FloatArray
    wanted_rpy_deg: tuple[float, float, float]

    @property
    def residual_angle_deg(self) -> float:
        """Angle of the rotation factor of E: the misalignment the firmware cannot represent."""
        return float(np.rad2deg(so3.angle(so3.polar(self.residual)[0])))

    @property
    def max_error_pct(self) -> float:
        """Largest |E b - b| / |b| over all field directions (spectral norm of E - I), in %."""
        return float(100.0 * np.linalg.norm(self.residual - np.eye(3), 2))

    def heading_error_deg(self, dip_deg: float) -> float:
        """Largest heading error the residual causes on a level vehicle, over all headings."""
        return heading_error_deg(self.residual, np.zeros(3), dip_deg)


def choose_rotation(firmware: str, wanted: FloatArray, *, fixed: FloatArray | None, custom: bool,
                    custom_above_deg: float, ids: Sequence[int] = rotations.EXPORTABLE) -> Rotation:
    """The rotation closest to `wanted` that the firmware can hold.

    `fixed` (internal compass): that matrix, nothing to choose. Otherwise the nearest enum, replaced by
    custom Euler angles when `custom` is allowed and the enum misses by more than `custom_above_deg`.
    """
    if fixed is not None:
        return Rotation("fixed", np.asarray(fixed, dtype=np.float64))
    enum_id, miss = rotations.nearest(firmware, wanted, ids)
    if custom and miss > custom_above_deg:
        rpy = tuple(round(v, 4) for v in rotations.euler_deg(wanted))   # firmware floats: 4 decimals of a degree
        return Rotation("custom", so3.from_rpy(np.deg2rad(rpy)), None, rpy, miss)  # type: ignore[arg-type]
    return Rotation("enum", rotations.matrix(firmware, enum_id), enum_id, None, miss)


def split_rotation_first(A: FloatArray, effective: FloatArray, rotation: Rotation, wanted: FloatArray) -> Split:
    """ArduPilot: A_fw = Ms V with V the rotation change `effective`; Ms = sym(A V^T)."""
    ms = sym(A @ effective.T)
    held = ms @ effective
    return Split(rotation, ms, held, held @ np.linalg.inv(A), rotations.euler_deg(wanted))


def split_symmetric_first(A: FloatArray, effective: FloatArray, rotation: Rotation, wanted: FloatArray) -> Split:
    """PX4: A_fw = R S with R the whole rotation `effective`; S = sym(R^T A)."""
    s = sym(effective.T @ A)
    held = effective @ s
    return Split(rotation, s, held, held @ np.linalg.inv(A), rotations.euler_deg(wanted))


def heading_error_deg(E: npt.ArrayLike, offset: npt.ArrayLike, dip_deg: float,
                      headings_deg: FloatArray = HEADINGS_DEG) -> float:
    """Largest |heading error| (deg) of a level vehicle whose compass reads E b + offset for the true field b.

    b is the unit Earth field [cos dip, 0, sin dip] seen at heading psi: b = Rz(psi)^T b_n; `offset` is in
    units of the field strength. The heading a level vehicle computes is atan2(-m_y, m_x).
    """
    return float(np.max(np.abs(heading_errors_deg(E, offset, dip_deg, headings_deg))))


def heading_errors_deg(E: npt.ArrayLike, offset: npt.ArrayLike, dip_deg: float,
                       headings_deg: FloatArray = HEADINGS_DEG) -> FloatArray:
    """Signed heading error (deg) at each heading, as in `heading_error_deg`."""
    psi = np.deg2rad(headings_deg)
    dip = np.arctan2(np.sin(np.deg2rad(dip_deg)), abs(np.cos(np.deg2rad(dip_deg))))  # |dip| > 90: north flipped
    b = np.stack([np.cos(dip) * np.cos(psi), -np.cos(dip) * np.sin(psi), np.full_like(psi, np.sin(dip))], axis=1)
    m = b @ np.asarray(E, dtype=np.float64).T + np.asarray(offset, dtype=np.float64)
    err = np.arctan2(-m[:, 1], m[:, 0]) - psi
    return np.rad2deg(np.angle(np.exp(1j * err)))
