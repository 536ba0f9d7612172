"""Which physics to add: screen, refit, check on held-out data, and name the rivals a log cannot separate.

mismatch.md sections 3.5-3.8. Candidates are added greedily (the strongest significant one, then the rest
screened again given it). An effect is accepted only when all of these hold:
1. its robust score test is significant after Holm's correction over the candidates (family alpha 5 %);
2. refitted, its fit is physically plausible (the plug-in's `limits`), its Wald p < WALD_ALPHA and
   2 ln(Bayes factor) ~ W - q ln(n_eff) > BIC_MIN given the other effects added;
3. the model with it, fitted on each training fold, predicts the held-out readings better (block-bootstrap 95 %
   interval of the likelihood gain above zero), and the screening on the training folds alone chose it in at
   least half of them;
4. it matters: at the 99th percentile of the log it moves the heading by >= RELEVANT_DEG or the field by >= 1 %
   (tilt or 10-s attitude for IMU effects), or left out it would move D, o or the dip by >= RELEVANT_SIGMAS of
   their own stds (a calibration that leaves out what the log proves must not claim more precision than it has).
Significant candidates whose signatures the log cannot separate (canonical correlation > SEPARABLE) are
`ambiguous` together.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from magcal_cli import effects as registry
from magcal_cli.diagnose.parallel import Outcome
from magcal_cli.diagnose.relevance import relevance, relevant
from magcal_cli.diagnose.score import Score, Screen, screen
from magcal_cli.diagnose.validate import FOLD_NOISE_ROUNDS, REFIT_ERRORS, Heldout, crossvalidate
from magcal_cli.effects.base import Target
from magcal_cli.errors import reason
from magcal_cli.models.map.effects import Bound, forget
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.models.map.fit import fit_map
from magcal_cli.models.problem import Problem
from magcal_cli.models.result import EffectFit
from magcal_cli.progress import Hook, current
from magcal_cli.streams import Stream

FAMILY_ALPHA = 0.05
#: Wald p-value an effect must keep given the others (backward check)
WALD_ALPHA = 0.01
#: largest canonical correlation at which two candidates are still told apart
SEPARABLE = 0.95
#: 2 ln(Bayes factor) for "strong" evidence (Kass & Raftery 1995)
BIC_MIN = 6.0
MAX_EFFECTS = 3
#: a fold "chose" an effect often enough
MIN_SHARE = 0.5

#: the work that follows if the held-out check confirms a model (`select`)
Ahead = Callable[[MapEstimate], Sequence[Callable[[], object]]]


@dataclass(frozen=True, eq=False)
class Selection:
    """The final estimate (base plus accepted effects), every candidate's verdict and the held-out record."""

    estimate: MapEstimate
    verdicts: tuple[EffectFit, ...]
    heldout: Heldout | None
    ambiguous: tuple[frozenset[str], ...]
    #: the estimate the work `select` was given to run ahead was made for, and that work's outcomes
    ahead: tuple[MapEstimate | None, tuple[Outcome[object], ...]] = (None, ())


def holm(scr: Screen, alpha: float = FAMILY_ALPHA) -> list[str]:
    """Candidates significant under Holm's step-down correction, the one whose step lowers the cost most first.

    Significance is the robust test's; the order is the classical statistic's (the likelihood gain of adding the
    candidate): the robust statistics of rivals differ by how each one's own step leaves the other's signal in
    its variance, which ranked throttle above an injected current."""
    ranked = sorted(scr.scores, key=lambda s: s.p_value)
    out = []
    for i, s in enumerate(ranked):
        if not s.p_value <= alpha / (len(ranked) - i):
            break
        out.append(s)
    return [s.id for s in sorted(out, key=lambda s: -s.classical)]


def two_ln_bayes(statistic: float, dof: int, neff: float) -> float:
    """2 ln(Bayes factor) of adding an effect, by BIC: its likelihood-ratio (or Wald) statistic less dof ln(n_eff)."""
    return float(statistic - dof * float(np.log(neff)))


def n_eff(est: MapEstimate) -> float:
    """Effective number of magnetometer readings: n / (1 + 2 sum of the residuals' autocorrelation)."""
    ctx = est.context
    assert ctx is not None
    r = ctx.linearize(holdout=None)(ctx.states, ctx.theta, False)[1].r
    n = r.shape[0]
    rho_sum = 0.0
    for lag in range(1, min(200, n // 4)):
        rho = float(np.mean([np.corrcoef(r[:-lag, i], r[lag:, i])[0, 1] for i in range(3)]))
        if not rho > 0.05:
            break
        rho_sum += rho
    return float(n / (1.0 + 2.0 * rho_sum))


@dataclass(frozen=True, eq=False)
class Forward:
    """Greedy forward selection: the effects added, the fit with them, each candidate's latest score (given what
    was added before it) and the pairs the log could not tell apart."""

    picked: tuple[str, ...]
    estimate: MapEstimate
    scores: dict[str, Score]
    screens: tuple[Screen, ...]
    ambiguous: tuple[frozenset[str], ...]
    implausible: dict[str, str]


def forward(problem: Problem, mag: Stream, base: MapEstimate, candidates: Sequence[str], declination: float,
            loss: str, dip_prior: float | None, holdout: tuple[tuple[float, float], ...] = (),
            progress: Hook | None = None, given: tuple[str, ...] = ()) -> Forward:
    """Add the strongest significant candidate, refit, screen the rest given it; at most MAX_EFFECTS rounds
    (counting the effects `given`, which `base` models already).

    Re-screening after each addition matters: an unmodelled strong effect leaks into the score of every other
    candidate (the IMU scale factors pick up part of a current's signature), so adding all significant ones at
    once would take passengers. Candidates the log cannot tell apart from the one added are recorded as pairs.
    """
    est = base
    picked: list[str] = list(given)
    pairs: list[frozenset[str]] = []
    screens: list[Screen] = []
    scores: dict[str, Score] = {}
    implausible: dict[str, str] = {}
    left = list(candidates)
    hook = progress or current()
    for _ in range(MAX_EFFECTS + 2):
        if len(picked) == MAX_EFFECTS:
            break
        hook(f"{mag.id} diagnosis: screening {len(left)} effects" + (f" beside {', '.join(picked)}" if picked else ""),
             0)
        scr = screen(problem, mag, est, left, declination)
        screens.append(scr)
        scores.update({s.id: s for s in scr.scores})
        sig = holm(scr)
        if not sig:
            break
        fits: Trials = {}
        best, rivals = _nested_choice(problem, mag, est, tuple(picked), sig, scr, loss, dip_prior, declination,
                                      holdout, fits)
        pairs += [frozenset((best, r)) for r in rivals]
        hook(f"{mag.id} diagnosis: fitting with {best}", 0)
        try:
            trial = _trial(problem, mag, est, (*picked, best), loss, dip_prior, declination, holdout, fits)
        except REFIT_ERRORS as exc:
            # a weakly determined log (an offsets-only flight) may not carry the extra term at all: the effect is
            # not established, and the diagnosis goes on without it
            trial, bad = est, _failed(exc, problem, mag)
        else:
            bad = beyond_limits(trial, best)
        if bad:                   # it stands in for other physics (e.g. an accelerometer scale of -90 % in flight)
            implausible[best] = bad
            pairs = [p for p in pairs if best not in p]
            left = [e for e in left if e != best]
            continue
        picked.append(best)
        left = [e for e in left if e != best and e not in rivals]
        est = trial
    return Forward(tuple(picked), est, scores, tuple(screens), tuple(pairs), implausible)


#: one forward round's trial fits by their effects (or what the fit raised): `_beyond`'s fit with the nested term
#: is the forward step's fit when that term is then added
Trials = dict[tuple[str, ...], "MapEstimate | Exception"]


def _trial(problem: Problem, mag: Stream, est: MapEstimate, effects: tuple[str, ...], loss: str,
           dip_prior: float | None, declination: float, holdout: tuple[tuple[float, float], ...],
           fits: Trials) -> MapEstimate:
    """The fit with `effects` from `est` (what a forward step fits), made once per round."""
    got = fits.get(effects)
    if got is None:
        try:
            got = fit_map(problem, mag, loss, dip_prior, FOLD_NOISE_ROUNDS, effects=effects,
                          declination=declination, holdout=holdout, warm=est.context)
        except REFIT_ERRORS as exc:
            got = exc
        fits[effects] = got
    if isinstance(got, Exception):
        raise got
    return got


def _nested_choice(problem: Problem, mag: Stream, est: MapEstimate, picked: tuple[str, ...], sig: list[str],
                   scr: Screen, loss: str, dip_prior: float | None, declination: float,
                   holdout: tuple[tuple[float, float], ...], fits: Trials) -> tuple[str, list[str]]:
    """The candidate to add and its rivals. Without nesting effects (Effect.nests) this is the old rule: the
    strongest, rivals above SEPARABLE. A nested term that explains the same readings with fewer parameters is added
    instead (throttle rather than per-motor fields when the motors move together) and the nesting one becomes its
    rival; a nesting pair whose bigger term explains more than the smaller one is not a pair of rivals."""
    beyond: dict[tuple[str, str], bool] = {}

    def goes_beyond(big: str, small: str) -> bool:
        if (big, small) not in beyond:
            beyond[big, small] = _beyond(problem, mag, est, (*picked, small), big, loss, dip_prior, declination,
                                         holdout, fits)
        return beyond[big, small]

    def close(a: str, b: str) -> bool:
        return scr.correlation.get(frozenset((a, b)), 0.0) > SEPARABLE

    best = sig[0]
    best = next((e for e in sig[1:] if e in registry.get(best).nests and close(best, e) and not goes_beyond(best, e)),
                best)
    rivals = [e for e in sig if e != best and close(best, e)
              and not (e in registry.get(best).nests and goes_beyond(best, e))
              and not (best in registry.get(e).nests and goes_beyond(e, best))]
    return best, rivals


def _beyond(problem: Problem, mag: Stream, est: MapEstimate, given: tuple[str, ...], best: str, loss: str,
            dip_prior: float | None, declination: float, holdout: tuple[tuple[float, float], ...],
            fits: Trials | None = None) -> bool:
    """Whether `best`, whose term nests the last of `given` (Effect.nests: per-motor fields contain the throttle's as
    the case where the motors move together), still explains significantly more with that one fitted: then the
    two are not rivals (the canonical correlation of nested terms is always near 1), whichever was added first.
    False for other pairs."""
    if given[-1] not in registry.get(best).nests:
        return False
    try:
        fitted = _trial(problem, mag, est, given, loss, dip_prior, declination, holdout, {} if fits is None else fits)
    except REFIT_ERRORS:
        return False
    scr = screen(problem, mag, fitted, [best], declination)
    if not holm(scr):
        return False
    # the backward step's evidence bar too: the extra parameters must pay for themselves (2 ln BF > BIC_MIN)
    s = scr.scores[0]
    return two_ln_bayes(s.classical, s.dof, n_eff(fitted)) > BIC_MIN


def beyond_limits(est: MapEstimate, eid: str) -> str:
    """Why the fitted effect is physically implausible ('' when it is not)."""
    eff = registry.get(eid)
    for name, limit in eff.limits.items():
        v = est.value(f"{eid}.{name}")
        if v.size and float(np.max(np.abs(v))) > limit:
            return (f"its fitted {name} ({float(np.max(np.abs(v))):.3g} SI) is beyond the plausible {limit:g}: it "
                    "stands in for other physics")
    return ""


def select(problem: Problem, mag: Stream, base: MapEstimate, candidates: Sequence[str], declination: float = 0.0,
           loss: str = "l2", dip_prior: float | None = None, progress: Hook | None = None,
           ahead: Ahead | None = None) -> Selection:
    """Select forward against the base fit, check backward, validate on held-out data, decide. `ahead(est)` names
    the work that follows if the held-out check confirms `est` (the forward selection's model): it runs beside the
    check's folds, and `Selection.ahead` returns its outcomes."""
    hook = progress or current()

    failed: dict[str, str] = {}

    def fit(ids: Sequence[str], warm: MapEstimate) -> tuple[MapEstimate, list[str]]:
        """The fit with effects `ids` (the base fit without any), and the effects it kept: a weakly determined
        flight may carry an effect on the training part (the forward step's fit) and not on the whole log; the
        last added is then dropped, with its reason, until the fit stands."""
        kept = list(ids)
        while kept:
            try:
                return fit_map(problem, mag, loss, dip_prior, effects=tuple(kept), declination=declination,
                               warm=warm.context), kept
            except REFIT_ERRORS as exc:
                failed[kept.pop()] = _failed(exc, problem, mag)
        return base, kept

    def procedure(fold_base: MapEstimate, hold: tuple[tuple[float, float], ...]) -> tuple[str, ...]:
        # what the training data alone finds significant against the base model (the first forward step)
        chosen = tuple(holm(screen(problem, mag, fold_base, candidates, declination)))
        forget(problem, keep=picked)          # the fold's screening inputs: not asked again
        return chosen

    fw = forward(problem, mag, base, candidates, declination, loss, dip_prior, progress=hook)
    scr = fw.screens[0]
    first = fw.picked
    ambiguous = list(fw.ambiguous)

    def backward(est: MapEstimate, picked: list[str]) -> tuple[MapEstimate, list[str]]:
        for _ in range(2):           # keep what stays significant, with strong evidence, given the rest
            neff = n_eff(est) if picked else float("nan")
            weak = [f.id for f in est.effects if f.id in picked and not (
                f.p_value < WALD_ALPHA and two_ln_bayes(f.statistic, f.dof, neff) > BIC_MIN)]
            if not weak:
                break
            hook(f"{mag.id} diagnosis: refitting without {', '.join(weak)}", 0)
            est, picked = fit([p for p in picked if p not in weak], base)
        return est, picked

    est, picked = backward(*fit(fw.picked, fw.estimate))
    if any(registry.get(e).nests for e in fw.picked if e not in picked):
        # a nesting term the others then made weak (per-motor fields, once the lag is modelled: log171's MAG[0]) had
        # kept out the terms it nests: the selection goes on from what stayed, without it
        more = forward(problem, mag, est, [c for c in candidates if c not in fw.picked], declination, loss, dip_prior,
                       progress=hook, given=tuple(picked))
        if len(more.picked) > len(picked):
            fw = Forward(more.picked, more.estimate, {**fw.scores, **more.scores}, (*fw.screens, *more.screens),
                         (*fw.ambiguous, *more.ambiguous), {**fw.implausible, **more.implausible})
            ambiguous = list(fw.ambiguous)
            est, picked = backward(*fit(more.picked, more.estimate))
    made_for = est if picked and ahead else None
    forget(problem, keep=picked)              # the whole log's screening inputs, before the folds (issue 39)
    held, done_ahead = crossvalidate(problem, mag, base, procedure, est, declination, loss, dip_prior, hook,
                                     ahead(est) if ahead else ()) if picked else (None, ())
    neff = n_eff(est) if picked else float("nan")
    verdicts: dict[str, EffectFit] = {}
    for f in est.effects:
        if f.id not in picked:
            continue
        rel = relevance(est, f.id)
        bic = two_ln_bayes(f.statistic, f.dof, neff)
        assert held is not None
        lo, hi = held.ci95()
        evidence = {"score_p_value": _p(fw.scores, f.id), "delta_bic": -bic, "n_eff": neff,
                    "heldout_gain_ci95": [lo, hi], "heldout_rms_before_si": held.rms_before,
                    "heldout_rms_after_si": held.rms_after, "folds_chose": held.share(f.id),
                    "heldout_protocol": held.protocol, **rel}
        why = [w for w, bad in (("the likelihood evidence is weak", not bic > BIC_MIN),
                                ("it does not improve held-out readings", not lo > 0.0),
                                ("most training folds did not choose it", held.share(f.id) < MIN_SHARE),
                                ("its size does not matter in practice", not relevant(rel))) if bad]
        verdicts[f.id] = replace(f, status="rejected" if why else "accepted", evidence=evidence,
                                 reason="; ".join(why))
    accepted = tuple(e for e, v in verdicts.items() if v.status == "accepted")
    if set(accepted) != set(picked):
        est, kept = fit(accepted, base)
        accepted = tuple(kept)
        verdicts = {k: v for k, v in verdicts.items() if k not in failed}
        verdicts.update({f.id: replace(f, status="accepted", evidence=verdicts[f.id].evidence)
                         for f in est.effects if f.id in accepted})
    implausible = {**fw.implausible, **failed}
    for s in fw.scores.values():
        if s.id in verdicts:
            continue
        note = implausible.get(s.id) or _rejected(s, fw, first, picked, verdicts)
        verdicts[s.id] = EffectFit(s.id, _sensor(s.id, mag, problem), "rejected", None, (), s.robust, s.dof,
                                   s.p_value, reason=note, test_kind="score")
    # the score tests found a mismatch that follows rivals this log cannot tell apart: say so. One of each pair stays
    # in the fit, accepted or not: left out, its mean is absorbed by the offsets, which then claim a precision the
    # log does not have (hover logs: o 46-77 std off the truth). Either rival explains the same readings, so the one
    # whose term vanishes at rest is kept: the offsets are then the hard iron, not those at the log's mean temperature
    modelled = _modelled(accepted, ambiguous, fw.picked)
    if set(modelled) != set(accepted):
        est, kept = fit(modelled, base)
        fitted = {f.id: f for f in est.effects}
        for eid in kept:
            if eid not in accepted and eid in fitted and eid in verdicts:
                # the fit's own entry (estimate, constants such as T0, Wald test); its verdict follows below
                verdicts[eid] = replace(fitted[eid], evidence=verdicts[eid].evidence)
        modelled_ids = set(kept)
    else:
        modelled_ids = set(accepted)
    rivals_of: dict[str, set[str]] = {}
    for pair in ambiguous:
        for eid in pair:
            rivals_of.setdefault(eid, set()).update(pair - {eid})
    for eid, rs in rivals_of.items():
        rival = tuple(sorted(rs))
        carried = eid in modelled_ids
        said = f"cannot be told apart from {' or '.join(rival)} in this log" + (
            "" if any(e in modelled_ids for e in (eid, *rival)) else "; not modelled: the fit could not carry it")
        verdicts[eid] = replace(verdicts[eid], status="ambiguous", confounded_with=rival, reason=said,
                                estimate=verdicts[eid].estimate if carried else None)
    verdicts.update({u.id: u for u in scr.untestable if u.id not in verdicts})
    return Selection(est, tuple(verdicts.values()), held, tuple(ambiguous), (made_for, done_ahead))


def _rejected(s: Score, fw: Forward, first: Sequence[str], picked: Sequence[str],
              verdicts: dict[str, EffectFit]) -> str:
    """Why a candidate the forward selection screened was rejected, in one clause that agrees with its p-value (the
    report prints the p beside it)."""
    rivals = [p for pair in fw.ambiguous if s.id in pair for p in pair if p != s.id]
    significant = {e for sc in fw.screens for e in holm(sc)}
    if s.id in first:
        others = [p for p in picked if p != s.id]
        return ("the Wald test or BIC found its evidence weak " + (
            f"once {' and '.join(others)} {'is' if len(others) == 1 else 'are'} modelled" if others else "in the refit"))
    if s.id in significant and rivals:
        rival = verdicts.get(rivals[0])
        return f"it explains the same readings as {rivals[0]}" + (
            "" if rival is None else f", which was rejected: {rival.reason}" if rival.reason else ", which was accepted")
    if s.id in significant and len(fw.picked) == MAX_EFFECTS and s.id in holm(fw.screens[-1]):
        return (f"not added: a diagnosis adds at most {MAX_EFFECTS} effects, and {', '.join(fw.picked[:-1])} and "
                f"{fw.picked[-1]} came first")
    if s.id in significant:
        return "the effects added before it explained its signal"
    if s.p_value > FAMILY_ALPHA:
        return "the score test found no sign of it"
    tested = next((len(sc.scores) for sc in reversed(fw.screens) if sc.of(s.id) is not None), 1)
    return (f"too weak once corrected for testing {tested} effects at once "
            f"(Holm's method, {100 * FAMILY_ALPHA:.0f} % for all of them together)")


def _modelled(accepted: Sequence[str], pairs: Sequence[frozenset[str]], picked: Sequence[str]) -> tuple[str, ...]:
    """The effects the final fit carries: the accepted ones, and for each ambiguous pair that the forward selection
    acted on one member, preferring one whose term vanishes at rest (`Effect.zero_at_rest`) to one that does not."""
    out = list(accepted)
    for pair in pairs:
        if not any(e in picked for e in pair):
            continue
        at_rest = {e for e in pair if registry.get(e).zero_at_rest}
        inside = [e for e in pair if e in out]
        if inside and (not at_rest or any(e in at_rest for e in inside)):
            continue
        pool = at_rest or set(pair)
        out = [e for e in out if e not in inside]
        out.append(next((e for e in picked if e in pool), min(pool)))
    return tuple(dict.fromkeys(out))


def _failed(exc: Exception, problem: Problem, mag: Stream) -> str:
    """Why an effect was rejected when a fit with it failed."""
    return f"the fit with it failed ({reason(exc, f'{problem.where}: {mag.id}')})"


def _p(scores: dict[str, Score], eid: str) -> float:
    """The score test's p-value of `eid`."""
    s = scores.get(eid)
    return float("nan") if s is None else s.p_value


def _sensor(eid: str, mag: Stream, problem: Problem) -> str:
    """The sensor an effect belongs to."""
    return mag.id if registry.get(eid).target is Target.MAG else problem.imu_id


__all__ = ["Bound", "Selection", "select"]
