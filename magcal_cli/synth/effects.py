"""The physical effects `magcal simulate --effect` injects: ids, parameters, defaults, and the CLI syntax.

Ids and parameters are those of spec/calibration-file.md ("Effects"); every term is zero at parameter zero.
In Python (`EffectSpec`) parameters are SI: tesla, seconds, metres, m/s^2, fractions. On the command line the
magnetic ones carry their unit in the key (`c_uT_per_A`), vectors are written x/y/z and time windows
t0-t1/t0-t1 (docs/simulate-effects.md). The physics is in synth/inject.py (one injection per id, INJECTIONS)
and synth/physics.py.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from magcal_cli.errors import MagcalError


class EffectSpecError(MagcalError):
    """An --effect value or EffectSpec names an unknown effect or key, or a value of the wrong shape."""


@dataclass(frozen=True)
class Key:
    """One parameter: its SI name, its command-line key, value shape, CLI-to-SI factor, SI default and help."""

    param: str
    cli: str
    shape: str                      # "vector" (3 numbers), "number", "windows" ([[t0, t1], ...] s), "choice"
    factor: float
    default: Any                    # SI; None: derived from the log's duration
    help: str
    choices: tuple[str, ...] = ()


@dataclass(frozen=True)
class EffectDef:
    """An effect: the sensor it acts on, its keys, the channels the log must carry, truth units, the model term."""

    sensor: str                     # "magnetometer" or "imu"
    keys: tuple[Key, ...]
    channels: tuple[str, ...]       # stream kinds (streams.Kind values); this module stays free of numpy
    units: Mapping[str, str]        # truth parameter -> unit; "{mag}" is the log's magnetometer unit
    term: str


def _vec(param: str, cli: str, factor: float, default: tuple[float, float, float], help_: str) -> Key:
    return Key(param, cli, "vector", factor, default, help_)


#: every effect magcal simulate can inject, in the order the truth lists them (inject.INJECTIONS applies them)
EFFECTS: dict[str, EffectDef] = {
    "current_interference": EffectDef(
        "magnetometer", (_vec("c", "c_uT_per_A", 1e-6, (2e-8, -1e-8, 3e-8), "uT per ampere"),),
        ("battery_current",), {"c": "{mag}/ampere"}, "y += c I(t)"),
    "throttle_interference": EffectDef(
        "magnetometer", (_vec("c", "c_uT", 1e-6, (6e-7, -3e-7, 9e-7), "uT at full throttle"),
                         Key("p", "p", "number", 1.0, 1.5, "exponent")),
        ("throttle",), {"c": "{mag}", "p": "1"}, "y += c u(t)^p"),
    "temperature_drift": EffectDef(
        "magnetometer", (_vec("k", "k_uT_per_degC", 1e-6, (2e-8, -1.5e-8, 3e-8), "uT per degC"),
                         Key("T0", "T0", "number", 1.0, 25.0, "degC")),
        ("temperature",), {"k": "{mag}/degC", "T0": "degC"}, "y += k (T(t) - T0)"),
    "time_offset": EffectDef(
        "magnetometer", (Key("tau_s", "tau_s", "number", 1.0, 0.05, "s, > 0: the magnetometer lags"),),
        (), {"tau_s": "s"}, "the sample stamped t measured the field at t - tau_s"),
    "gyro_scale": EffectDef(
        "imu", (_vec("s", "s", 1.0, (0.010, -0.008, 0.012), "fraction"),), (), {"s": "1"},
        "w_meas = (I + diag(s)) w + b_g"),
    "accel_scale": EffectDef(
        "imu", (_vec("s", "s", 1.0, (0.008, -0.012, 0.006), "fraction"),), (), {"s": "1"},
        "f_meas = (I + diag(s)) f + b_a"),
    "lever_arm": EffectDef(
        "imu", (_vec("r_m", "r_m", 1.0, (0.06, -0.04, 0.03), "m, IMU frame"),), (), {"r_m": "m"},
        "f += w' x r + w x (w x r)"),
    "nongravity_acceleration": EffectDef(
        "imu", (Key("sigma_a", "sigma_a", "number", 1.0, 1.0, "m/s^2, RMS of each NED component of a_n"),
                Key("source", "source", "choice", 1.0, "gps", "log the position or not", ("gps", "none")),
                Key("delay_s", "delay_s", "number", 1.0, 0.0, "s, the logged position lags the motion")),
        ("position",), {"sigma_a": "m/s^2", "delay_s": "s"}, "f = R^T (a_n - g_n)"),
    "motor_interference": EffectDef(
        "magnetometer", (_vec("c1", "c1_uT", 1e-6, (3e-7, -1.5e-7, 2e-7), "uT per unit (u V)^0.65 of motor 1"),
                         _vec("c2", "c2_uT", 1e-6, (-2.5e-7, 2e-7, 1e-7), "uT per unit of motor 2"),
                         _vec("c3", "c3_uT", 1e-6, (1e-7, 3e-7, -2e-7), "uT per unit of motor 3"),
                         _vec("c4", "c4_uT", 1e-6, (-2e-7, -2.5e-7, 2.5e-7), "uT per unit of motor 4"),
                         Key("diff", "diff", "number", 1.0, 0.08,
                             "differential thrust per rad/s^2 of angular acceleration (0..1 output)")),
        ("motor_output", "battery_voltage"), {f"c{i}": "{mag}" for i in range(1, 5)} | {"diff": "1"},
        "y += sum_i c_i (u_i(t) V(t))^0.65"),
    "transient_disturbance": EffectDef(
        "magnetometer", (Key("windows_s", "windows_s", "windows", 1.0, None, "s"),
                         _vec("b_rel", "b_rel", 1.0, (0.12, -0.14, 0.06), "NED, fraction of the Earth field")),
        (), {"windows_s": "s", "b_n": "{mag}"}, "m_n += b_n / |field| inside the windows"),
}
#: the channels the simulated power system logs (inject.Draft.power)
POWER_CHANNELS = ("battery_current", "battery_voltage", "throttle")
#: the effects the power system drives: those that need one of its channels
POWER_EFFECTS = tuple(eid for eid, d in EFFECTS.items() if set(d.channels) & set(POWER_CHANNELS))
#: |tau_s| above this is not a time offset but a broken clock
MAX_TAU_S = 1.0
#: |s| above this is not a scale-factor error
MAX_SCALE = 0.5


def syntax() -> str:
    """Every id with its command-line keys, for help texts and error messages."""
    return "; ".join(f"{eid} ({', '.join(k.cli for k in d.keys)})" for eid, d in EFFECTS.items())


def _number(text: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        msg = f"{where}: {text.strip()!r} is not a number"
        raise EffectSpecError(msg) from None
    if not math.isfinite(value):
        msg = f"{where}: {text.strip()!r} is not a finite number"
        raise EffectSpecError(msg)
    return value


_WINDOW = re.compile(r"\s*(\d+(?:\.\d*)?(?:[eE][+]?\d+)?)\s*-\s*(\d+(?:\.\d*)?(?:[eE][+]?\d+)?)\s*")


def _parse_value(key: Key, text: str, where: str) -> Any:
    """A command-line value in SI."""
    if key.shape == "vector":
        parts = text.split("/")
        if len(parts) != 3:
            msg = f"{where}: expected 3 numbers separated by '/', e.g. 0.2/-0.1/0.3; got {text!r}"
            raise EffectSpecError(msg)
        return tuple(_number(p, where) * key.factor for p in parts)
    if key.shape == "number":
        return _number(text, where) * key.factor
    if key.shape == "windows":
        out = []
        for part in text.split("/"):
            m = _WINDOW.fullmatch(part)
            if m is None:
                msg = (f"{where}: expected windows as t0-t1 in seconds separated by '/', e.g. 100-130/200-215; "
                       f"got {text!r}")
                raise EffectSpecError(msg)
            out.append((float(m.group(1)), float(m.group(2))))
        return tuple(out)
    return text.strip()


def _check_value(eid: str, key: Key, value: Any) -> Any:
    """The value in its stored form (tuples of floats), or EffectSpecError saying what was expected."""
    where = f"effect {eid}: {key.param}"
    try:
        if key.shape == "vector":
            vec = tuple(float(v) for v in value)
            if len(vec) != 3 or not all(math.isfinite(v) for v in vec):
                raise ValueError
            return vec
        if key.shape == "number":
            num = float(value)
            if not math.isfinite(num):
                raise ValueError
            return num
        if key.shape == "windows":
            wins = tuple((float(a), float(b)) for a, b in value)
            if not wins or not all(0.0 <= a < b and math.isfinite(b) for a, b in wins):
                raise ValueError
            return wins
    except (TypeError, ValueError):
        shape = {"vector": "3 finite numbers", "number": "a finite number",
                 "windows": "a non-empty list of (t0, t1) with 0 <= t0 < t1"}[key.shape]
        msg = f"{where}: expected {shape}, got {value!r}"
        raise EffectSpecError(msg) from None
    if value not in key.choices:
        msg = f"{where}: expected one of {', '.join(key.choices)}, got {value!r}"
        raise EffectSpecError(msg)
    return value


def _check_range(eid: str, params: Mapping[str, Any]) -> None:
    """Physical limits beyond the shape."""
    if "tau_s" in params and abs(params["tau_s"]) > MAX_TAU_S:
        msg = f"effect {eid}: |tau_s| must be at most {MAX_TAU_S} s, got {params['tau_s']}"
        raise EffectSpecError(msg)
    if eid.endswith("_scale") and "s" in params and max(abs(v) for v in params["s"]) > MAX_SCALE:
        msg = f"effect {eid}: each scale error s must be within +-{MAX_SCALE}, got {params['s']}"
        raise EffectSpecError(msg)
    if eid == "throttle_interference" and "p" in params and params["p"] <= 0:
        msg = f"effect {eid}: the exponent p must be > 0, got {params['p']}"
        raise EffectSpecError(msg)
    if "delay_s" in params and abs(params["delay_s"]) > MAX_TAU_S:
        msg = f"effect {eid}: |delay_s| must be at most {MAX_TAU_S} s, got {params['delay_s']}"
        raise EffectSpecError(msg)
    if "sigma_a" in params and params["sigma_a"] < 0:
        msg = f"effect {eid}: sigma_a must be >= 0 m/s^2, got {params['sigma_a']}"
        raise EffectSpecError(msg)


@dataclass(frozen=True)
class EffectSpec:
    """An effect to inject: its id and the SI parameters that differ from the defaults (EFFECTS)."""

    id: str
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        d = EFFECTS.get(self.id)
        if d is None:
            msg = f"unknown effect {self.id!r}; valid ids: {', '.join(EFFECTS)}"
            raise EffectSpecError(msg)
        keys = {k.param: k for k in d.keys}
        unknown = sorted(set(self.params) - set(keys))
        if unknown:
            msg = f"effect {self.id} has no parameter {unknown[0]!r}; valid parameters: {', '.join(keys)}"
            raise EffectSpecError(msg)
        checked = {name: _check_value(self.id, keys[name], v) for name, v in self.params.items()}
        _check_range(self.id, checked)
        object.__setattr__(self, "params", MappingProxyType(checked))

    def resolved(self, duration: float) -> dict[str, Any]:
        """Every parameter (defaults filled in; windows default to 30-38 % and 62-68 % of `duration`)."""
        out = {k.param: k.default for k in EFFECTS[self.id].keys} | dict(self.params)
        if out.get("windows_s", 0) is None:
            out["windows_s"] = tuple((round(a * duration, 1), round(b * duration, 1))
                                     for a, b in ((0.30, 0.38), (0.62, 0.68)))
        return out


def parse_effect(text: str) -> EffectSpec:
    """`ID[:key=value,...]` (command-line units, see docs/simulate-effects.md) as an EffectSpec in SI."""
    eid, _, rest = text.partition(":")
    eid = eid.strip()
    d = EFFECTS.get(eid)
    if d is None:
        msg = f"unknown effect {eid!r}; valid ids: {', '.join(EFFECTS)}"
        raise EffectSpecError(msg)
    keys = {k.cli: k for k in d.keys}
    params: dict[str, Any] = {}
    for item in (s.strip() for s in rest.split(",")):
        if not item:
            continue
        name, eq, value = item.partition("=")
        name = name.strip()
        if name not in keys:
            msg = f"effect {eid} has no key {name!r}; valid keys: {', '.join(keys)}"
            raise EffectSpecError(msg)
        if not eq or not value.strip():
            msg = f"effect {eid}: key {name} has no value; write {name}=VALUE"
            raise EffectSpecError(msg)
        if keys[name].param in params:
            msg = f"effect {eid}: key {name} is given twice"
            raise EffectSpecError(msg)
        params[keys[name].param] = _parse_value(keys[name], value, f"effect {eid}: {name}")
    return EffectSpec(eid, params)


def check_unique(specs: tuple[EffectSpec, ...]) -> None:
    """Each effect at most once."""
    ids = [s.id for s in specs]
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if twice:
        msg = f"effect {twice[0]} is given more than once; give each effect once with all its keys"
        raise EffectSpecError(msg)
