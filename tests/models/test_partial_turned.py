"""Issue 38 item 3 on its 3-compass shape (tests/firmware/flightsim.py `three_compass_flight`): what a full turn
determines is estimated, and what stays held reports its prior's std.

An ArduCopter 3.5 quad turned through ~395 deg of heading with tilt within 16 deg; its internal compasses carry a
disturbance no logged channel explains, so their residuals are correlated in time and the sandwich widens the data's
information. Before the fix the partial path held MAG[1]'s o[1] (the choice judged the widened information against
a 68 mG prior, the 180 deg rule of issue 25 applied only to the narrow-cap pins), and reported it with 21 mG: the
soft prior's posterior, not the prior's own doubt.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from magcal_cli import so3
from magcal_cli.cli.main import cli
from magcal_cli.firmware.split import heading_errors_deg

from ..firmware.flightsim import ThreeCompass, three_compass_flight

#: the horizontal offsets in the body frame (the log is level within 16 deg, FRD axes as ArduPilot logs them)
HORIZONTAL = ("o[0]", "o[1]")


@pytest.fixture(scope="module")
def flight_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ThreeCompass]:
    """The simulated flight (seed 0) and its truth; the flight is the issue's shape (full yaw, tilt within 16 deg,
    one still segment, 700 mG of hard iron on the uncalibrated compass)."""
    path, truth = three_compass_flight(tmp_path_factory.mktemp("copter35"), seed=0)
    assert truth.yaw_deg >= 360.0 and truth.tilt_deg <= 16.0 and len(truth.still) == 1
    assert np.linalg.norm(truth.o[1]) == pytest.approx(700.0, rel=0.01)
    return path, truth


def _fit(path: Path, *options: str) -> dict[str, Any]:
    """`magcal fit` with the options; the calibration document."""
    out = path.parent / ("fit" + "".join(options).replace("-", "_"))
    res = CliRunner().invoke(cli, ["fit", str(path), "-o", str(out), "--outputs", "json", "-q", *options])
    assert res.exit_code == 0, res.output
    doc: dict[str, Any] = json.loads((out / "calibration.json").read_text(encoding="utf-8"))
    return doc


@pytest.fixture(scope="module")
def flight(flight_log: tuple[Path, ThreeCompass]) -> tuple[dict[str, Any], ThreeCompass]:
    """The default fit of the simulated flight and its truth."""
    return _fit(flight_log[0]), flight_log[1]


def test_horizontal_offsets_are_estimated_within_three_std(flight: tuple[dict[str, Any], ThreeCompass]) -> None:
    """Issue 25 item 5 on every path: every compass is calibrated, and one turned through >= 180 deg of heading
    gets o[0], o[1] estimated (never in `held`), their truth within 3 of their reported stds."""
    doc, truth = flight
    assert [m["id"] for m in doc["magnetometers"]] == ["MAG[0]", "MAG[1]", "MAG[2]"]
    assert not doc.get("refused")
    for k, m in enumerate(doc["magnetometers"]):
        held = {h["parameter"] for h in m["held"]}
        assert not held & set(HORIZONTAL), (m["id"], sorted(held))
        z = (np.array(m["o"][:2]) - truth.o[k][:2]) / np.array(m["std"]["o"][:2])
        assert np.all(np.abs(z) < 3.0), (m["id"], z)


def test_a_held_entry_reports_its_prior_std(flight: tuple[dict[str, Any], ThreeCompass]) -> None:
    """Whatever stays held has its prior's std in the document (std and covariance), not the soft prior's much
    smaller posterior; this flight holds part of MAG[2]'s D."""
    _held_stds_are_priors(flight[0])


def test_the_attitude_method_reports_held_priors_too(flight_log: tuple[Path, ThreeCompass]) -> None:
    """The same on the attitude path (`--method attitude`, which holds part of MAG[2]'s D here): it reported the
    soft prior's posterior times the axis's widening (36-112 mG for a 29 mG prior)."""
    _held_stds_are_priors(_fit(flight_log[0], "--method", "attitude"))


def test_the_attitude_method_never_holds_a_turned_offset() -> None:
    """`_held_fit` would hold an offset whose prior is far tighter than the data; not one of `free` (a horizontal
    axis after a half turn, `turned_axes`): that one is estimated, its prior a prior, not a pin."""
    from magcal_cli.models.attitude_ref import _held_fit, turned_axes

    rng = np.random.default_rng(3)
    u = rng.normal(size=(400, 3))
    x = np.column_stack([u, np.ones(400)])
    y = u @ [1.0, 0.1, -0.2] + 0.5 + rng.normal(0.0, 1.0, 400)
    mean, var = np.array([1.0, 0.1, -0.2, 0.0]), np.array([1.0, 1.0, 1.0, 1e-6])
    blocks = np.arange(400) // 40
    assert 3 in _held_fit(x, y, mean, var, blocks)[1]
    _, held = _held_fit(x, y, mean, var, blocks, (3,))
    assert 3 not in held
    level = so3.from_rpy(np.column_stack([np.zeros(50), np.zeros(50), np.linspace(0.0, np.pi, 50)]))
    assert turned_axes(level) == (0, 1)
    assert turned_axes(level[:20]) == ()


def _held_stds_are_priors(doc: dict[str, Any]) -> None:
    """Every held D or o entry's std and covariance diagonal equal its prior_std."""
    held = [(m, h) for m in doc["magnetometers"] for h in m["held"]]
    assert held
    for m, h in held:
        name = h["parameter"]
        if name.startswith("D["):
            i, j = int(name[2]), int(name[5])
            sd, at = m["std"]["D"][i][j], 3 * j + i           # cov order: vec(D) column-major, o, dip_deg
        elif name.startswith("o["):
            sd, at = m["std"]["o"][int(name[2])], 9 + int(name[2])
        else:
            continue
        assert sd == pytest.approx(h["prior_std"], rel=1e-6), (m["id"], name)
        assert np.sqrt(m["covariance"]["matrix"][at][at]) == pytest.approx(h["prior_std"], rel=1e-6), (m["id"], name)


def test_heading_against_the_truth(flight: tuple[dict[str, Any], ThreeCompass]) -> None:
    """Level heading error of each calibration over a full turn (its mean removed): MAG[0] (no disturbance beyond
    what is modelled) within 0.5 deg; the disturbed uncalibrated MAG[1] within 6 deg (17 deg with o[1] held) and
    MAG[2] within 12 deg, the limit its 15 mG wandering disturbance leaves on a 220 mG horizontal field."""
    doc, truth = flight
    for k, (m, limit) in enumerate(zip(doc["magnetometers"], (0.5, 6.0, 12.0), strict=True)):
        a, b = np.array(m["A"]), np.array(m["b"])
        e = heading_errors_deg(a @ truth.D[k], a @ (truth.o[k] - b), truth.dip_deg)
        assert np.max(np.abs(e - e.mean())) < limit, m["id"]
