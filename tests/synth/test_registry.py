"""The simulator's effects (synth.effects.EFFECTS, synth.inject.INJECTIONS) tied to the estimator's plug-ins
(magcal_cli.effects.EFFECTS): a simulated effect is its plug-in, its injection and one registry line (issue 26)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from magcal_cli import so3
from magcal_cli.effects import EFFECTS as ESTIMATOR_EFFECTS
from magcal_cli.effects import get as estimator_effect
from magcal_cli.effects.base import Target
from magcal_cli.synth.effects import EFFECTS, POWER_CHANNELS, POWER_EFFECTS, EffectDef, EffectSpec
from magcal_cli.synth.inject import INJECTIONS
from magcal_cli.synth.simulate import simulate

#: estimator effects (magcal_cli.effects.EFFECTS) that magcal simulate cannot inject
NOT_SIMULATED: tuple[str, ...] = ()
#: simulated effects that name no estimator effect
SIMULATOR_ONLY: tuple[str, ...] = ()


def mismatches(simulated: Mapping[str, EffectDef], estimator: Mapping[str, str],
               injections: Mapping[str, object]) -> list[str]:
    """Where the simulated effects, their injections and the estimator's plug-ins disagree (empty: tied)."""
    out = [f"simulated {e} is no estimator effect" for e in simulated
           if e not in estimator and e not in SIMULATOR_ONLY]
    out += [f"estimator effect {e} is not simulated" for e in estimator
            if e not in simulated and e not in NOT_SIMULATED]
    out += [f"{e} is listed as not simulated but is" for e in NOT_SIMULATED if e in simulated]
    out += [f"{e} is listed as simulator-only but is an estimator effect" for e in SIMULATOR_ONLY if e in estimator]
    out += [f"simulated {e} has no injection" for e in simulated if e not in injections]
    out += [f"injection {e} is no simulated effect" for e in injections if e not in simulated]
    for e in (e for e in simulated if e in estimator):
        plugin = estimator_effect(e)
        if simulated[e].channels != tuple(k.value for k in plugin.channels):
            out.append(f"{e}: the simulator logs {simulated[e].channels}, the estimator reads {plugin.channels}")
        if (simulated[e].sensor == "magnetometer") != (plugin.target is Target.MAG):
            out.append(f"{e}: the simulator puts it on the {simulated[e].sensor}, the estimator on {plugin.target}")
    return out


def test_simulated_effects_are_the_estimators_and_each_has_an_injection() -> None:
    """Every simulated effect is an estimator effect with its channels and sensor, the estimator effects the
    simulator cannot inject are NOT_SIMULATED (none today), and each simulated effect has its line in INJECTIONS."""
    assert NOT_SIMULATED == ()
    assert SIMULATOR_ONLY == ()
    assert mismatches(EFFECTS, ESTIMATOR_EFFECTS, INJECTIONS) == []


def test_the_tie_fails_when_one_side_changes() -> None:
    """The tie can fail: an effect missing on either side, an injection missing or extra, other channels or sensor."""
    fake = EffectDef("imu", (), (), {}, "")
    assert mismatches({**EFFECTS, "wobble": fake}, ESTIMATOR_EFFECTS, {**INJECTIONS, "wobble": print}) == [
        "simulated wobble is no estimator effect"]
    assert mismatches({k: v for k, v in EFFECTS.items() if k != "lever_arm"}, ESTIMATOR_EFFECTS, INJECTIONS) == [
        "estimator effect lever_arm is not simulated", "injection lever_arm is no simulated effect"]
    assert mismatches(EFFECTS, ESTIMATOR_EFFECTS, {k: v for k, v in INJECTIONS.items() if k != "gyro_scale"}) == [
        "simulated gyro_scale has no injection"]
    moved = {**EFFECTS, "time_offset": replace(EFFECTS["time_offset"], sensor="imu", channels=("temperature",))}
    assert mismatches(moved, ESTIMATOR_EFFECTS, INJECTIONS) == [
        "time_offset: the simulator logs ('temperature',), the estimator reads ()",
        "time_offset: the simulator puts it on the imu, the estimator on Target.MAG"]


def test_power_effects_are_the_injections_that_log_the_power_system() -> None:
    """POWER_EFFECTS (whose motors vibrate the IMU) are exactly the effects whose injection logs POWER_CHANNELS."""
    knots = so3.exp(np.arange(201)[:, None] / 100.0 * np.array([0.3, -0.5, 0.8]))     # 2 s at a constant rate
    for eid in EFFECTS:
        sim = simulate("paper", 5, rate=100.0, noise_scale=0.0, trajectory=knots, effects=(EffectSpec(eid),))
        logged = {s.kind.value for s in sim.recording.streams} & set(POWER_CHANNELS)
        assert logged == (set(POWER_CHANNELS) if eid in POWER_EFFECTS else set()), eid
    assert POWER_EFFECTS == ("current_interference", "throttle_interference", "motor_interference")
