"""Why a candidate effect was rejected, in words that agree with its p-value (issue 30 item 4)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from magcal_cli.diagnose import select as select_module
from magcal_cli.diagnose.score import Score, Screen


def _select(monkeypatch: pytest.MonkeyPatch, p_values: dict[str, float]) -> dict[str, Any]:
    """`select` on a screen whose candidates have these p-values and no significant one: no fit runs."""
    scores = tuple(Score(eid, 1.0, 1.0, 3, p) for eid, p in p_values.items())
    monkeypatch.setattr(select_module, "screen", lambda *a, **k: Screen(scores, (), {}))
    problem = SimpleNamespace(imu_id="IMU[0]", where="log.bin")
    mag = SimpleNamespace(id="MAG[0]")
    base = SimpleNamespace(effects=())
    sel = select_module.select(problem, mag, base, tuple(p_values))  # type: ignore[arg-type]
    return {v.id: v for v in sel.verdicts}


def test_a_p_below_five_percent_is_not_called_no_sign(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 30: 'rejected; score test p = 0.032. the score test found no sign of it (p = 0.032)'. With three
    candidates Holm's first step needs p <= 0.017, so 0.032 is rejected as too weak once corrected for testing three
    effects at once; a p of 0.4 is no sign at all. The reason no longer repeats the p the report prints beside it."""
    verdicts = _select(monkeypatch, {"temperature_drift": 0.032, "current_interference": 0.4,
                                     "throttle_interference": 0.2})
    weak = verdicts["temperature_drift"]
    assert weak.status == "rejected" and weak.p_value == pytest.approx(0.032)
    assert "no sign" not in weak.reason and "p =" not in weak.reason
    assert weak.reason == "too weak once corrected for testing 3 effects at once (Holm's method, 5 % for all of them " \
                          "together)"
    assert verdicts["current_interference"].reason == "the score test found no sign of it"
    assert all(np.isfinite(v.p_value) for v in verdicts.values())


def test_only_nesting_pairs_are_refitted_for_rivalry(monkeypatch: pytest.MonkeyPatch) -> None:
    """issue 28: `_beyond` refits only where the added effect nests the other (per-motor fields nest throttle and
    current); any other pair keeps the canonical-correlation rule without a fit. The nesting term must also pass the
    backward step's BIC bar."""
    calls: list[tuple[str, ...]] = []

    def fake_fit(*a: Any, effects: tuple[str, ...] = (), **k: Any) -> object:
        calls.append(effects)
        return object()

    monkeypatch.setattr(select_module, "fit_map", fake_fit)
    monkeypatch.setattr(select_module, "screen", lambda *a, **k: Screen((Score("motor_interference", 500.0, 500.0,
                                                                               12, 1e-9),), (), {}))
    monkeypatch.setattr(select_module, "n_eff", lambda est: 100.0)        # 500 - 12 ln 100 > 6: it pays its way
    est = SimpleNamespace(context=None)
    args = (SimpleNamespace(), SimpleNamespace(), est)
    assert not select_module._beyond(*args, ("current_interference",), "throttle_interference",  # type: ignore[arg-type]
                                     "cauchy", None, 0.0, ())
    assert calls == []
    assert select_module._beyond(*args, ("throttle_interference",), "motor_interference",  # type: ignore[arg-type]
                                 "cauchy", None, 0.0, ())
    assert calls == [("throttle_interference",)]
    monkeypatch.setattr(select_module, "n_eff", lambda est: 1e20)         # 12 ln n_eff > 500: not worth it
    assert not select_module._beyond(*args, ("throttle_interference",), "motor_interference",  # type: ignore[arg-type]
                                     "cauchy", None, 0.0, ())


@pytest.mark.parametrize(("diff", "motor", "throttle"), [(0.08, "accepted", "rejected"),
                                                      (0.003, "ambiguous", "ambiguous")])
def test_per_motor_fields_accepted_with_differential_thrust_ambiguous_without(diff: float, motor: str,
                                                                                throttle: str) -> None:
    """issue 28: a simulated quad with four different per-motor field vectors. With differential thrust (turns,
    attitude changes: diff 0.08) `--effects auto` accepts motor_interference (held-out gain above zero; estimates
    within 10 % of the 0.3-0.9 uT truth) and rejects throttle, which its term nests. With the motors moving
    (almost) together (diff 0.003) the two are `ambiguous` and the simpler throttle term is the one carried."""
    from magcal_cli.pipeline import calibrate_recording, command_config
    from magcal_cli.synth.effects import EffectSpec
    from magcal_cli.synth.simulate import simulate

    c = {"c1": (9e-7, -4.5e-7, 6e-7), "c2": (-7.5e-7, 6e-7, 3e-7), "c3": (3e-7, 9e-7, -6e-7), "c4": (-6e-7, -7.5e-7, 7.5e-7)}
    sim = simulate("multirotor", 5, duration=100.0, effects=(EffectSpec("motor_interference", {"diff": diff} | c),))
    got = {e["id"]: e for e in calibrate_recording(sim.recording, command_config()).calibration.effects}
    assert (got["motor_interference"]["status"], got["throttle_interference"]["status"]) == (motor, throttle)
    if motor == "accepted":
        assert got["motor_interference"]["evidence"]["heldout_gain_ci95"][0] > 0
        est = np.array([got["motor_interference"]["params"][k] for k in c])
        assert np.max(np.abs(est - np.array(list(c.values())))) < 0.1 * 9e-7
    else:
        assert got["motor_interference"]["confounded_with"] == ["throttle_interference"]
        assert "c" in got["throttle_interference"]["params"] and not got["motor_interference"]["params"]


def test_log171_mag0_keeps_its_interference_after_the_per_motor_term_is_dropped(realdata: Path) -> None:
    """Issue 28 regression: on log171's MAG[0] the per-motor fields were added first (keeping throttle and current
    out as terms they nest), then dropped once the lag was modelled, and nothing screened throttle and current again:
    the compass lost its interference term. The selection now goes on from what stayed."""
    from magcal_cli.config import Config
    from magcal_cli.pipeline import calibrate

    res = calibrate(realdata / "ardupilot" / "log171.bin", Config(diagnose=True, mag="MAG[0]"))
    status = {e["id"]: e["status"] for e in res.calibration.effects if e["sensor"] == "MAG[0]"}
    assert status["motor_interference"] == "rejected"
    assert status["throttle_interference"] in ("accepted", "ambiguous")
    assert status["current_interference"] in ("accepted", "ambiguous")


def test_a_forward_rounds_trial_fit_is_made_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """`_beyond`'s fit with the nested term is the forward step's fit when that term is then added: one fit per
    round and effects (a failure too is remembered, and raised again)."""
    calls: list[tuple[str, ...]] = []

    def fake(*_a: object, effects: tuple[str, ...] = (), **_k: object) -> object:
        calls.append(effects)
        if effects == ("bad",):
            raise np.linalg.LinAlgError("singular")
        return SimpleNamespace(effects=effects)

    monkeypatch.setattr(select_module, "fit_map", fake)
    fits: select_module.Trials = {}
    est = SimpleNamespace(context=None)
    args = (None, None, est, ("throttle_interference",), "l2", None, 0.0, ())
    first = select_module._trial(*args, fits)  # type: ignore[arg-type]
    assert select_module._trial(*args, fits) is first  # type: ignore[arg-type]
    for _ in range(2):
        with pytest.raises(np.linalg.LinAlgError):
            select_module._trial(None, None, est, ("bad",), "l2", None, 0.0, (), fits)  # type: ignore[arg-type]
    assert calls == [("throttle_interference",), ("bad",)]
    select_module._trial(*args, {})  # type: ignore[arg-type]
    assert len(calls) == 3                                   # a new round (a new start) fits again
