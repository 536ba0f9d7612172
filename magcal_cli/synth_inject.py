"""Injecting effects into a simulation: the physics of each effect and the auxiliary channels it needs.

`inject` takes the true body rates and specific forces at the IMU epochs and returns them with the IMU
effects applied, the magnetometer's body-frame unit field and additive terms at the sensing times, the
streams to log (battery current and voltage, throttle, temperature, position, all noisy like real sensors
unless the noise is scaled to zero) and the injected effects in SI. The magnetometer sample stamped t_j
senses everything at t_j - tau_s (time_offset), including the current and the external field.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from . import synth_physics as phys
from . import units
from .streams import Kind, Recording, Stream
from .synth_effects import EFFECTS, EffectSpec, check_unique

FloatArray = npt.NDArray[np.float64]

#: stream ids of the auxiliary channels (ROS topics; the other formats have their own names)
CURRENT_ID, THROTTLE_ID = "/battery", "/mavros/target_actuator_control"
TEMPERATURE_ID, POSITION_ID = "/imu/temperature", "/gps/fix"
#: the GNSS receiver's rate (Hz)
POSITION_RATE_HZ = 10.0
#: per-sample noise (std) of the logged current (A), voltage (V) and temperature (degC) at noise_scale 1
AUX_NOISE = {"current": 0.05, "voltage": 0.005, "temperature": 0.05}
#: second entry of the seed of every effect's generator, so effects never disturb the base simulation's draws
SEED_TAG = 0x5EFFEC7


@dataclass(frozen=True, eq=False)
class InjectedEffect:
    """An effect in the simulation: SI parameters (truth names), channel kinds logged, signals for tests.

    `signals` holds e.g. "term" (the added magnetometer term, tesla, at the magnetometer epochs), "a_n"
    (NED acceleration at the IMU epochs) or "omega"/"omega_dot" (the lever arm's rates).
    """

    id: str
    params: Mapping[str, Any]
    channels: tuple[Kind, ...]
    signals: Mapping[str, FloatArray]

    @property
    def sensor(self) -> str:
        """"magnetometer" or "imu"."""
        return EFFECTS[self.id].sensor


@dataclass(frozen=True, eq=False)
class Base:
    """What the effects act on: knots (N+1, 3, 3) body->NED at `rate` Hz, one magnetometer sample per `step`,
    and the scenario's translation if it has one."""

    knots: FloatArray
    rate: float
    step: int
    m_n: FloatArray
    field_strength: float
    seed: int
    noise_scale: float
    source: str
    power_profile: str = "flight"
    motion: phys.Motion | None = None       # the scenario's own translation (multirotor, rover)


@dataclass(frozen=True, eq=False)
class Injected:
    """The measurements' true parts with the effects in; None where the base simulation's stands unchanged."""

    omega: FloatArray
    force: FloatArray
    mag_body: FloatArray | None
    mag_extra: FloatArray | None
    streams: tuple[Stream, ...]
    effects: tuple[InjectedEffect, ...]


def _rng(seed: int, k: int) -> np.random.Generator:
    """The generator of one signal model (k), independent of the base simulation and of the other effects."""
    return np.random.default_rng([seed, SEED_TAG, k])


def _body(rot: FloatArray, v_n: FloatArray) -> FloatArray:
    """R^T v for (N, 3, 3) rotations and (N, 3) nav-frame vectors."""
    out: FloatArray = np.einsum("nji,nj->ni", rot, v_n)
    return out


def _translation(q: dict[str, Any] | None, base: Base, t: FloatArray, force: FloatArray,
                 streams: list[Stream], effects: list[InjectedEffect]) -> FloatArray:
    """f += R^T a_n for the scenario's translation plus the effect's sway; the summed path is logged as GNSS
    positions unless the effect says source "none". Either alone is one nongravity_acceleration effect."""
    moves: list[phys.Motion | phys.Path] = [] if base.motion is None else [base.motion]
    if q is not None:
        moves.append(phys.path(_rng(base.seed, 2), t, q["sigma_a"]))
    if not moves:
        return force
    source = "gps" if q is None else str(q["source"])
    delay = 0.0 if q is None else float(q.get("delay_s", 0.0))      # the fix stamped t was taken at t - delay
    t_pos = np.arange(0.0, t[-1] + 1e-9, 1.0 / POSITION_RATE_HZ)
    a_n, p_n, p_pos = np.zeros((len(t), 3)), np.zeros((len(t), 3)), np.zeros((len(t_pos), 3))
    for move in moves:
        a_n += move.acceleration(t)
        p_n += move.position(t)
        p_pos += move.position(t_pos - delay)
    channels: tuple[Kind, ...] = ()
    if source == "gps":
        lla = phys.geodetic(p_pos)
        streams.append(Stream(Kind.POSITION, POSITION_ID, t_pos, lla, f"{base.source}#{POSITION_ID}", "deg"))
        channels = (Kind.POSITION,)
    effects.append(InjectedEffect("nongravity_acceleration",
                                  {"sigma_a": float(np.sqrt(np.mean(a_n**2))), "source": source,
                                   "delay_s": delay},
                                  channels, {"a_n": a_n, "p_n": p_n}))
    return force + _body(base.knots[:-1], a_n)                # f = R^T (a_n - g_n)


def _imu(p: dict[str, dict[str, Any]], base: Base, t: FloatArray, omega: FloatArray, force: FloatArray,
         streams: list[Stream], effects: list[InjectedEffect]) -> tuple[FloatArray, FloatArray]:
    """Translation, lever arm, then the scale factors, which act on the whole measured quantity."""
    force = _translation(p.get("nongravity_acceleration"), base, t, force, streams, effects)
    if "lever_arm" in p:
        r = np.array(p["lever_arm"]["r_m"])
        w, w_dot = phys.Trajectory.from_knots(base.knots, 1.0 / base.rate).rate_and_acceleration(t)
        term = np.cross(w_dot, r) + np.cross(w, np.cross(w, r))
        force = force + term
        effects.append(InjectedEffect("lever_arm", {"r_m": r}, (), {"term": term, "omega": w, "omega_dot": w_dot}))
    if "accel_scale" in p:
        s = np.array(p["accel_scale"]["s"])
        force = force * (1.0 + s)
        effects.append(InjectedEffect("accel_scale", {"s": s}, (), {}))
    if "gyro_scale" in p:
        s = np.array(p["gyro_scale"]["s"])
        omega = omega * (1.0 + s)
        effects.append(InjectedEffect("gyro_scale", {"s": s}, (), {}))
    return omega, force


def _aux(kind: Kind, sid: str, t: FloatArray, v: FloatArray, unit: str, base: Base) -> Stream:
    return Stream(kind, sid, t, v, f"{base.source}#{sid}", unit)


def _mag(p: dict[str, dict[str, Any]], base: Base, t_mag: FloatArray, duration: float,
         streams: list[Stream], effects: list[InjectedEffect]) -> tuple[FloatArray | None, FloatArray | None]:
    """The body-frame unit field and the additive terms (tesla) sensed at t_mag - tau_s."""
    tau = float(p.get("time_offset", {}).get("tau_s", 0.0))
    sensed = t_mag - tau
    noise = _rng(base.seed, 4)
    ns = base.noise_scale
    mag_body = None
    if "time_offset" in p or "transient_disturbance" in p:
        if "time_offset" in p:
            rot = phys.Trajectory.from_knots(base.knots, 1.0 / base.rate).at(sensed)
            effects.append(InjectedEffect("time_offset", {"tau_s": tau}, (), {"rotations": rot}))
        else:
            rot = base.knots[:-1][::base.step]
        nav = np.broadcast_to(base.m_n, (len(t_mag), 3))
        if "transient_disturbance" in p:
            q = p["transient_disturbance"]
            b_rel, wins = np.array(q["b_rel"]), np.array(q["windows_s"], dtype=np.float64)
            d = phys.window(sensed, wins)[:, None] * b_rel
            nav = nav + d
            effects.append(InjectedEffect("transient_disturbance",
                                          {"windows_s": wins, "b_n": b_rel * base.field_strength}, (),
                                          {"d_n": d, "term_body": _body(rot, d)}))
        mag_body = _body(rot, nav)
    terms: list[FloatArray] = []
    if "current_interference" in p or "throttle_interference" in p:
        pw = phys.power(_rng(base.seed, 1), duration, base.power_profile)
        n = len(t_mag)
        current = pw.current(t_mag) + ns * AUX_NOISE["current"] * noise.standard_normal(n)
        voltage = pw.voltage(t_mag) + ns * AUX_NOISE["voltage"] * noise.standard_normal(n)
        streams += [_aux(Kind.BATTERY_CURRENT, CURRENT_ID, t_mag, current, "A", base),
                    _aux(Kind.BATTERY_VOLTAGE, CURRENT_ID, t_mag, voltage, "V", base),
                    _aux(Kind.THROTTLE, THROTTLE_ID, t_mag, pw.throttle(t_mag), "1", base)]
        if "current_interference" in p:
            c = np.array(p["current_interference"]["c"])
            term = pw.current(sensed)[:, None] * c
            terms.append(term)
            effects.append(InjectedEffect("current_interference", {"c": c}, (Kind.BATTERY_CURRENT,),
                                          {"term": term}))
        if "throttle_interference" in p:
            c, expo = np.array(p["throttle_interference"]["c"]), float(p["throttle_interference"]["p"])
            term = pw.throttle(sensed)[:, None] ** expo * c
            terms.append(term)
            effects.append(InjectedEffect("throttle_interference", {"c": c, "p": expo}, (Kind.THROTTLE,),
                                          {"term": term}))
    if "temperature_drift" in p:
        k, t_ref = np.array(p["temperature_drift"]["k"]), float(p["temperature_drift"]["T0"])
        temp = phys.temperature(duration)
        logged = temp(t_mag) + ns * AUX_NOISE["temperature"] * _rng(base.seed, 5).standard_normal(len(t_mag))
        streams.append(_aux(Kind.TEMPERATURE, TEMPERATURE_ID, t_mag, logged, "degC", base))
        term = (temp(sensed) - t_ref)[:, None] * k
        terms.append(term)
        effects.append(InjectedEffect("temperature_drift", {"k": k, "T0": t_ref}, (Kind.TEMPERATURE,),
                                      {"term": term}))
    extra = None
    if terms:
        extra = terms[0]
        for term in terms[1:]:
            extra = extra + term
    return mag_body, extra


def inject(specs: tuple[EffectSpec, ...], base: Base, omega: FloatArray, force: FloatArray) -> Injected:
    """Apply `specs` to the true body rates (N, 3) and specific forces (N, 3) at the IMU epochs."""
    check_unique(specs)
    n = len(base.knots) - 1
    t = np.arange(n) / base.rate
    duration = float(t[-1]) if n else 0.0
    p = {s.id: s.resolved(duration) for s in specs}
    streams: list[Stream] = []
    effects: list[InjectedEffect] = []
    omega, force = _imu(p, base, t, omega, force, streams, effects)
    mag_body, extra = _mag(p, base, t[::base.step], duration, streams, effects)
    order = list(EFFECTS)
    effects.sort(key=lambda e: order.index(e.id))
    return Injected(omega, force, mag_body, extra, tuple(streams), tuple(effects))


def _json(value: Any, factor: float) -> Any:
    """A parameter as JSON: arrays to (nested) lists of floats, numbers scaled by `factor`."""
    if isinstance(value, str):
        return value
    arr = np.asarray(value, dtype=np.float64) * factor
    return arr.tolist() if arr.ndim else float(arr)


def truth_entry(effect: InjectedEffect, log: Recording, imu_id: str) -> dict[str, Any]:
    """The effect as a calibration-file.md `effects` entry for the written `log`: its ids, its magnetometer unit.

    Channels are the ids the reader reports for the kinds the effect needs; a format without a place for a
    channel (a CSV has no position column) lists none, and nongravity_acceleration's source is then "none".
    """
    mag = log.select(Kind.MAGNETOMETER)
    unit = units.canonical(mag.native_unit)
    d = EFFECTS[effect.id]
    channels = [log.of_kind(k)[0].id for k in effect.channels if log.of_kind(k)]
    params: dict[str, Any] = {}
    out_units: dict[str, str] = {}
    for name, value in effect.params.items():
        template = d.units.get(name)
        factor = units.from_si(unit) if template is not None and template.startswith("{mag}") else 1.0
        params[name] = _json(value, factor)
        if template is not None:
            out_units[name] = template.replace("{mag}", unit)
    if effect.id == "nongravity_acceleration" and not channels:
        params["source"] = "none"
    return {"id": effect.id, "sensor": mag.id if d.sensor == "magnetometer" else imu_id, "status": "injected",
            "channels": channels, "params": params, "units": out_units, "term": d.term}
