"""Injecting effects into a simulation: the physics of each effect in continuous time and the channels it needs.

`inject` returns what ideal sensors measure with the effects in, as functions of time (`Injected`): the gyro's
and accelerometer's instantaneous inputs (translation, lever arm and scale factors act on the instantaneous
quantity, before any averaging a sensor does; synth/sampling.py samples them) and, for a magnetometer reading
stamped t, the body-frame unit field and the additive terms it senses at t - tau_s (time_offset): attitude,
current, throttle, temperature and external field alike. It also returns the streams to log (battery current
and voltage, throttle and temperature at the magnetometer stamps, position at 10 Hz; noisy like real sensors
unless the noise is scaled to zero) and the injected effects in SI, with their signals at the stamps.

Each effect is one injection function and its line in INJECTIONS (effect id -> function); its ids, keys and
defaults are in synth/effects.py, and tests/synth/test_registry.py ties both to the estimator's effects.EFFECTS.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
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
    """The sensors' true inputs with the effects in, as functions of time (s) (`ImuTruth` for synth/sampling.py),
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
        return lever_force(w, w_dot, self.lever_arm)

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


def lever_force(w: FloatArray, w_dot: FloatArray, r: FloatArray) -> FloatArray:
    """w' x r + w x (w x r) (M, 3) m/s^2: the specific force of a lever arm r (3,) m at rates w, w' (M, 3)."""
    out: FloatArray = np.cross(w_dot, r) + np.cross(w, np.cross(w, r))
    return out


def _aux(kind: Kind, sid: str, t: FloatArray, v: FloatArray, unit: str, base: Base) -> Stream:
    """A logged auxiliary channel of the simulation."""
    return Stream(kind, sid, t, v, f"{base.source}#{sid}", unit)


@dataclass(eq=False)
class Draft:
    """An injection in progress: the base, the log's duration (s) and what the injections have set so far.

    Each field starts as "no effect" (no sway, gains of one, tau 0, no disturbance, no terms); `streams` are the
    auxiliary channels in the order they are logged, `effects` the truth entries in any order.
    """

    base: Base
    duration: float
    moves: list[Motion | phys.Path] = field(default_factory=list)
    gnss: tuple[str, float] = ("gps", 0.0)          # the position's source and its delay (s) behind the motion
    lever_arm: FloatArray | None = None
    gyro_gain: FloatArray = field(default_factory=lambda: np.ones(3))
    accel_gain: FloatArray = field(default_factory=lambda: np.ones(3))
    tau: float = 0.0
    disturbance: tuple[FloatArray, FloatArray] | None = None
    terms: list[Term] = field(default_factory=list)
    streams: list[Stream] = field(default_factory=list)
    effects: list[InjectedEffect] = field(default_factory=list)
    power_model: phys.Power | None = None

    @property
    def sensed(self) -> FloatArray:
        """When the magnetometer readings were sensed (s): their stamps minus tau_s."""
        out: FloatArray = self.base.t_mag - self.tau
        return out

    def power(self) -> phys.Power:
        """The vehicle's power system, drawn and logged (POWER_CHANNELS at the magnetometer stamps, noisy) on first
        use and shared by every effect that needs it."""
        if self.power_model is not None:
            return self.power_model
        base = self.base
        pw = phys.power(_rng(base.seed, 1), self.duration, base.power_profile)
        t_mag, noise, ns = base.t_mag, _rng(base.seed, 4), base.noise_scale
        n = len(t_mag)
        current = pw.current(t_mag) + ns * AUX_NOISE["current"] * noise.standard_normal(n)
        voltage = pw.voltage(t_mag) + ns * AUX_NOISE["voltage"] * noise.standard_normal(n)
        self.streams += [_aux(Kind.BATTERY_CURRENT, CURRENT_ID, t_mag, current, "A", base),
                         _aux(Kind.BATTERY_VOLTAGE, CURRENT_ID, t_mag, voltage, "V", base),
                         _aux(Kind.THROTTLE, THROTTLE_ID, t_mag, pw.throttle(t_mag), "1", base)]
        self.power_model = pw
        return pw

    def add_term(self, eid: str, term: Term, params: Mapping[str, Any], channels: tuple[Kind, ...]) -> None:
        """An additive magnetometer term and its truth entry (its signal: the term at the sensing times)."""
        self.terms.append(term)
        self.effects.append(InjectedEffect(eid, params, channels, {"term": term(self.sensed)}))

    def translation(self) -> tuple[list[Stream], tuple[Motion | phys.Path, ...]]:
        """The position streams and the moves: the scenario's translation plus any sway, their summed path logged
        as GNSS positions unless the source is "none". Either alone is one nongravity_acceleration entry (added)."""
        base, t = self.base, self.base.t_imu
        if not self.moves:
            return [], ()
        source, delay = self.gnss                   # the fix stamped t was taken at t - delay
        t_pos = np.arange(0.0, t[-1] + 1e-9, 1.0 / POSITION_RATE_HZ)
        a_n, p_n, p_pos = np.zeros((len(t), 3)), np.zeros((len(t), 3)), np.zeros((len(t_pos), 3))
        for move in self.moves:
            a_n += move.acceleration(t)
            p_n += move.position(t)
            p_pos += move.position(t_pos - delay)
        streams: list[Stream] = []
        channels: tuple[Kind, ...] = ()
        if source == "gps":
            lla = phys.geodetic(p_pos)
            streams.append(Stream(Kind.POSITION, POSITION_ID, t_pos, lla, f"{base.source}#{POSITION_ID}", "deg"))
            channels = (Kind.POSITION,)
        self.effects.append(InjectedEffect("nongravity_acceleration",
                                           {"sigma_a": float(np.sqrt(np.mean(a_n**2))), "source": source,
                                            "delay_s": delay},
                                           channels, {"a_n": a_n, "p_n": p_n}))
        return streams, tuple(self.moves)

    def done(self) -> Injected:
        """The finished injection: the position first among the logged channels, entries in EFFECTS order."""
        position, moves = self.translation()
        order = list(EFFECTS)
        self.effects.sort(key=lambda e: order.index(e.id))
        base = self.base
        return Injected(base.trajectory, base.g_n, base.m_n, moves, self.lever_arm, self.gyro_gain, self.accel_gain,
                        self.tau, self.disturbance, tuple(self.terms), (*position, *self.streams), tuple(self.effects))


#: an effect's injection: its resolved SI parameters (EffectSpec.resolved) act on the draft
Injection = Callable[[Mapping[str, Any], Draft], None]


def _nongravity(q: Mapping[str, Any], d: Draft) -> None:
    """nongravity_acceleration: a sway path of RMS sigma_a on top of the scenario's translation."""
    d.moves.append(phys.path(_rng(d.base.seed, 2), d.base.t_imu, q["sigma_a"]))
    d.gnss = (str(q["source"]), float(q.get("delay_s", 0.0)))


def _time_offset(q: Mapping[str, Any], d: Draft) -> None:
    """time_offset: the reading stamped t measured the field at t - tau_s."""
    d.tau = float(q["tau_s"])
    d.effects.append(InjectedEffect("time_offset", {"tau_s": d.tau}, (), {"rotations": d.base.trajectory.at(d.sensed)}))


def _transient(q: Mapping[str, Any], d: Draft) -> None:
    """transient_disturbance: an external field b_rel (NED, in Earth fields) inside the windows."""
    b_rel, wins = np.array(q["b_rel"]), np.array(q["windows_s"], dtype=np.float64)
    d.disturbance = (b_rel, wins)
    sensed = d.sensed
    n_d = phys.window(sensed, wins)[:, None] * b_rel
    d.effects.append(InjectedEffect("transient_disturbance", {"windows_s": wins, "b_n": b_rel * d.base.field_strength},
                                    (), {"d_n": n_d, "term_body": _body(d.base.trajectory.at(sensed), n_d)}))


def _current(q: Mapping[str, Any], d: Draft) -> None:
    """current_interference: c I(t)."""
    pw, c = d.power(), np.array(q["c"])
    d.add_term("current_interference", lambda s: pw.current(s)[:, None] * c, {"c": c}, (Kind.BATTERY_CURRENT,))


def _throttle(q: Mapping[str, Any], d: Draft) -> None:
    """throttle_interference: c u(t)^p."""
    pw, c, expo = d.power(), np.array(q["c"]), float(q["p"])
    d.add_term("throttle_interference", lambda s: pw.throttle(s)[:, None] ** expo * c, {"c": c, "p": expo},
               (Kind.THROTTLE,))


#: a quad X's motors 1-4 (ArduCopter's order: front-right, back-left, front-left, back-right) as roll, pitch and yaw
#: factors of AP_MotorsMatrix: differential thrust turns body angular acceleration into per-motor outputs
QUAD_X = np.array([[-0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.5, 0.5, -0.5], [-0.5, -0.5, -0.5]])
MOTOR_ID = "motor[{}]"


def _motor(q: Mapping[str, Any], d: Draft) -> None:
    """motor_interference: sum_i c_i (u_i V)^0.65, u_i the throttle plus the quad X mix of the body's angular
    acceleration times `diff`, clipped to 0..1; the four outputs are logged at the magnetometer stamps."""
    from magcal_cli.effects.motor import EXPO

    pw, base = d.power(), d.base
    c = np.array([q[f"c{i}"] for i in range(1, 5)])
    gain = float(q["diff"])

    def outputs(s: FloatArray) -> FloatArray:
        _, w_dot = base.trajectory.rate_and_acceleration(s)
        out: FloatArray = np.clip(pw.throttle(s)[:, None] + gain * w_dot @ QUAD_X.T, 0.0, 1.0)
        return out

    def term(s: FloatArray) -> FloatArray:
        x = outputs(s) * pw.voltage(s)[:, None]
        out: FloatArray = np.where(x > 0, np.abs(x) ** EXPO, 0.0) @ c
        return out

    u = outputs(base.t_mag)
    d.streams += [_aux(Kind.MOTOR_OUTPUT, MOTOR_ID.format(i + 1), base.t_mag, u[:, i], "1", base) for i in range(4)]
    d.add_term("motor_interference", term, {f"c{i}": c[i - 1] for i in range(1, 5)} | {"diff": gain},
               (Kind.MOTOR_OUTPUT, Kind.BATTERY_VOLTAGE))


def _temperature(q: Mapping[str, Any], d: Draft) -> None:
    """temperature_drift: k (T(t) - T0) of a warming board, whose temperature is logged."""
    base = d.base
    k, t_ref = np.array(q["k"]), float(q["T0"])
    temp = phys.temperature(d.duration)
    noise = base.noise_scale * AUX_NOISE["temperature"] * _rng(base.seed, 5).standard_normal(len(base.t_mag))
    d.streams.append(_aux(Kind.TEMPERATURE, TEMPERATURE_ID, base.t_mag, temp(base.t_mag) + noise, "degC", base))
    d.add_term("temperature_drift", lambda s: (temp(s) - t_ref)[:, None] * k, {"k": k, "T0": t_ref},
               (Kind.TEMPERATURE,))


def _scale(eid: str, q: Mapping[str, Any], d: Draft) -> FloatArray:
    """1 + s of a scale-factor effect, with its truth entry."""
    s = np.array(q["s"])
    d.effects.append(InjectedEffect(eid, {"s": s}, (), {}))
    return 1.0 + s


def _gyro_scale(q: Mapping[str, Any], d: Draft) -> None:
    """gyro_scale: w_meas = (I + diag(s)) w."""
    d.gyro_gain = _scale("gyro_scale", q, d)


def _accel_scale(q: Mapping[str, Any], d: Draft) -> None:
    """accel_scale: f_meas = (I + diag(s)) f."""
    d.accel_gain = _scale("accel_scale", q, d)


def _lever_arm(q: Mapping[str, Any], d: Draft) -> None:
    """lever_arm: the accelerometer r_m from the centre of rotation senses w' x r + w x (w x r)."""
    r = np.array(q["r_m"])
    d.lever_arm = r
    w, w_dot = d.base.trajectory.rate_and_acceleration(d.base.t_imu)
    d.effects.append(InjectedEffect("lever_arm", {"r_m": r}, (),
                                    {"term": lever_force(w, w_dot, r), "omega": w, "omega_dot": w_dot}))


#: effect id -> its injection, in the order they are applied: time_offset before the magnetometer's other effects
#: (they are sensed at t - tau_s); the logged channels and the additive terms keep this order
INJECTIONS: dict[str, Injection] = {
    "nongravity_acceleration": _nongravity,
    "time_offset": _time_offset,
    "transient_disturbance": _transient,
    "current_interference": _current,
    "throttle_interference": _throttle,
    "temperature_drift": _temperature,
    "motor_interference": _motor,
    "gyro_scale": _gyro_scale,
    "accel_scale": _accel_scale,
    "lever_arm": _lever_arm,
}


def inject(specs: tuple[EffectSpec, ...], base: Base) -> Injected:
    """The sensors' inputs with `specs` applied, as functions of time; signals and channels at the stamps."""
    check_unique(specs)
    t = base.t_imu
    duration = float(t[-1]) if len(t) else 0.0
    p = {s.id: s.resolved(duration) for s in specs}
    draft = Draft(base, duration, [] if base.motion is None else [base.motion])
    if base.log_power:
        draft.power()                               # logged without a magnetic term
    for eid, injection in INJECTIONS.items():
        if eid in p:
            injection(p[eid], draft)
    return draft.done()


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
