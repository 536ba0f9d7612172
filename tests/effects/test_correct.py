"""Removing fitted magnetometer effects from readings (`effects.correct.remove`)."""

from __future__ import annotations

import numpy as np

from magcal_cli.effects.correct import remove
from magcal_cli.streams import Kind
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.simulate import simulate


def test_an_unmodelled_ambiguous_entry_is_left_alone() -> None:
    """An ambiguous rival the fit did not model carries constants (a reference temperature) but no estimate: it
    is not removed, and it must not crash the fit (exit 123, KeyError 'k', in 2 of 40 inseparable suite runs)."""
    rec = simulate("handheld", 1, duration=60.0, effects=(EffectSpec("temperature_drift"),)).recording
    mag = rec.select(Kind.MAGNETOMETER)
    entries = [{"id": "temperature_drift", "sensor": mag.id, "status": "ambiguous", "params": {"T0": 25.0},
                "channels": []},
               {"id": "current_interference", "sensor": mag.id, "status": "ambiguous", "params": {}}]
    t, y, notes = remove(entries, mag.id, rec, mag.t, mag.xyz, ("accepted", "ambiguous"))
    assert np.array_equal(y, mag.xyz) and np.array_equal(t, mag.t) and notes == []
    fitted = [{**entries[0], "params": {"k": [1e-8, 0.0, 0.0], "T0": 25.0}}]
    _, y2, notes2 = remove(fitted, mag.id, rec, mag.t, mag.xyz, ("accepted", "ambiguous"))
    assert notes2 == [f"{mag.id}: temperature_drift removed"] and not np.array_equal(y2, mag.xyz)


def test_the_per_motor_term_is_removed_exactly() -> None:
    """issue 28: motor_interference's correct reads all four motor streams (one per motor) and the voltage: with the
    true c it removes exactly the injected term."""
    sim = simulate("handheld", 1, duration=60.0, effects=(EffectSpec("motor_interference"),))
    rec, inj = sim.recording, sim.effects[0]
    mag = rec.select(Kind.MAGNETOMETER)
    entry = {"id": "motor_interference", "sensor": mag.id, "status": "accepted", "channels": [],
             "params": {k: list(v) for k, v in inj.params.items() if k.startswith("c")} | {"expo": 0.65}}
    _, y, notes = remove([entry], mag.id, rec, mag.t, mag.xyz)
    assert notes == [f"{mag.id}: motor_interference removed"]
    assert np.max(np.abs((mag.xyz - y) - inj.signals["term"])) < 1e-12 + 1e-3 * np.max(np.abs(inj.signals["term"]))
