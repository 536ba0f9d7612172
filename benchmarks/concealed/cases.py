"""The case matrix of the concealed-effect suite (issue 11; design mismatch.md section 7).

Each case is a `magcal simulate` scenario, the effects injected in `--effect ID:key=value` syntax (zero-valued
effects only add their channels: decoys), the ids that should come out `accepted`, the ids `magcal fit
--effects` gets in "explicit" mode, and for an inseparable confusable pair the pair that should come out
`ambiguous`. Clear-tier magnitudes give a median Wald chi^2 of about 60 with `--effects ID` (README.md):
about 0.05-0.2 of the per-sample noise, most of it absorbed by the base calibration (the mean current or
temperature by the offset). Strong tier: the simulator's defaults (visible above the noise).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

#: tiers in report order
TIERS = ("negative", "timing", "flight", "clear", "lag", "strong", "separable", "inseparable")
#: the timing grid (issue 25): IMU and magnetometer rates (Hz), and the IMU convention with the format that holds it
IMU_RATES, MAG_RATES = (50.0, 100.0, 200.0, 400.0), (10.0, 25.0, 50.0, 100.0)
CONVENTIONS = (("instant", ".bin"), ("preceding", ".ulg"))
#: the lag tier's range of true lags (s), drawn log-uniformly
LAG_RANGE_S = (0.005, 0.060)
#: zero-valued effects that only log their channels (current, voltage, throttle; temperature; GPS position)
POWER_DECOY = "current_interference:c_uT_per_A=0/0/0"
TEMPERATURE_DECOY = "temperature_drift:k_uT_per_degC=0/0/0"
POSITION_DECOY = "nongravity_acceleration:sigma_a=0"
#: clear-tier magnitudes (command-line units), calibrated in README.md
CLEAR = {
    "current_interference": "c_uT_per_A=0.0024/-0.0012/0.0036",
    "throttle_interference": "c_uT=0.11/-0.055/0.165",
    "temperature_drift": "k_uT_per_degC=0.0044/-0.0032/0.0064",
    "time_offset": "tau_s=0.002",
    "gyro_scale": "s=0.0015/-0.0012/0.0018",
    "accel_scale": "s=0.0038/-0.0058/0.0028",
    "lever_arm": "r_m=0.010/-0.0065/0.005",
}
#: the natural scenario of each effect: continuous rotation (paper) for power and temperature, hand moves else
SCENARIO = {"current_interference": "paper", "throttle_interference": "paper", "temperature_drift": "paper",
            "time_offset": "handheld", "gyro_scale": "handheld", "accel_scale": "handheld", "lever_arm": "handheld",
            "nongravity_acceleration": "handheld"}


@dataclass(frozen=True)
class Case:
    """One cell of the matrix: what is simulated, what should be accepted, what the explicit fit is given."""

    name: str
    tier: str
    scenario: str
    effects: tuple[str, ...]
    expected: tuple[str, ...]
    candidates: tuple[str, ...]
    ambiguous: tuple[str, ...] = ()
    duration: float = 150.0
    rate: float | None = None
    power_profile: str = "flight"
    note: str = ""
    #: per-seed variation: "" (none), "grid" (rates, phase and convention from the timing grid), "lag" (the grid
    #: plus a true lag drawn from LAG_RANGE_S)
    vary: str = ""
    #: the log's format (suffix) and rates when not varied, further `simulate` keywords, and the firmware the
    #: vehicle flew with (a synth_firmware name: "stale" is STALE_CURRENT_COMPENSATION)
    suffix: str = ".bin"
    mag_rate: float | None = None
    simulate: tuple[tuple[str, object], ...] = ()
    firmware: str = ""

    def settings(self, seed: int) -> Settings:
        """What run `seed` simulates: rates, magnetometer phase, log format and effects."""
        if not self.vary:
            return Settings(self.rate, self.mag_rate, None, self.suffix, self.effects,
                            "preceding" if self.suffix == ".ulg" else "instant")
        combos = [(r, m, c) for c in CONVENTIONS for r in IMU_RATES for m in MAG_RATES]
        imu, mag, (convention, suffix) = combos[seed % len(combos)]
        rng = np.random.default_rng([seed, 25])
        phase = float(rng.uniform(0.0, min(0.005, 1.0 / mag)))
        effects = self.effects
        if self.vary == "lag":
            tau = float(np.exp(rng.uniform(*np.log(LAG_RANGE_S))))
            effects = (f"time_offset:tau_s={tau:.6f}", *effects)
        return Settings(imu, mag, phase, suffix, effects, convention)


class Settings(NamedTuple):
    """One run's simulation settings."""

    rate: float | None
    mag_rate: float | None
    mag_phase_s: float | None
    suffix: str
    effects: tuple[str, ...]
    convention: str = "instant"


def _decoys(eid: str) -> tuple[str, ...]:
    """Channels present but inert: every magnetometer single carries current, throttle, voltage and temperature."""
    if eid in ("current_interference", "throttle_interference"):
        return (TEMPERATURE_DECOY,)
    if eid == "temperature_drift":
        return (POWER_DECOY,)
    return (POWER_DECOY, TEMPERATURE_DECOY) if SCENARIO[eid] == "paper" else (TEMPERATURE_DECOY,)


def _single(eid: str, tier: str, value: str) -> Case:
    spec = f"{eid}:{value}" if value else eid
    return Case(f"{tier}_{eid}", tier, SCENARIO[eid], (spec, *_decoys(eid)), (eid,), (eid,),
                note=f"{eid} {value or '(simulate defaults)'} among decoy channels")


def _cases() -> list[Case]:
    out = [
        Case("neg_clean_paper", "negative", "paper", (), (), ("gyro_scale", "accel_scale"),
             note="no effect, no auxiliary channel"),
        Case("neg_clean_handheld", "negative", "handheld", (), (),
             ("time_offset", "gyro_scale", "accel_scale", "lever_arm"), note="no effect, no auxiliary channel"),
        Case("neg_decoys_flight", "negative", "paper", (POWER_DECOY, TEMPERATURE_DECOY), (),
             ("current_interference", "throttle_interference", "temperature_drift"),
             note="current, voltage, throttle (steps, payload) and temperature (warm-up) logged, no effect"),
        Case("neg_decoys_hover", "negative", "paper", (POWER_DECOY, TEMPERATURE_DECOY), (),
             ("current_interference", "temperature_drift"), power_profile="hover",
             note="time-trending decoys: current, throttle, voltage, temperature all monotone, no effect"),
        Case("neg_position_handheld", "negative", "handheld", (POSITION_DECOY, TEMPERATURE_DECOY), (),
             ("nongravity_acceleration", "lever_arm"), note="GPS position (still) and temperature, no effect"),
    ]
    out += [
        Case("timing_handheld", "timing", "handheld", (), (), ("time_offset",), vary="grid",
             note="no effect; IMU 50-400 Hz x magnetometer 10-100 Hz x random phase x instant (.bin) / preceding "
                  "(.ulg) gyro, one combination per seed"),
        Case("timing_flight", "timing", "multirotor", (), ("nongravity_acceleration",),
             ("time_offset", "nongravity_acceleration"),
             vary="grid", note="a flight (its own acceleration is physics, GPS logged), no other effect: the grid"),
        Case("lag_handheld", "lag", "handheld", (), ("time_offset",), ("time_offset",), vary="lag",
             note="a true lag of 5-60 ms (log-uniform) on the timing grid"),
    ]
    flight = (("n_mags", 2), ("tilt_limit_deg", 15.0), ("accel_limit_mps2", 1.5))
    out += [
        Case("flight_ardupilot", "flight", "multirotor", (), ("nongravity_acceleration",),
             ("nongravity_acceleration", "current_interference", "throttle_interference"), duration=240.0,
             rate=100.0, mag_rate=10.0, simulate=(*flight, ("log_power", True)), firmware="stale",
             note="ArduPilot .bin: two compasses with their onboard calibrations, COMPASS_MOTCT=2 with a stale "
                  "COMPASS_MOT, MAG int16 mG at 10 Hz, IMU 100 Hz with motor vibration, tilt <= 15 deg, "
                  "acceleration <= 1.5 m/s^2; no magnetic effect"),
        Case("flight_px4_current", "flight", "multirotor", ("current_interference",),
             ("current_interference", "nongravity_acceleration"),
             ("nongravity_acceleration", "current_interference", "throttle_interference"), duration=240.0,
             rate=200.0, mag_rate=50.0, suffix=".ulg", simulate=flight,
             note="PX4 .ulg: sensor_combined at 200 Hz (the mean over each interval), two sensor_mag at 50 Hz, motor "
                  "vibration, current interference (simulate's default, 0.2/-0.1/0.3 mG/A) on the first"),
    ]
    out += [_single(eid, "clear", value) for eid, value in CLEAR.items()]
    out += [_single(eid, "strong", "") for eid in ("current_interference", "temperature_drift", "time_offset",
                                                     "gyro_scale", "nongravity_acceleration")]
    cur, thr, tem = "current_interference", "throttle_interference", "temperature_drift"
    out += [
        Case("sep_current_vs_throttle", "separable", "paper", (f"{cur}:{CLEAR[cur]}", TEMPERATURE_DECOY), (cur,),
             (cur, thr), note="flight: throttle steps and a payload switching on its own (corr(I, u^1.5) ~0.86)"),
        Case("sep_throttle_vs_current", "separable", "paper", (f"{thr}:{CLEAR[thr]}", TEMPERATURE_DECOY), (thr,),
             (cur, thr), note="flight: throttle injected, the current (with payload steps) a decoy"),
        Case("sep_current_vs_temperature", "separable", "paper", (f"{cur}:{CLEAR[cur]}", TEMPERATURE_DECOY),
             (cur,), (cur, tem), note="flight: throttle steps at a steadily warming board (corr(I, T) ~0.1)"),
        Case("sep_temperature_vs_current", "separable", "paper", (f"{tem}:{CLEAR[tem]}", POWER_DECOY), (tem,),
             (cur, tem), note="flight: warm-up injected, the current a decoy"),
        Case("insep_current_vs_throttle", "inseparable", "paper",
             (f"{cur}:c_uT_per_A=0.0027/-0.0013/0.004", TEMPERATURE_DECOY), (cur,), (cur, thr), (cur, thr),
             power_profile="hover", note="hover: no payload, current follows throttle^1.5 (corr > 0.998)"),
        Case("insep_current_vs_temperature", "inseparable", "paper",
             (f"{cur}:c_uT_per_A=0.0027/-0.0013/0.004", TEMPERATURE_DECOY), (cur,), (cur, tem), (cur, tem),
             power_profile="hover", note="hover: current rises with the pack's polarisation as the board warms "
             "(corr(I, T) > 0.996)"),
    ]
    return out


#: every case by name
CASES: dict[str, Case] = {c.name: c for c in _cases()}


def select(names: str) -> list[Case]:
    """Cases by comma-separated names or tiers ("" or "all": every case)."""
    if names.strip() in ("", "all"):
        return list(CASES.values())
    out: list[Case] = []
    for name in (n.strip() for n in names.split(",") if n.strip()):
        hits = [c for c in CASES.values() if name in (c.name, c.tier)]
        if not hits:
            msg = f"unknown case or tier {name!r}; cases: {', '.join(CASES)}; tiers: {', '.join(TIERS)}"
            raise SystemExit(msg)
        out += [c for c in hits if c not in out]
    return out
