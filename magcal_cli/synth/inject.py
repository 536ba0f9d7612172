"""Injecting effects into a simulation: the physics of each effect in continuous time and the channels it needs.

`inject` returns what ideal sensors measure with the effects in, as functions of time (`Injected`): the gyro's
and accelerometer's instantaneous inputs (translation, lever arm and scale factors act on the instantaneous
quantity, before any averaging a sensor does; synth_sampling.py samples them) and, for a magnetometer reading
stamped t, the body-frame unit field and the additive terms it senses at t - tau_s (time_offset): attitude,
current, throttle, temperature and external field alike. It also returns the streams to log (battery current
and voltage, throttle and temperature at the magnetometer stamps, position at 10 Hz; noisy like real sensors
unless the noise is scaled to zero) and the injected effects in SI, with their signals at the stamps.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli import so3, units
from magcal_cli.streams import FloatArray, Kind, Recording, Stream
from magcal_cli.synth import physics as phys
from magcal_cli.synth.effects import EFFECTS, EffectSpec, check_unique
from magcal_cli.synth.motion import Motion, Trajectory

#: an additive magnetometer term (M, 3) tesla as a function of the sensing time (s)
Term = Callable[[FloatArray], FloatArray]

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

    `signals` hold instantaneous values at the stamps, e.g. "term" (the added magnetometer term, tesla, at the
    magnetometer stamps), "a_n"/"p_n" (NED acceleration and position at the IMU stamps) or "omega"/"omega_dot"
    (the lever arm's rates at the IMU stamps).
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
    """What the effects act on: the true attitude (body->NED) and the scenario's translation (None: a pure
    rotation), both functions of time; the IMU and magnetometer stamps (s); gravity g_n (m/s^2) and the field.
    `log_power` logs the power channels even when no power effect adds a magnetic term."""

    trajectory: Trajectory
    t_imu: FloatArray
    t_mag: FloatArray
    g_n: FloatArray
    m_n: FloatArray
    field_strength: float
    seed: int
    noise_scale: float
    source: str
    power_profile: str = "flight"
    motion: Motion | None = None
    log_power: bool = False


@dataclass(frozen=True, eq=False)
class Injected:
    """The sensors' true inputs with the effects in, as functions of time (s) (`ImuTruth` for synth_sampling),
    plus the logged channels and the injected effects.

    `moves` sum to the NED acceleration; gains are 1 + s of the scale factors; `disturbance` is (b_rel (3,),
    windows (K, 2) s); `terms` are the magnetometer's additive terms as functions of the sensing time.
    """

    trajectory: Trajectory
    g_n: FloatArray
    m_n: FloatArray
    moves: tuple[Motion | phys.Path, ...]
    lever_arm: FloatArray | None
    gyro_gain: FloatArray
    accel_gain: FloatArray
    tau: float
    disturbance: tuple[FloatArray, FloatArray] | None
    terms: tuple[Term, ...]
    streams: tuple[Stream, ...] = ()
    effects: tuple[InjectedEffect, ...] = ()

    def nav_acceleration(self, t: FloatArray) -> FloatArray:
        """a_n (M, 3) m/s^2: the sum of the translations."""
        out = np.zeros((len(t), 3))
        for move in self.moves:
            out += move.acceleration(t)
        return out

    def lever(self, t: FloatArray) -> FloatArray:
        """w' x r + w x (w x r) (M, 3) m/s^2, the lever arm's specific force (zero without one)."""
        if self.lever_arm is None:
            return np.zeros((len(t), 3))
        w, w_dot = self.trajectory.rate_and_acceleration(t)
        out: FloatArray = np.cross(w_dot, self.lever_arm) + np.cross(w, np.cross(w, self.lever_arm))
        return out

    def rate(self, t: FloatArray) -> FloatArray:
        """(I + diag(s)) w(t): an ideal gyro's instantaneous reading (M, 3) rad/s."""
        return self.gyro_gain * self.trajectory.rate(t)

    def mean_rate(self, t0: FloatArray, t1: FloatArray) -> FloatArray:
        """(I + diag(s)) Log(R(t0)^T R(t1)) / (t1 - t0): the mean rate over [t0, t1] as an integrating gyro
        reports it (the scale acts on the rate before it is integrated; to first order in s the same)."""
        rel = np.swapaxes(self.trajectory.at(t0), -1, -2) @ self.trajectory.at(t1)
        return self.gyro_gain * so3.log(rel) / (t1 - t0)[:, None]

    def force(self, t: FloatArray) -> FloatArray:
        """(I + diag(s)) (R^T (a_n - g_n) + lever arm term): an ideal accelerometer's instantaneous reading."""
        f = _body(self.trajectory.at(t), self.nav_acceleration(t) - self.g_n) + self.lever(t)
        return self.accel_gain * f

    def disturbance_n(self, sensed: FloatArray) -> FloatArray:
        """The external field (M, 3) NED, in units of the Earth field, at sensing times."""
        if self.disturbance is None:
            return np.zeros((len(sensed), 3))
        b_rel, windows = self.disturbance
        return phys.window(sensed, windows)[:, None] * b_rel

    def field(self, t: FloatArray) -> FloatArray:
        """The body-frame unit field (M, 3) of readings stamped t: R(t - tau)^T (m_n + disturbance)."""
        sensed = t - self.tau
        return _body(self.trajectory.at(sensed), self.m_n + self.disturbance_n(sensed))

    def extra(self, t: FloatArray) -> FloatArray:
        """The additive terms (M, 3) tesla of readings stamped t, sensed at t - tau."""
        out = np.zeros((len(t), 3))
        for term in self.terms:
            out += term(t - self.tau)
        return out


def _rng(seed: int, k: int) -> np.random.Generator:
    """The generator of one signal model (k), independent of the base simulation and of the other effects."""
    return np.random.default_rng([seed, SEED_TAG, k])


def _body(rot: FloatArray, v_n: npt.ArrayLike) -> FloatArray:
    """R^T v for (N, 3, 3) rotations and (N, 3) or (3,) nav-frame vectors."""
    out: FloatArray = np.einsum("nji,nj->ni", rot, np.broadcast_to(v_n, (len(rot), 3)))
    return out


def _translation(q: dict[str, Any] | None, base: Base, streams: list[Stream],
                 effects: list[InjectedEffect]) -> tuple[Motion | phys.Path, ...]:
    """The scenario's translation plus the effect's sway; the summed path is logged as GNSS positions unless the
    effect says source "none". Either alone is one nongravity_acceleration effect."""
    t = base.t_imu
    moves: list[Motion | phys.Path] = [] if base.motion is None else [base.motion]
    if q is not None:
        moves.append(phys.path(_rng(base.seed, 2), t, q["sigma_a"]))
    if not moves:
        return ()
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
    return tuple(moves)


def _aux(kind: Kind, sid: str, t: FloatArray, v: FloatArray, unit: str, base: Base) -> Stream:
    return Stream(kind, sid, t, v, f"{base.source}#{sid}", unit)


def _power_terms(p: dict[str, dict[str, Any]], base: Base, sensed: FloatArray, duration: float,
                 streams: list[Stream], effects: list[InjectedEffect]) -> list[Term]:
    """current_interference c I(t) and throttle_interference c u(t)^p, and the three power channels they log (also
    logged without either effect when `base.log_power`)."""
    if "current_interference" not in p and "throttle_interference" not in p and not base.log_power:
        return []
    pw = phys.power(_rng(base.seed, 1), duration, base.power_profile)
    t_mag, noise, ns = base.t_mag, _rng(base.seed, 4), base.noise_scale
    n = len(t_mag)
    current = pw.current(t_mag) + ns * AUX_NOISE["current"] * noise.standard_normal(n)
    voltage = pw.voltage(t_mag) + ns * AUX_NOISE["voltage"] * noise.standard_normal(n)
    streams += [_aux(Kind.BATTERY_CURRENT, CURRENT_ID, t_mag, current, "A", base),
                _aux(Kind.BATTERY_VOLTAGE, CURRENT_ID, t_mag, voltage, "V", base),
                _aux(Kind.THROTTLE, THROTTLE_ID, t_mag, pw.throttle(t_mag), "1", base)]
    terms: list[Term] = []
    if "current_interference" in p:
        c = np.array(p["current_interference"]["c"])
        terms.append(lambda s: pw.current(s)[:, None] * c)
        effects.append(InjectedEffect("current_interference", {"c": c}, (Kind.BATTERY_CURRENT,),
                                      {"term": terms[-1](sensed)}))
    if "throttle_interference" in p:
        ct, expo = np.array(p["throttle_interference"]["c"]), float(p["throttle_interference"]["p"])
        terms.append(lambda s: pw.throttle(s)[:, None] ** expo * ct)
        effects.append(InjectedEffect("throttle_interference", {"c": ct, "p": expo}, (Kind.THROTTLE,),
                                      {"term": terms[-1](sensed)}))
    return terms


def _mag(p: dict[str, dict[str, Any]], base: Base, duration: float, streams: list[Stream],
         effects: list[InjectedEffect]) -> tuple[float, tuple[FloatArray, FloatArray] | None, tuple[Term, ...]]:
    """time_offset's tau_s, transient_disturbance's (b_rel, windows) and the additive terms, with their entries."""
    tau = float(p.get("time_offset", {}).get("tau_s", 0.0))
    sensed = base.t_mag - tau
    rot = base.trajectory.at(sensed) if "time_offset" in p or "transient_disturbance" in p else None
    if "time_offset" in p and rot is not None:
        effects.append(InjectedEffect("time_offset", {"tau_s": tau}, (), {"rotations": rot}))
    disturbance = None
    if "transient_disturbance" in p and rot is not None:
        q = p["transient_disturbance"]
        b_rel, wins = np.array(q["b_rel"]), np.array(q["windows_s"], dtype=np.float64)
        disturbance = (b_rel, wins)
        d = phys.window(sensed, wins)[:, None] * b_rel
        effects.append(InjectedEffect("transient_disturbance", {"windows_s": wins, "b_n": b_rel * base.field_strength},
                                      (), {"d_n": d, "term_body": _body(rot, d)}))
    terms = _power_terms(p, base, sensed, duration, streams, effects)
    if "temperature_drift" in p:
        k, t_ref = np.array(p["temperature_drift"]["k"]), float(p["temperature_drift"]["T0"])
        temp = phys.temperature(duration)
        noise = base.noise_scale * AUX_NOISE["temperature"] * _rng(base.seed, 5).standard_normal(len(base.t_mag))
        streams.append(_aux(Kind.TEMPERATURE, TEMPERATURE_ID, base.t_mag, temp(base.t_mag) + noise, "degC", base))
        terms.append(lambda s: (temp(s) - t_ref)[:, None] * k)
        effects.append(InjectedEffect("temperature_drift", {"k": k, "T0": t_ref}, (Kind.TEMPERATURE,),
                                      {"term": terms[-1](sensed)}))
    return tau, disturbance, tuple(terms)


def _gain(p: dict[str, dict[str, Any]], eid: str, effects: list[InjectedEffect]) -> FloatArray:
    """1 + s of a scale-factor effect (ones when it is not injected)."""
    if eid not in p:
        return np.ones(3)
    s = np.array(p[eid]["s"])
    effects.append(InjectedEffect(eid, {"s": s}, (), {}))
    return 1.0 + s


def inject(specs: tuple[EffectSpec, ...], base: Base) -> Injected:
    """The sensors' inputs with `specs` applied, as functions of time; signals and channels at the stamps."""
    check_unique(specs)
    t = base.t_imu
    duration = float(t[-1]) if len(t) else 0.0
    p = {s.id: s.resolved(duration) for s in specs}
    streams: list[Stream] = []
    effects: list[InjectedEffect] = []
    moves = _translation(p.get("nongravity_acceleration"), base, streams, effects)
    lever = np.array(p["lever_arm"]["r_m"]) if "lever_arm" in p else None
    tau, disturbance, terms = _mag(p, base, duration, streams, effects)
    done = Injected(base.trajectory, base.g_n, base.m_n, moves, lever, _gain(p, "gyro_scale", effects),
                    _gain(p, "accel_scale", effects), tau, disturbance, terms)
    if lever is not None:
        w, w_dot = base.trajectory.rate_and_acceleration(t)
        effects.append(InjectedEffect("lever_arm", {"r_m": lever}, (),
                                      {"term": done.lever(t), "omega": w, "omega_dot": w_dot}))
    order = list(EFFECTS)
    effects.sort(key=lambda e: order.index(e.id))
    return replace(done, streams=tuple(streams), effects=tuple(effects))


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
