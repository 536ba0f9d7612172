"""Rotation enums: generated from the angle tables, checked against the firmware's axis permutations."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_cli.firmware import FirmwareError, rotations

from . import fwsim


def test_axis_permutation_examples() -> None:
    """ArduPilot vector3.cpp: YAW_90 is x' = -y, y' = x; ROLL_90 is y' = -z, z' = y (design note section 1)."""
    v = np.array([1.0, 2.0, 3.0])
    for fw in rotations.FIRMWARES:
        assert np.allclose(rotations.matrix(fw, 2) @ v, [-2.0, 1.0, 3.0], atol=1e-15)
        assert np.allclose(rotations.matrix(fw, 16) @ v, [1.0, -3.0, 2.0], atol=1e-15)
        assert np.allclose(rotations.matrix(fw, 8) @ v, [1.0, -2.0, -3.0], atol=1e-15)      # ROLL_180
        assert np.allclose(rotations.matrix(fw, 24) @ v, [3.0, 2.0, -1.0], atol=1e-15)      # PITCH_90


@pytest.mark.parametrize("fw", rotations.FIRMWARES)
def test_every_common_id_matches_the_independent_table(fw: str) -> None:
    """Ids 0..40 (not 38) equal Rz(yaw) Ry(pitch) Rx(roll) from the test's own table, in both firmwares."""
    for rot_id, angles in fwsim.ANGLES.items():
        assert np.allclose(rotations.matrix(fw, rot_id), fwsim.euler(*angles), atol=1e-14), rot_id


def test_the_special_38() -> None:
    """ArduPilot 38 is vector3.cpp's explicit matrix ("actually roll 90, pitch 68.8, yaw 293.3"); PX4's is the
    integer angles (90, 68, 293), 0.85 deg away."""
    ap, px = rotations.matrix("ardupilot", 38), rotations.matrix("px4", 38)
    assert np.allclose(ap @ ap.T, np.eye(3), atol=1e-15) and np.linalg.det(ap) == pytest.approx(1.0)
    assert np.allclose(ap, fwsim.euler(90, 68.8, 293.3), atol=1e-6)
    assert np.allclose(px, fwsim.euler(90, 68, 293), atol=1e-14)
    assert rotations.nearest("px4", ap)[0] == 38
    assert np.rad2deg(np.arccos((np.trace(ap.T @ px) - 1) / 2)) == pytest.approx(0.854, abs=0.001)


def test_firmware_specific_ids() -> None:
    """41..43 differ: ArduPilot PITCH_7, ROLL_45, ROLL_315; PX4 ROLL_270_YAW_180 .. ROLL_270_YAW_315 up to 47."""
    assert np.allclose(rotations.matrix("ardupilot", 41), fwsim.euler(0, 7, 0))
    assert np.allclose(rotations.matrix("ardupilot", 43), fwsim.euler(315, 0, 0))
    assert np.allclose(rotations.matrix("px4", 41), fwsim.euler(270, 0, 180))
    assert np.allclose(rotations.matrix("px4", 47), fwsim.euler(270, 0, 315))
    assert rotations.name("px4", 45) == "ROTATION_PITCH_45"


def test_nearest_finds_each_enum_and_measures_the_miss() -> None:
    """Each enum is its own nearest (or an identical twin such as 10 = 27); a 3 deg tilt is a 3 deg miss."""
    for rot_id in rotations.EXPORTABLE:
        found, miss = rotations.nearest("ardupilot", rotations.matrix("ardupilot", rot_id))
        assert miss < 1e-6 and np.allclose(rotations.matrix("ardupilot", found), rotations.matrix("ardupilot", rot_id))
    found, miss = rotations.nearest("px4", fwsim.enum(4) @ fwsim.rx(3.0))
    assert found == 4 and miss == pytest.approx(3.0)


def test_euler_round_trip() -> None:
    """euler_deg is the inverse of Rz Ry Rx."""
    assert np.allclose(rotations.euler_deg(fwsim.euler(10, -20, 30)), (10, -20, 30))


def test_unknown_ids_and_firmwares_are_errors() -> None:
    """Messages name the enum range and the known firmwares."""
    with pytest.raises(FirmwareError, match=r"ardupilot rotation 44 is not in the enum \(0\.\.43\); check the "
                                            r"orientation parameter"):
        rotations.matrix("ardupilot", 44)
    with pytest.raises(FirmwareError, match="firmware 'inav' is not known; use one of ardupilot, px4"):
        rotations.table("inav")
