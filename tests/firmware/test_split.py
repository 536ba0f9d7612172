"""The split's heading-error measure against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli import so3
from magcal_cli.firmware.split import heading_error_deg, heading_errors_deg


def test_identity_has_no_heading_error() -> None:
    assert heading_error_deg(np.eye(3), np.zeros(3), 65.0) == pytest.approx(0.0, abs=1e-12)


def test_a_yaw_rotation_is_a_constant_heading_error() -> None:
    """A compass yawed by a reads every heading off by a (sign: the body field turns the other way)."""
    e = heading_errors_deg(so3.exp(np.deg2rad([0.0, 0.0, 3.0])), np.zeros(3), 65.0)
    assert np.allclose(e, -3.0)


def test_a_horizontal_offset_gives_asin_of_offset_over_horizontal_field() -> None:
    """Offset d (field units) at dip 60: the worst error is asin(d / cos 60)."""
    assert heading_error_deg(np.eye(3), [0.05, 0.0, 0.0], 60.0) == pytest.approx(np.rad2deg(np.arcsin(0.1)),
                                                                                 rel=1e-4)


def test_a_tilt_acts_like_an_offset_of_tilt_times_vertical_field() -> None:
    """A 2 deg pitch of the compass at dip 66 moves x by sin(2 deg) Z: error asin(tan 66 sin 2 deg)."""
    got = heading_error_deg(so3.exp(np.deg2rad([0.0, 2.0, 0.0])), np.zeros(3), 66.0)
    assert got == pytest.approx(np.rad2deg(np.arcsin(np.tan(np.deg2rad(66)) * np.sin(np.deg2rad(2)))), rel=0.02)


def test_dip_beyond_90_is_the_same_field_with_north_flipped() -> None:
    """A document dip of -114 deg means the field points south-up: heading errors as for dip -66."""
    E = np.diag([1.02, 0.98, 1.0])
    assert heading_error_deg(E, np.zeros(3), -114.0) == pytest.approx(heading_error_deg(E, np.zeros(3), -66.0))
