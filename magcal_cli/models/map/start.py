"""How a MAP fit starts: its settings, start values (Huang et al. 2025, Sec. III-D) and the effects bound there."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from magcal_cli import so3
from magcal_cli.detect import MIN_STILL_S
from magcal_cli.effects import get
from magcal_cli.effects.base import Target
from magcal_cli.models import partial
from magcal_cli.models.accel import G
from magcal_cli.models.epochs import Epochs, Noise, epochs_for, initial_noise
from magcal_cli.models.factor import Linearize
from magcal_cli.models.gyro import Preintegrated, preintegrate_epochs
from magcal_cli.models.map import init as map_init
from magcal_cli.models.map.cost import held_out, mag_layout, make_linearize
from magcal_cli.models.map.effects import Bound, bind, layout_for
from magcal_cli.models.map.estimate import FitContext
from magcal_cli.models.map.hold import rechoose
from magcal_cli.models.map.noise import NOISE_ROUNDS
from magcal_cli.models.partial import Held
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit
from magcal_cli.models.spikes import despike
from magcal_cli.params import BASE, Layout
from magcal_cli.streams import FloatArray, Stream


@dataclass(frozen=True, eq=False)
class FitSettings:
    """How `fit.fit_map` fits one magnetometer: the loss, the dip prior (rad), the noise rounds, IMU noise levels to
    start from, the effect plug-ins to model, the declination (rad), held-out windows (s), a fit of the same
    magnetometer to start from (`warm`) and a prior to hold what the motion cannot determine at (`prior`)."""

    loss: str = "l2"
    dip_prior: float | None = None
    noise_rounds: int = NOISE_ROUNDS
    imu_start: Noise | None = None
    effects: tuple[str, ...] = ()
    declination: float = 0.0
    holdout: tuple[tuple[float, float], ...] = ()
    warm: FitContext | None = None
    prior: partial.MagPrior | None = None


@dataclass(eq=False)
class Run:
    """A fit in progress, in the solver's scaled units: the data and model `prepare` sets up (epochs,
    preintegration, noise levels and their floor, layout with the bound effects, held-out row weights, held
    entries), the current point, and the record so far (notes, log lines, iterations)."""

    where: str
    mag_id: str
    ep: Epochs
    pre: Preintegrated
    noise: Noise
    floor: Noise | None
    layout: Layout
    bound: tuple[Bound, ...]
    untestable: list[EffectFit]
    hold: FloatArray | None
    held: Held | None
    states: FloatArray
    theta: FloatArray
    notes: list[str]
    log: list[str] = field(default_factory=list)
    iters: int = 0

    def cost(self, held: Held | None) -> Linearize:
        """The fit's cost with the current data and noise levels, `held` entries held at their prior."""
        return make_linearize(self.ep, self.pre, self.noise, self.layout, self.bound, self.hold, held)


def prepare(problem: Problem, mag: Stream, cfg: FitSettings, cache: dict[bytes, Preintegrated]) -> Run:
    """The fit's start: epochs, noise levels (and the floor still data measured), start values, or those of
    `cfg.warm`; the effects bound; with `cfg.prior`, what the motion cannot determine held at it."""
    where = f"{problem.where}: {mag.id}"
    prior, warm = cfg.prior, cfg.warm
    clean, spikes = despike(mag.xyz)            # outliers would wreck the algebraic start values
    if prior is not None:
        intr = map_init.from_prior(clean, prior.D, prior.o)
    elif warm is not None:                # the fit to start from may be a partial one: no ellipsoid needed
        d, o, _ = mag_layout(warm.layout).unpack(warm.theta)
        intr = map_init.from_prior(clean, d * warm.ep.scale, o * warm.ep.scale)
    else:
        intr = map_init.intrinsic_fit(clean, where)
    ep = epochs_for(problem, mag, intr.scale, average=True)
    noise = initial_noise(problem, mag, intr.scale, intr.noise_rms)
    still_s = sum(seg.end - seg.start for seg in problem.still.segments)
    floor = noise if still_s >= MIN_STILL_S else None
    if cfg.imu_start is not None:              # already estimated on this IMU (floors still apply below)
        noise = Noise(cfg.imu_start.acc, cfg.imu_start.gyr, noise.mag)
    else:
        # in motion the accelerometer also sees linear acceleration: start from the spread of |a| about g
        dev = np.linalg.norm(ep.acc, axis=1) - G
        spread = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
        noise = Noise(np.maximum(noise.acc, spread), noise.gyr, noise.mag)
    if warm is not None:                  # same magnetometer, same epochs: start where that fit ended
        ep, noise, pre, states = warm.ep, warm.noise, warm.pre, warm.states
        notes: list[str] = []
        theta = BASE.zeros()
        BASE.carry(theta, warm.layout, warm.theta)
    else:
        clean_ep = replace(ep, mag=ep.readings(clean) / intr.scale, notes=(), index=np.zeros(0, np.int64))
        states, theta, pre, notes = initial_state(problem, clean_ep, intr, noise, cfg, cache)
    layout, bound, untestable, theta, pre = with_effects(problem, mag, ep, pre, theta, cfg)
    if warm is not None:                  # the effect blocks that fit also had
        layout.carry(theta, warm.layout, warm.theta)
    hold = held_out(ep.t, cfg.holdout + problem.unmeasured)
    held = warm.held if warm is not None else None
    if prior is not None:
        held = rechoose(partial.prior_of(layout, theta, prior, ep.scale, cfg.dip_prior),
                        make_linearize(ep, pre, noise, layout, bound, hold), states, theta, where)
        theta[held.theta_cols] = held.mean
    held = None if held is None else held.placed(layout)      # a warm start's hold, in this fit's layout
    if floor is not None and any(b.effect.target.value == "mag" and b.effect.params for b in bound):
        # a magnetometer effect also acts while the vehicle is still (current, temperature): the still
        # readings' spread is not the sensor's white noise then, so it is no floor for the magnetometer level
        floor = Noise(floor.acc, floor.gyr, np.full(3, 1e-12))
    if spikes:
        notes.append(f"{mag.id}: {spikes} isolated spikes in the readings were smoothed for the start values "
                     "only" + ("" if cfg.loss != "l2" else "; consider --robust-loss huber"))
    return Run(where, mag.id, ep, pre, noise, floor, layout, bound, untestable, hold, held, states, theta, notes)


def start_on(problem: Problem, base: FitContext, mag: Stream) -> FitContext:
    """A warm start for a fit of `mag` on other epochs than `base`'s (every k-th reading, for the diagnosis):
    base's trajectory slerped to the new epochs, its parameters, noise levels and gyro bias, preintegrated between
    the new epochs."""
    ep = epochs_for(problem, mag, base.ep.scale, average=True)
    pre = preintegrated(problem, ep, base.pre.bias, base.noise, {})
    states = so3.slerp(base.states, base.ep.t, ep.t)
    return replace(base, ep=ep, pre=pre, states=states, holdout=None, excluded=None)


def preintegrated(problem: Problem, ep: Epochs, bias: FloatArray, noise: Noise,
                  cache: dict[bytes, Preintegrated], scale_jacobian: bool = False) -> Preintegrated:
    """Preintegrate between the epochs (with the gyro-scale Jacobian when asked), or rescale a cached
    preintegration of the same epochs and bias."""
    key = ep.t.tobytes() + np.asarray(bias, dtype=np.float64).tobytes() + bytes([scale_jacobian])
    hit = cache.get(key)
    if hit is not None:
        ratio = noise.gyr / hit.noise_std
        if np.allclose(ratio, ratio[0], rtol=1e-12):
            return hit.scaled(float(ratio[0]) ** 2)
    pre = preintegrate_epochs(problem, ep, bias, noise.gyr, f"{problem.where}: {ep.mag_id}", scale_jacobian)
    # the entry is a copy that shares the arrays: the component-major stacks the fit makes on `pre` (13 MB at
    # 60 000 epochs) must not stay in the cache for the rest of the run (issue 39); a hit is rescaled anyway
    cache[key] = replace(pre)
    return pre


def initial_state(problem: Problem, ep: Epochs, intr: map_init.Intrinsic, noise: Noise, cfg: FitSettings,
                  cache: dict[bytes, Preintegrated]) -> tuple[FloatArray, FloatArray, Preintegrated, list[str]]:
    """Start values (states, theta, preintegration) as in Sec. III-D; the trajectory that fits better wins.
    With a prior (`cfg.prior`) the start D stays in the body frame (a flat log cannot align); a gyro effect needs
    the preintegration's scale Jacobian (integrate once, not twice)."""
    dip_prior, align = cfg.dip_prior, cfg.prior is None
    scale_jacobian = any(get(e).target is Target.GYRO for e in cfg.effects)
    notes = []
    if problem.still.segments:
        bias = problem.still.gyr_bias
        notes.append(f"{ep.mag_id}: gyro bias started from {len(problem.still.segments)} still segments")
    else:
        bias = np.zeros(3)
    pre = preintegrated(problem, ep, bias, noise, cache, scale_jacobian)
    h = (ep.mag - intr.o0) @ np.linalg.inv(intr.D0).T
    window = max(1, int(round(map_init.ALIGNMENT_WINDOW_S / float(np.median(pre.duration)))))
    r_d, db = map_init.wu_luo(h, so3.log_small(pre.delta), pre.duration, window) if align else (np.eye(3), np.zeros(3))
    db = db if not problem.still.segments else np.zeros(3)
    if not problem.still.segments and align:           # the first-order bias correction carries db (no re-integration)
        notes.append(f"{ep.mag_id}: no still segment; gyro bias started from the Wu & Luo alignment "
                     f"({np.array2string(bias + db, precision=4)} rad/s)")
    d0 = intr.D0 @ r_d
    m_b = (ep.mag - intr.o0) @ np.linalg.inv(d0).T
    dip = dip_prior if dip_prior is not None else map_init.dip_from_data(m_b, ep.acc)
    theta = BASE.zeros()
    BASE.put(theta, "gyroscope_bias", db)
    BASE.put(theta, "D", d0.ravel(order="F"))
    BASE.put(theta, "o", intr.o0)
    BASE.put(theta, "dip", dip)
    att = map_init.attitudes(m_b, ep.acc, dip)
    delta = pre.delta @ so3.exp(pre.d_bias @ db)
    candidates = {"gyro-integrated": map_init.integrated(delta, att, pre.broken),
                  "accelerometer/magnetometer": att}
    lin = make_linearize(ep, pre, noise, holdout=held_out(ep.t, problem.unmeasured))
    costs = {k: sum(float(np.sum(f.r**2)) for f in lin(s, theta, False)) for k, s in candidates.items()}
    best = min(costs, key=costs.__getitem__)
    notes.append(f"{ep.mag_id}: started from the {best} trajectory")
    return candidates[best], theta, pre, notes


def with_effects(problem: Problem, mag: Stream, ep: Epochs, pre: Preintegrated, theta: FloatArray, cfg: FitSettings
                 ) -> tuple[Layout, tuple[Bound, ...], list[EffectFit], FloatArray, Preintegrated]:
    """Bind the effects `cfg.effects` at the start values: the extended layout and theta, and a preintegration with
    the scale Jacobian when a gyro effect needs it."""
    bias = pre.bias + BASE.get(theta, "gyroscope_bias")
    bound, untestable = bind(problem, mag, ep.t_obs, bias, cfg.effects, cfg.declination)
    layout = layout_for(bound)
    full = layout.zeros()
    layout.carry(full, BASE, theta)
    for b in bound:
        full[layout.cols(*b.names())] = b.effect.start()
    if any(b.effect.target.value == "gyro" for b in bound) and pre.d_scale is None:
        pre = preintegrate_epochs(problem, ep, pre.bias, pre.noise_std, f"{problem.where}: {mag.id}", True)
    return layout, tuple(bound), untestable, full, pre


def with_coverage(problem: Problem, mag: Stream, prior: partial.MagPrior, dip: float | None,
                  cache: dict[bytes, Preintegrated]) -> partial.MagPrior:
    """The prior with what the motion shows of the field (`partial.covered`): from the gyro-integrated attitude
    levelled by the accelerometer, never from the readings about the prior."""
    ep = epochs_for(problem, mag, 1.0, average=True)
    bias = problem.still.gyr_bias if problem.still.segments else np.zeros(3)
    pre = preintegrated(problem, ep, bias, Noise(np.ones(3), np.full(3, 1e-3), np.ones(3)), cache)
    return partial.covered(prior, pre.delta, ep.acc, dip, ep.mag)
