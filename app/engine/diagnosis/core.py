"""The fitting core of the gap diagnosis: recalibrate, locate, attribute, measure the closure.

A *family* describes one kind of rig: its measured channels, the baseline
model's parameters (what the thesis models), and the candidate effects it can
add (each at most three bounded parameters, named as in
:data:`~app.engine.params.EFFECT_NAMES`). The core is family-agnostic:

1. **Recalibrate** the baseline on the calibration experiments (bounded
   least squares on noise-whitened residuals) and report identifiability:
   parameter SDs from the Jacobian, their correlation matrix, the condition
   number, and parameters stuck on a bound — so that parameter error is not
   blamed on a missing effect.
2. **Where**: the baseline's residuals per channel and per regime, their
   whiteness (lag autocorrelation, Ljung–Box) and cross-correlation with the
   inputs.
3. **Which**: each candidate is fitted on the calibration experiments together
   with the baseline parameters and scored on held-out experiments: NRMSE per
   channel, gap closure GC = (E_base − E_with)/(E_base − E_floor) with E the
   channel-mean NRMSE and E_floor the noise floor's (the median of each
   log's noise estimate, times the root of the share of it a right model's
   error carries: :func:`noise_floor`), ΔBIC on the calibration
   fit, a bootstrap CI of GC over held-out experiments (or over blocks of
   time when fewer than four are held out). An effect is *significant* when
   ΔBIC > 10 (strong evidence), the CI's lower end is above zero, GC ≥ 0.2,
   and it lowers the held-out RMS error of some channel by more than the
   family's *relevance* (the smallest error that matters on the rig, e.g. the
   PRV's 0.01 bar deadband); and its fit neither leaves every parameter of it
   on a bound of its range nor keeps its gain once its dynamics are taken out
   (the family's ``static_part``: a tube of no volume is a restriction).
   Significant effects are added greedily (each next one judged against the
   model that already has the previous ones).
4. **Confusable**: a candidate that also explains the gap (significant, or
   relevant with a GC CI reaching the winner's) while the paired bootstrap CI
   of GC(winner) − GC(candidate) contains zero is reported as confusable —
   the held-out data cannot say which does more — with the protocol
   experiments that would tell the two apart.
5. **How far**: NRMSE per channel before and after the selected effects, and
   the gap left unexplained.

Optional family attributes (for expensive, piecewise-smooth models such as a
replayed simulator): ``diff_step``, ``max_nfev`` and ``tol`` (its ``ftol`` and
``xtol``: a rippled cost gains nothing from steps finer than its ripple) for the descent,
``grid_points`` for a coarse grid start over each candidate's parameters
(``grid_refinements`` finer grids around its best, default 1),
``base_grid`` (a range per baseline parameter) for a grid start of the
baseline's recalibration (run again with the first fit's values of the
other parameters: :func:`recalibrate`; ``base_grids``, several such groups
gridded one after the other, ``base_grid_levels`` values per axis for each,
default 3) and, over those that ``rebase`` names, of a
candidate's fit after its own grid, ``form_grids`` (groups of ranges of baseline
parameters of the model's form, e.g. one valve's, the form's switch first) recalibrated
one group after the other beside the nominal form (:func:`recalibrate_forms`) and searched again in a
candidate's fit where the recalibration moved them (that fit's grid then runs both
from the nominal form and beside the reference's),
``frozen(effects)`` naming parameters the candidate being added cannot trade with
(held at the reference fit), ``rebase(effects)`` naming baseline parameters
whose reference values may stand in for the candidate being added (the grid
and a second descent start them from their nominal values, free in that
descent even where ``frozen`` holds them; the fit with the lower calibration
cost is kept), ``prefetch(preps, params_list, effects)`` to compute
predictions for many parameter sets at once (e.g. on all cores),
``static_part(effect)`` giving the extra parameters that take a dynamic effect's
dynamics out and their description (see :data:`STATIC_SHARE`),
``linear_start(preps, params, effects)`` giving, instead of the grid, a start for a
candidate's descent with the parameters that enter the predictions (nearly)
linearly at their least-squares values (or ``None``: the grid; with ``rebase``,
taken again at the baseline grid's best),
``drops_at_off(effect)``, true where the family leaves the effect out of its
model at its ``off`` values (the cost jumps there, so that point is a fallback
of the candidate's descent, not a start: :func:`fit`), and
``nominal_scales`` naming baseline parameters that scale a nominal value
(the report flags one the recalibration moved past :data:`FAR_FACTOR`:
:func:`recalibration`), ``meaning`` (what each baseline parameter is, for
that report) and ``absorbs`` (per such parameter, what an unmodelled effect
it can stand in for looks like there), and
``shared_scale``: groups of channels of one quantity normalised by one
scale, the largest of their SDs (a regulated supply's own SD is its noise:
normalised by it, its NRMSE is ≈ 1 whatever the model, and the ±1–2 %
error of any noise estimate would outweigh every other channel's gap).
A NaN in a measured channel marks a sample the family does not score.
"""

from __future__ import annotations

import copy
import itertools
import math
import threading
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
from scipy import stats
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from app.engine.diagnosis.logs import Experiment, flat_channels, sampling_irregularity

BIC_STRONG = 10.0  # Kass & Raftery (1995): ΔBIC > 10 is very strong evidence
GC_MIN = 0.2
N_BOOT = 300
MAX_EFFECTS = 3
# A nominal value the recalibration moved by more than this factor either way is off by more than
# any tolerance on a datasheet or a drawing: the fit is standing in for something the model lacks
# (on a rig written apart from ours, bench/independent_rig.py, a 5 m tube behind each valve was
# taken as 5.0 × the dead volumes, at the range's end, beside 0.33 × the PRV capacity)
FAR_FACTOR = 2.0
_T = TypeVar("_T")
_R = TypeVar("_R")
EVALUATIONS = 2
"""Candidate fits (and recalibration descents) run at once: see :func:`_each`."""


@dataclass(frozen=True)
class Param:
    """One bounded model parameter.

    Attributes:
        name: Name (``effect.param`` for effect parameters).
        x0: Initial value.
        lo: Lower bound.
        hi: Upper bound.
        unit: Unit.
        log: Fit in log space (spans decades; needs ``lo > 0``).
        off: For an effect parameter, the value at which the effect vanishes,
            so that a fit started there is never worse than the model without
            it (``None``: ``x0``). Where the effect's physics only nearly
            vanishes there, the family leaves it out of its model at that value
            (docs/diagnosis-record.md, "Where 'off' is not the baseline").
    """

    name: str
    x0: float
    lo: float
    hi: float
    unit: str = ""
    log: bool = False
    off: float | None = None


class Family(Protocol):
    """What the core needs to know about a kind of rig."""

    name: str
    channels: tuple[str, ...]
    candidates: tuple[str, ...]
    relevance: dict[str, float]

    def baseline(self) -> list[Param]:
        """Baseline (thesis-model) parameters to recalibrate."""
        ...

    def effect(self, name: str) -> list[Param]:
        """The ≤ 3 parameters of candidate effect ``name``."""
        ...

    def prepare(self, exp: Any) -> Any:
        """Per-experiment precomputation (filtering, derived signals)."""
        ...

    def measured(self, prep: Any) -> dict[str, np.ndarray]:
        """Measured channels aligned with :meth:`predict`."""
        ...

    def predict(self, prep: Any, x: dict[str, float], effects: tuple[str, ...]) -> dict[str, np.ndarray]:
        """Predicted channels under parameters ``x`` with ``effects`` added."""
        ...

    def noise(self, prep: Any) -> dict[str, float]:
        """Noise SD per channel (the floor no model can beat)."""
        ...

    def times(self, prep: Any) -> np.ndarray:
        """Time of each sample :meth:`measured` gives, from the log's start [s]."""
        ...

    def noise_shows(self, prep: Any) -> dict[str, np.ndarray]:
        """Per scored sample, the share of a channel's noise variance a right model's error carries [0–1].

        Aligned with :meth:`measured`; a channel left out carries all of it.
        Less than 1 where the prediction is built from the measurement itself
        (the rotary torque at standstill, :meth:`RotaryFamily.noise_shows`).
        """
        ...

    def regimes(self, prep: Any) -> dict[str, np.ndarray]:
        """Boolean masks of operating regimes (aligned with :meth:`measured`)."""
        ...

    def inputs(self, prep: Any) -> dict[str, np.ndarray]:
        """Input signals for the cross-correlation test (aligned)."""
        ...


@dataclass
class Fit:
    """A fitted model.

    Attributes:
        effects: Effects added to the baseline.
        params: Fitted values by name.
        sd: Standard deviations (Jacobian-based) by name.
        at_bound: Parameters that ended on a bound.
        corr: Correlation matrix of the parameters (row order of ``params``).
        cond: Condition number of the whitened Jacobian.
        rss: Whitened residual sum of squares on the calibration data.
        n: Residuals.
        k: Parameters.
        free: Parameters this fit moved (row order of ``corr``; the others were
            held at the reference fit's values, their SDs NaN).
    """

    effects: tuple[str, ...]
    params: dict[str, float]
    sd: dict[str, float]
    at_bound: list[str]
    corr: np.ndarray
    cond: float
    rss: float
    n: int
    k: int
    free: list[str] = field(default_factory=list)

    @property
    def bic(self) -> float:
        """n·ln(RSS/n) + k·ln(n) on the whitened calibration residuals."""
        return self.n * math.log(max(self.rss, 1e-300) / self.n) + self.k * math.log(self.n)

    def identifiability(self) -> dict[str, Any]:
        """JSON view: SDs, bounds hit, strongly correlated pairs (|r| > 0.95), condition number."""
        names = self.free or list(self.params)
        pairs = [[names[i], names[j], float(self.corr[i, j])] for i in range(len(names))
                 for j in range(i + 1, len(names)) if abs(self.corr[i, j]) > 0.95]
        return {"params": self.params, "sd": self.sd, "at_bound": self.at_bound, "condition_number": self.cond,
                "correlated_pairs": pairs}


@dataclass
class Scores:
    """Held-out errors of one model.

    Attributes:
        sse: Per held-out unit (experiment or block), per channel: Σ residual².
        cnt: Per unit, per channel: samples.
    """

    sse: np.ndarray
    cnt: np.ndarray


TRIM_K = 3.0  # second differences beyond this many SDs are signal (steps), not noise
_TRIM_VAR = 1.0 - 2.0 * TRIM_K * float(stats.norm.pdf(TRIM_K)) / (2.0 * float(stats.norm.cdf(TRIM_K)) - 1.0)


def white_noise_sd(x: np.ndarray) -> float:
    """SD of the white noise on a sampled signal, robust to the signal itself.

    For white noise of SD σ the second difference has SD σ·√6, while a
    smooth signal barely moves it. The median absolute second difference
    gives a first value that steps cannot move; the variance of the second
    differences within ±3 of those SDs (corrected for the trimmed Gaussian
    tails) then gives the estimate. The median alone moves in whole
    quantisation steps on an ADC's output (0.86–1.11 × the truth on the
    station's pressure channels); the trimmed variance does not, and
    scatters less from log to log (2 % against 3.3 %).
    """
    d2 = np.diff(np.asarray(x, dtype=float), 2)
    d2 = d2[np.isfinite(d2)]
    if d2.size == 0:
        return 0.0
    r = d2 - np.median(d2)
    sd = float(np.median(np.abs(r)) / 0.6745 / math.sqrt(6.0))
    for _ in range(3):
        if sd <= 0.0:
            break
        keep = r[np.abs(r) < TRIM_K * math.sqrt(6.0) * sd]
        sd = math.sqrt(float(np.mean(keep**2)) / _TRIM_VAR / 6.0) if keep.size else sd
    # a quantised signal with little noise has a zero median difference; its floor is the LSB's
    steps = np.abs(np.diff(np.asarray(x, dtype=float)))
    steps = steps[steps > 0]
    lsb = float(steps.min()) if steps.size else 0.0
    return max(sd, lsb / math.sqrt(12.0))


def _specs(family: Family, effects: Sequence[str]) -> list[Param]:
    specs = list(family.baseline())
    for e in effects:
        ps = family.effect(e)
        if len(ps) > 3:
            raise ValueError(f"effect {e} has {len(ps)} parameters; at most three")
        specs += ps
    return specs


def _to_x(specs: list[Param], values: dict[str, float]) -> np.ndarray:
    out = []
    for s in specs:
        v = min(max(values.get(s.name, s.x0), s.lo), s.hi)
        out.append(math.log(v) if s.log else v)
    return np.asarray(out)


def _from_x(specs: list[Param], x: np.ndarray) -> dict[str, float]:
    return {s.name: float(math.exp(v) if s.log else v) for s, v in zip(specs, x, strict=True)}


def _bounds(specs: list[Param]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([math.log(s.lo) if s.log else s.lo for s in specs])
    hi = np.array([math.log(s.hi) if s.log else s.hi for s in specs])
    return lo, hi


def channel_scales(family: Family, preps: list[Any]) -> dict[str, float]:
    """Whitening scale per channel: the pooled noise SD (floored at 0.1 % of the channel's SD)."""
    out = {}
    for c in family.channels:
        noise = [family.noise(p)[c] for p in preps]
        spread = float(np.nanstd(np.concatenate([family.measured(p)[c] for p in preps])))
        out[c] = max(float(np.sqrt(np.mean(np.square(noise)))), 1e-3 * spread, 1e-12)
    return out


def channel_spread(family: Family, meas: list[dict[str, np.ndarray]]) -> np.ndarray:
    """NRMSE normaliser per channel: its SD over ``meas``, or its group's largest (``shared_scale``)."""
    sd = {c: float(np.nanstd(np.concatenate([m[c] for m in meas]))) or 1.0 for c in family.channels}
    for group in getattr(family, "shared_scale", ()):
        group = tuple(c for c in group if c in sd)
        if group:
            top = max(sd[c] for c in group)
            sd |= {c: top for c in group}
    return np.array([sd[c] for c in family.channels])


class Cancelled(Exception):
    """The diagnosis was asked to stop (``stop`` set); nothing was concluded."""


def _each(fn: Callable[[_T], _R], items: Sequence[_T]) -> list[_R]:
    """``[fn(i) for i in items]``, :data:`EVALUATIONS` at a time, in ``items``' order.

    The replays already run on all cores, but between two batches of them a
    fit is Python (its descent's step, the torque balance, the residuals) on
    one core while the others wait: on the ten-minute bench that was 19 of
    its 152 s. Independent fits side by side fill those gaps. Each is a pure
    function of its inputs (the replay caches only spare work), so the
    results are those of the loop. The first failure (a :class:`Cancelled`
    included) is raised once the fits already running have ended; the ones
    not started are dropped.
    """
    if len(items) < 2 or EVALUATIONS < 2:
        return [fn(i) for i in items]
    with ThreadPoolExecutor(max_workers=EVALUATIONS, thread_name_prefix="diagnosis") as ex:
        futures = [ex.submit(fn, i) for i in items]
        try:
            return [f.result() for f in futures]
        except BaseException:
            for f in futures:
                f.cancel()
            raise


def checked_candidates(family: str, known: Sequence[str], candidates: Sequence[str] | None) -> list[str]:
    """The effects a diagnosis tries: all ``known`` for None, else ``candidates``, each once in their order.

    Raises:
        ValueError: A name the family (called ``family`` in the message) has
            no add-on for, or an empty list; the message lists ``known``.
    """
    if candidates is None:
        return list(known)
    unknown = [c for c in candidates if c not in known]
    if unknown:
        raise ValueError(f"the {family} family has no candidate {', '.join(unknown)}; known: {', '.join(known)}")
    if not candidates:
        raise ValueError(f"no candidate effect given; known: {', '.join(known)}")
    return list(dict.fromkeys(candidates))


def raise_if_stopped(stop: threading.Event | None, what: str = "diagnosis") -> None:
    """Raise :class:`Cancelled` once ``stop`` is set."""
    if stop is not None and stop.is_set():
        raise Cancelled(f"the {what} was stopped before it finished")


def _weighted(r: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """Residuals for least squares: an unscored sample (NaN measurement) weighs nothing, a
    prediction that failed (NaN where something was measured) weighs heavily."""
    if np.isfinite(r).all():  # the common case, and then ``meas`` is finite too
        return r
    return np.where(np.isfinite(meas), np.where(np.isfinite(r), r, 1e3), 0.0)


def _residuals(family: Family, preps: list[Any], meas: list[dict[str, np.ndarray]], x: dict[str, float],
               effects: tuple[str, ...], scales: dict[str, float]) -> np.ndarray:
    """The scaled, weighted residuals of ``x`` on ``preps``, all channels, as one vector (see :func:`_weighted`)."""
    parts = []
    for p, m in zip(preps, meas, strict=True):
        pr = family.predict(p, x, effects)
        for c in family.channels:
            parts.append(_weighted((pr[c] - m[c]) / scales[c], m[c]))
    return np.concatenate(parts)


def fit(family: Family, preps: list[Any], effects: tuple[str, ...] = (), start: dict[str, float] | None = None,
        scales: dict[str, float] | None = None, starts: list[dict[str, float]] | None = None,
        stop: threading.Event | None = None, free: set[str] | None = None,
        hold: Iterable[str] = (), fallback: dict[str, float] | None = None) -> Fit:
    """Bounded least squares of the baseline (plus ``effects``) on ``preps``.

    ``starts`` (several starting points) overrides ``start``: the descent
    starts from the one with the lowest cost. ``free`` names parameters the
    family's ``frozen`` holds that this descent moves anyway; ``hold``,
    parameters it keeps at the first start's values besides. ``fallback`` is a
    start not descended from unless the descent ends above its cost: an effect
    the family leaves out at its "off" values (``drops_at_off``) has a cost that
    jumps there, and a descent from that point sees only the jump. ``stop``,
    once set, ends the fit at its next cost evaluation with :class:`Cancelled`.
    """
    all_specs = _specs(family, effects)
    first = (starts or [start or {}])[0]
    # parameters the family says cannot interact with these effects stay where the
    # reference fit put them (e.g. flow capacities when only the torque balance changes)
    frozen_names: set[str] = (getattr(family, "frozen", lambda _e: set())(effects) - (free or set())) | set(hold)
    fixed = {s.name: min(max(first.get(s.name, s.x0), s.lo), s.hi) for s in all_specs if s.name in frozen_names}
    specs = [s for s in all_specs if s.name not in fixed]
    scales = scales or channel_scales(family, preps)
    meas = [family.measured(p) for p in preps]
    prefetch = getattr(family, "prefetch", None)

    def params_at(x: np.ndarray) -> dict[str, float]:
        return fixed | _from_x(specs, x)

    def resid(x: np.ndarray) -> np.ndarray:
        raise_if_stopped(stop)
        v = params_at(x)
        if prefetch is not None:
            prefetch(preps, [v], effects)
        return _residuals(family, preps, meas, v, effects, scales)

    lo, hi = _bounds(specs)
    # a replayed simulator with switching (valve hysteresis, stiction) is piecewise smooth:
    # difference steps of the family's size see through the jumps
    diff_step = getattr(family, "diff_step", None)
    max_nfev = getattr(family, "max_nfev", 200 * (len(specs) + 1))
    # descend from the best of the starting points (one descent: each costs many replays)
    xs = [_to_x(specs, st) for st in starts or [start or {}]]
    x_best = xs[0] if len(xs) == 1 else min(xs, key=lambda x: float(np.sum(resid(x) ** 2)))
    tol = getattr(family, "tol", 1e-8)

    def jacobian_columns(f: Callable[[np.ndarray], np.ndarray], xs: Iterable[np.ndarray]) -> list[np.ndarray]:
        # least squares' difference quotients: one prefetch for all of a Jacobian's points (the
        # replays of one log at a time had left a core idle at the end of each), then the same
        # evaluations in the same order from the cache
        pts = list(xs)
        if prefetch is not None:
            prefetch(preps, [params_at(x) for x in pts], effects)
        return [f(x) for x in pts]

    sol = least_squares(resid, x_best, bounds=(lo, hi), x_scale="jac", max_nfev=max_nfev, diff_step=diff_step,
                        ftol=tol, xtol=tol, workers=jacobian_columns)
    if fallback is not None:
        x_fb = _to_x(specs, fallback)
        r_fb = resid(x_fb)
        if float(r_fb @ r_fb) < float(sol.fun @ sol.fun):
            sol = least_squares(resid, x_fb, bounds=(lo, hi), x_scale="jac", max_nfev=max_nfev,
                                diff_step=diff_step, ftol=tol, xtol=tol, workers=jacobian_columns)
    params = params_at(sol.x)
    params = {sp.name: params[sp.name] for sp in all_specs}
    jac = sol.jac
    # k counts the frozen parameters too: they were fitted on the same data by the reference
    n, k = int(sol.fun.size), len(all_specs)
    rss = float(sol.fun @ sol.fun)
    sd: dict[str, float] = {name: math.nan for name in fixed}
    corr = np.eye(len(specs))
    cond = math.inf
    try:
        s = np.linalg.svd(jac, compute_uv=False)
        cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
        cov = np.linalg.pinv(jac.T @ jac) * rss / max(n - k, 1)
        dsd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = np.nan_to_num(cov / np.outer(dsd, dsd))
        for i, sp in enumerate(specs):
            # log-space SDs map to linear ones by the delta method
            sd[sp.name] = float(dsd[i] * (params[sp.name] if sp.log else 1.0))
    except np.linalg.LinAlgError:
        sd = {sp.name: math.nan for sp in all_specs}
    at_bound = [sp.name for sp, v, a, b in zip(specs, sol.x, lo, hi, strict=True)
                if abs(v - a) <= 1e-6 * max(1.0, abs(a)) or abs(v - b) <= 1e-6 * max(1.0, abs(b))]
    return Fit(effects, params, sd, at_bound, corr, cond, rss, n, k, [sp.name for sp in specs])


def _units(n: int, blocks: int) -> list[np.ndarray]:
    edges = np.linspace(0, n, blocks + 1).astype(int)
    return [np.arange(a, b) for a, b in itertools.pairwise(edges) if b > a]


def score(family: Family, preps: list[Any], f: Fit, blocks: int) -> Scores:
    """Held-out squared errors per unit (experiment, or ``blocks`` time blocks of each) and channel."""
    return score_at(family, preps, f.params, f.effects, blocks)


def score_at(family: Family, preps: list[Any], params: dict[str, float], effects: tuple[str, ...],
             blocks: int) -> Scores:
    """:func:`score` of the model with ``effects`` at ``params`` (fitted or not)."""
    rows_sse, rows_cnt = [], []
    prefetch = getattr(family, "prefetch", None)
    if prefetch is not None:
        prefetch(preps, [params], effects)
    for p in preps:
        pr = family.predict(p, params, effects)
        m = family.measured(p)
        n = len(m[family.channels[0]])
        for idx in _units(n, blocks):
            rows_sse.append([float(np.nansum((pr[c][idx] - m[c][idx]) ** 2)) for c in family.channels])
            rows_cnt.append([int(np.isfinite(pr[c][idx] - m[c][idx]).sum()) for c in family.channels])
    return Scores(np.asarray(rows_sse), np.asarray(rows_cnt, dtype=float))


def noise_floor(family: Family, preps: Sequence[Any], meas: Sequence[dict[str, np.ndarray]]) -> np.ndarray:
    """Per channel, the RMS error the sensors' noise alone leaves a right model over ``preps``.

    The same pooling as E (:func:`_e`): the noise's variance weighted by the
    share of it the scored samples carry (:meth:`Family.noise_shows`). The
    rotary torque's prediction at standstill is the measurement clipped to
    what stiction holds, so there every model scores no error. Counting the
    full noise there had read the protocol's torque floor 1.4–1.75 times what
    the noise adds to a right model's error (0.83–1.07 times now; measured
    on the same rig with its torque sensor noise-free, docs/diagnosis-record.md).

    Args:
        family: The rig family.
        preps: Prepared logs.
        meas: Their :meth:`Family.measured` channels.

    Returns:
        Noise floor per channel of ``family.channels`` [channel units].
    """
    out = []
    for c in family.channels:
        # a sensor's noise is the same in every log of one rig: the median over the logs keeps an
        # experiment whose signal has content at the sample rate (a fast sine's torque) from
        # passing that content off as noise and raising the floor
        sd = float(np.median([family.noise(p)[c] for p in preps]))
        carried = scored = 0.0
        for p, m in zip(preps, meas, strict=True):
            ok = np.isfinite(m[c])
            w = family.noise_shows(p).get(c)
            scored += float(ok.sum())
            carried += float(ok.sum()) if w is None else float(np.clip(w[ok], 0.0, 1.0).sum())
        out.append(sd * math.sqrt(carried / scored) if scored > 0 else sd)
    return np.asarray(out)


@dataclass
class _Norm:
    spread: np.ndarray  # per channel SD of the held-out measurement
    floor: np.ndarray  # per channel noise SD


def _e(sc: Scores, norm: _Norm, rows: np.ndarray | slice = slice(None)) -> tuple[float, np.ndarray]:
    sse = sc.sse[rows].sum(axis=0)
    cnt = np.maximum(sc.cnt[rows].sum(axis=0), 1.0)
    nrmse = np.sqrt(sse / cnt) / norm.spread
    return float(nrmse.mean()), nrmse


def gap_closure(base: Scores, with_: Scores, norm: _Norm, rows: np.ndarray | slice = slice(None)) -> float:
    """GC = (E_base − E_with)/(E_base − E_floor) over the held-out ``rows``."""
    eb, _ = _e(base, norm, rows)
    ew, _ = _e(with_, norm, rows)
    ef = float((norm.floor / norm.spread).mean())
    return (eb - ew) / (eb - ef) if eb - ef > 1e-12 else 0.0


def bootstrap_gc(base: Scores, with_: Scores, norm: _Norm, seed: int = 0) -> tuple[float, float]:
    """5 % and 95 % points of GC over resampled held-out units."""
    rng = np.random.default_rng(seed)
    n = base.sse.shape[0]
    gcs = [gap_closure(base, with_, norm, np.asarray(rng.integers(0, n, n))) for _ in range(N_BOOT)]
    return float(np.percentile(gcs, 5)), float(np.percentile(gcs, 95))


def bootstrap_gap(base: Scores, norm: _Norm, seed: int = 2) -> tuple[float, float]:
    """5 % and 95 % points of E_base − E_floor over resampled held-out units: is there a gap at all?"""
    rng = np.random.default_rng(seed)
    n = base.sse.shape[0]
    ef = float((norm.floor / norm.spread).mean())
    gaps = [_e(base, norm, np.asarray(rng.integers(0, n, n)))[0] - ef for _ in range(N_BOOT)]
    return float(np.percentile(gaps, 5)), float(np.percentile(gaps, 95))


GC_TIE = 1e-9
"""A GC difference this small is rounding, not a difference (two models that predict the same)."""


def bootstrap_gc_difference(base: Scores, a: Scores, b: Scores, norm: _Norm, seed: int = 1) -> tuple[float, float]:
    """5 % and 95 % points of GC(a) − GC(b) on the same resampled held-out units (paired).

    Differences within :data:`GC_TIE` of 0 count as 0: two models that make the
    same predictions differ only by rounding, and rounding has a sign (an
    offset and a slope per sign fitted to a signal that is only ever ±1 had a
    CI of [8e-15, 2e-13], which excluded 0 and called them distinguishable;
    with another numpy build it had held 0).
    """
    rng = np.random.default_rng(seed)
    n = base.sse.shape[0]
    d = np.empty(N_BOOT)
    for k in range(N_BOOT):
        rows = np.asarray(rng.integers(0, n, n))
        d[k] = gap_closure(base, a, norm, rows) - gap_closure(base, b, norm, rows)
    d[np.abs(d) < GC_TIE] = 0.0
    return float(np.percentile(d, 5)), float(np.percentile(d, 95))


def ljung_box(r: np.ndarray, lags: int = 10) -> tuple[list[float], float]:
    """Autocorrelation at lags 1…``lags`` and the Ljung–Box p-value (white residuals: p large)."""
    r = r[np.isfinite(r)]
    r = r - r.mean()
    n = r.size
    den = float(r @ r) or 1.0
    ac = [float(r[:-k] @ r[k:]) / den for k in range(1, lags + 1)]
    q = n * (n + 2) * sum(a * a / (n - k) for k, a in enumerate(ac, start=1))
    return ac, float(stats.chi2.sf(q, lags))


TRACE_POINTS = 300
"""Points per log and series in :func:`traces`: a chart's width, not the log's rate."""


def traces(family: Family, preps: list[Any], fits: dict[str, Fit], names: list[str],
           points: int = TRACE_POINTS, confusable: dict[str, Fit] | None = None) -> list[dict[str, Any]]:
    """Each log's measured channels over time beside the predictions of ``fits``: where in time a gap lies.

    Block means of at most ``points`` per series, four significant digits: the report's tables say
    how large the residuals are, this says when. Every series of a channel skips the samples its
    measurement does not score (a block with none is null), so their means cover the same samples.

    Args:
        family: The rig family.
        preps: Prepared logs.
        fits: Label → fit (the baseline, the model the verdict ends with).
        names: The logs' names.
        points: Points per series.
        confusable: Effect → its single fit, for the effects the verdict cannot tell from its own:
            each channel gets their series under ``confusable`` (where in time they differ, if anywhere).

    Returns:
        Per log: ``log``, ``t`` [s from its start] and, per channel, ``measured`` and each label's series.
    """
    def blocks(x: np.ndarray, size: int) -> list[float | None]:
        x = np.asarray(x, dtype=float)
        pad = np.full((-len(x)) % size, np.nan)
        grid = np.concatenate([x, pad]).reshape(-1, size)
        ok = np.isfinite(grid)
        n = ok.sum(axis=1)
        m = np.where(ok, grid, 0.0).sum(axis=1) / np.maximum(n, 1)
        return [float(f"{v:.4g}") if k else None for v, k in zip(m, n, strict=True)]

    out = []
    for prep, name in zip(preps, names, strict=True):
        t = family.times(prep)
        size = max(1, math.ceil(len(t) / points))
        meas = family.measured(prep)
        preds = {label: family.predict(prep, f.params, f.effects) for label, f in fits.items()}
        others = {label: family.predict(prep, f.params, f.effects) for label, f in (confusable or {}).items()}
        channels: dict[str, Any] = {}
        for c in family.channels:
            # a prediction is averaged over the samples its measurement scores, so both means cover the same
            seen = np.isfinite(meas[c])
            channels[c] = {"measured": blocks(meas[c], size)} | {
                label: blocks(np.where(seen, pr[c], np.nan), size) for label, pr in preds.items()}
            if others:
                channels[c]["confusable"] = {label: blocks(np.where(seen, pr[c], np.nan), size)
                                             for label, pr in others.items()}
        out.append({"log": name, "t": blocks(t, size), "channels": channels})
    return out


def where(family: Family, preps: list[Any], f: Fit, floor: np.ndarray,
          names: list[str] | None = None) -> list[dict[str, Any]]:
    """Residuals of fit ``f`` per channel, regime and log, whiteness and input cross-correlation.

    Each channel's ``noise`` is its sensor's noise SD, ``floor`` the RMS that
    noise alone leaves a right model, to which ``rms`` compares. Under
    ``experiments`` each log's RMS and its ``share`` of the channel's summed
    squared residual: which experiment the gap lies in (on the rig model of
    ``bench/independent_rig.py`` the DCV steps carried 80 % of p_a's).

    Args:
        family: The rig family.
        preps: Prepared logs.
        f: The fit whose residuals are read.
        floor: :func:`noise_floor` of ``preps``, per channel of ``family.channels``.
        names: The logs' names (default: their order).
    """
    out: list[dict[str, Any]] = []
    res = {c: [] for c in family.channels}  # type: dict[str, list[np.ndarray]]
    masks: dict[str, list[np.ndarray]] = {}
    ins: dict[str, list[np.ndarray]] = {}
    for p in preps:
        pr = family.predict(p, f.params, f.effects)
        m = family.measured(p)
        for c in family.channels:
            res[c].append(pr[c] - m[c])
        for k, v in family.regimes(p).items():
            masks.setdefault(k, []).append(v)
        for k, v in family.inputs(p).items():
            ins.setdefault(k, []).append(v)
    noise = channel_scales(family, preps)
    tt = family.times(preps[0]) if preps else np.zeros(0)
    dt = float(tt[1] - tt[0]) if len(tt) > 1 else math.nan  # the scored samples' spacing [s]
    # what the RMS is to be read against: where the prediction is built from the measurement (the
    # rotary torque at standstill) the sensor's noise cancels, so its SD alone would flatter the fit
    for c, fl in zip(family.channels, floor, strict=True):
        r = np.concatenate(res[c])
        ac, p_white = ljung_box(r)
        entry: dict[str, Any] = {"channel": c, "rms": float(np.sqrt(np.nanmean(r ** 2))),
                                 "bias": float(np.nanmean(r)), "noise": noise[c], "floor": float(fl),
                                 "autocorr_lag1_10": ac, "ljung_box_p": p_white, "regimes": {}, "input_xcorr": {},
                                 "experiments": {}}
        total = float(np.nansum(r ** 2))
        for j, rj in enumerate(res[c]):
            if np.isfinite(rj).any():
                sq = float(np.nansum(rj ** 2))
                entry["experiments"][names[j] if names else str(j)] = {
                    "rms": float(np.sqrt(np.nanmean(rj ** 2))), "share": sq / total if total > 0.0 else 0.0}
        for k, ms in masks.items():
            mk = np.concatenate(ms) & np.isfinite(r)  # unscored samples (NaN) belong to no regime
            if mk.sum() >= 5:
                entry["regimes"][k] = {"rms": float(np.sqrt(np.nanmean(r[mk] ** 2))), "bias": float(np.nanmean(r[mk])),
                                       "n": int(mk.sum()), "share": float(mk.mean())}
        for k, vs in ins.items():
            xc = input_xcorr(np.concatenate(vs), r, inputs=len(ins))
            if xc is not None:
                entry["input_xcorr"][k] = xc | {"lag_s": xc["lag_samples"] * dt}
        out.append(entry)
    return out


XCORR_LAGS = 50
"""Lags [scored samples] over which a residual's cross-correlation with an input is read (the residual later)."""


def xcorr_z(inputs: int = 1, lags: int = XCORR_LAGS) -> float:
    """Standard errors a cross-correlation must pass for a 5 % test over ``lags`` lags of ``inputs`` inputs.

    One channel's residual is tested against each input: at 5 % per input, the chance of naming one it does
    not follow is up to 23 % per channel of five (Bonferroni over both: 3.29 for one input, 3.72 for five).
    """
    return float(stats.norm.isf(0.05 / 2.0 / (max(1, lags) * max(1, inputs))))


def _acf(z: np.ndarray, lags: int) -> np.ndarray:
    """Autocorrelation of ``z`` (mean zero) at lags 0…``lags`` (by FFT: the logs are 10⁴–10⁵ samples)."""
    n = z.size
    f = np.fft.rfft(z, 2 * n)
    a = np.fft.irfft(f * np.conj(f), 2 * n)[: lags + 1]
    return a / a[0] if a[0] > 0 else np.zeros(lags + 1)


def input_xcorr(u: np.ndarray, r: np.ndarray, lags: int = XCORR_LAGS, inputs: int = 1) -> dict[str, Any] | None:
    """The residual ``r``'s largest cross-correlation with input ``u`` over lags 0…``lags``−1 (``r`` later).

    Significant when it passes a 5 % test over all the lags and the ``inputs`` the residual is tested
    against (:func:`xcorr_z` standard errors: 3.29 for one input), with the
    standard error of two autocorrelated series (Bartlett 1946: var ≈ (1/n)·Σ_j ρ_u(j)·ρ_r(j)). A step
    command and a slow residual are each far fewer independent samples than n: the white-noise error
    1/√n, and 3 of them at the largest of 50 lags, which the report used before, called a slow residual
    significantly correlated with a step command drawn apart from it in 17 of 20 draws; this test, in none
    (``test_an_input_is_not_called_significant_for_a_slow_residual_it_does_not_drive``).

    Args:
        u: The input, sample by sample.
        r: The residual on the same samples (NaN where unscored).
        lags: Lags read [samples].
        inputs: How many inputs the same residual is tested against (the test is family-wise over them).

    Returns:
        ``max_abs``, ``lag_samples``, ``se``, ``z`` (the standard errors it had to pass) and
        ``significant``; None when either series is constant.
    """
    ok = np.isfinite(r)
    if np.std(u) == 0 or ok.sum() < 10 or not np.nanstd(r) > 0:
        return None
    n = r.size
    du = (u - u.mean()) / u.std()
    rr = (r - np.nanmean(r)) / np.nanstd(r)
    xc = [float(np.nanmean(du[: n - k] * rr[k:])) for k in range(min(lags, n // 4))]
    j = int(np.argmax(np.abs(xc)))
    m = max(1, min(n // 10, 2000))
    var = (1.0 + 2.0 * float(np.sum(_acf(du, m)[1:] * _acf(np.where(ok, rr, 0.0), m)[1:]))) / ok.sum()
    se = math.sqrt(max(var, 1.0 / ok.sum()))
    z = xcorr_z(inputs, lags)
    return {"max_abs": abs(xc[j]), "lag_samples": j, "se": se, "z": z, "significant": abs(xc[j]) > z * se}


@dataclass
class Candidate:
    """How one candidate effect did."""

    effect: str
    fit: Fit
    scores: Scores
    gap_closure: float
    ci: tuple[float, float]
    delta_bic: float
    nrmse: dict[str, float]
    improvement: dict[str, float]
    significant: bool
    relevant: bool
    switched_off: bool = False
    rebased_gap_closure: float | None = None
    why_not: tuple[str, ...] = ()  # the significance tests it failed, in words (empty when significant)

    def as_dict(self) -> dict[str, Any]:
        """JSON view."""
        return {"effect": self.effect, "gap_closure": self.gap_closure, "switched_off": self.switched_off,
                "not_significant_because": list(self.why_not),
                "rebased_gap_closure": self.rebased_gap_closure,
                "params_at_bound": [n for n in self.fit.at_bound if "." in n], "gap_closure_ci90": list(self.ci),
                "delta_bic": self.delta_bic, "significant": self.significant, "relevant": self.relevant,
                "nrmse": self.nrmse, "rms_improvement": self.improvement,
                "params": {k: v for k, v in self.fit.params.items() if "." in k},
                "params_sd": {k: v for k, v in self.fit.sd.items() if "." in k},
                "baseline_params": {k: v for k, v in self.fit.params.items() if "." not in k}}


def _evaluate(family: Family, calib: list[Any], held: list[Any], ref: Fit, ref_sc: Scores, effects: tuple[str, ...],
              norm: _Norm, blocks: int, scales: dict[str, float], stop: threading.Event | None = None) -> Candidate:
    # from the effect switched off (the reference, where "off" vanishes exactly) and from its typical size
    new = [p for e in effects for p in family.effect(e) if p.name not in ref.params]
    off = ref.params | {p.name: p.x0 if p.off is None else p.off for p in new}
    typ = ref.params | {p.name: p.x0 for p in new}
    starts = [off, typ] if off != typ else [off]
    # Where the family leaves the effect out at its "off" values, the cost jumps there: a descent
    # from that start sees only the jump and stays. It is the fallback, not a start: once the
    # replay at "off" was the baseline itself, the cheapest start on a rig written apart from ours
    # was that one for a 5 m tube, whose fit had closed 0.52 of the held-out gap from its grid's start
    fallback = None
    if off != typ and getattr(family, "drops_at_off", lambda _e: False)(effects[-1]):
        starts, fallback = [typ], off
    hold = held_form(family, ref.params)
    moved = [g for g in form_groups(family) if g[0].name not in hold]
    points = int(getattr(family, "grid_points", 0))
    rounds = int(getattr(family, "grid_refinements", 1))
    rebase = set(getattr(family, "rebase", lambda _e: set())(effects))
    prior = ref.params | {s.name: s.x0 for s in family.baseline() if s.name in rebase}
    linear = getattr(family, "linear_start", None)
    lin_ref = linear(calib, off, effects) if linear is not None else None
    if lin_ref is not None:
        # parameters that enter (nearly) linearly start from their least-squares values,
        # which a coarse grid over their range only approximates
        starts.append(lin_ref)
    if points and new and prior != ref.params:
        # The reference recalibrated its baseline without the effect, so some of its values
        # stand in for it (a missing heat exchange shrank the fitted dead volumes by a third).
        # On a rough cost surface a descent from there rarely travels back, so the grid runs
        # with those parameters at their nominal values; the reference's own starts (the effect
        # off or typical) stay in the running, and the cheapest start is descended from.
        raise_if_stopped(stop)
        grid_base = [p for g in base_groups(family) for p in g if p.name in rebase]

        def gridded(p0: dict[str, float]) -> dict[str, float]:
            # an effect with a linear start needs no grid of its own, only that start from the
            # nominal values, taken again once the baseline's grid has moved them
            lin = linear(calib, p0 | {p.name: off[p.name] for p in new}, effects) if linear is not None else None
            st = lin if lin is not None else _grid_start(family, calib, effects, p0, new, points, scales, rounds)
            # then the nominal values themselves move on the baseline's own grid, the effect where
            # its grid put it: from nominal the descent had left them there (a vane leak's fit kept
            # the flow capacities and dead volumes at 1.00 × nominal for a true 0.92 / 0.82 / 1.19 ×,
            # at 6 × the truth's calibration cost)
            # the model's form too, from its grid's own levels: the reference's form may stand in for
            # the effect as well (a valve left leaking at its centre for a chamber that leaks)
            for group in moved:
                st = _grid_start(family, calib, effects, st, group, 3, scales)
            if grid_base:
                st = _grid_start(family, calib, effects, st, grid_base, 3, scales)
                if lin is not None and linear is not None:
                    st = linear(calib, st, effects) or st
            return st

        grid_starts = [gridded(prior)]
        # and where the reference moved the model's form, the effect's grid runs again beside the
        # form it found, the flows and volumes still nominal: a form far from nominal (a valve shut
        # at its centre, a regulator without hysteresis) is more than the form grid's three levels
        # per parameter find back, and under the nominal form the effect's grid chose another basin
        # (on a rig written apart from ours, bench/independent_rig.py, a 5 m tube's grid chose 10 cm
        # of 12 mm bore, GC 0.14; beside the form the recalibration found, 4.9 m of 3.4 mm, GC 0.73)
        beside_form = prior | {p.name: ref.params[p.name] for g in moved for p in g}
        if beside_form != prior:
            grid_starts.append(gridded(beside_form))
        # One descent, not one from each: a least-squares descent never ends above its start, so
        # the fit is still never worse than its effect-off start (see docs/diagnosis-record.md, "One descent")
        f = fit(family, calib, effects, scales=scales, stop=stop, starts=[*starts, *grid_starts], free=rebase,
                hold=hold, fallback=fallback)
    else:
        if lin_ref is None and points and new:
            raise_if_stopped(stop)
            starts.append(_grid_start(family, calib, effects, ref.params, new, points, scales, rounds))
        f = fit(family, calib, effects, scales=scales, starts=starts, stop=stop, hold=hold, fallback=fallback)
    sc = score(family, held, f, blocks)
    gc = gap_closure(ref_sc, sc, norm)
    ci = bootstrap_gc(ref_sc, sc, norm)
    _, nr = _e(sc, norm)
    imp = rms_gain(family, ref_sc, sc)
    relevant = any(imp[c] > family.relevance.get(c, 0.0) for c in family.channels)
    dbic = ref.bic - f.bic
    # An effect its own fit left where it vanishes explains nothing: whatever that fit gained came
    # from the baseline's parameters it refitted beside it (the browser test's effect-free rig once
    # named external_leakage at c = 1e-5 l/(s·bar), its off bound, with GC 0.79)
    gone = switched_off(new, f.params)
    # An effect whose every parameter its fit pushed onto a bound of its range (not where it
    # vanishes) is mimicking a shape it cannot make: the data want something past its physics
    # (the ranking already put such a fit below one inside its bounds: _rank_key)
    pinned = not gone and bool(new) and all(p.name in f.at_bound for p in new)
    sig = dbic > BIC_STRONG and ci[0] > 0.0 and gc >= GC_MIN and relevant and not gone and not pinned
    static = None
    part = getattr(family, "static_part", lambda _e: None)(effects[-1]) if sig else None
    if part is not None:
        # a dynamic effect whose gain stays once its dynamics are taken out is its static part:
        # a flow form of the baseline's, not the effect
        gc_static = gap_closure(ref_sc, score_at(family, held, f.params | part[0], effects, blocks), norm)
        if gc_static >= STATIC_SHARE * gc:
            sig, static = False, f"its gain stays with {part[1]} (GC {gc_static:.3g} of {gc:.3g})"
    why = () if sig else _why_not(family, gc, ci, dbic, imp, relevant, gone,
                                  [(p, f.params[p.name]) for p in new] if pinned else [])
    return Candidate(effects[-1], f, sc, gc, ci, dbic, dict(zip(family.channels, map(float, nr), strict=True)),
                     imp, sig, relevant, gone, _rebased_gc(family, held, ref, ref_sc, f, new, norm, blocks),
                     (*why, static) if static else why)


def form_groups(family: Family) -> list[list[Param]]:
    """The family's groups of form parameters (``form_grids``), each searched on its own grid."""
    return [list(g) for g in getattr(family, "form_grids", ()) if g]


def held_form(family: Family, params: dict[str, float]) -> list[str]:
    """The family's form parameters (``form_grids``) in groups that ``params`` has all nominal.

    A group the recalibration kept nominal stays so in every later fit (see
    :func:`recalibrate`); one it moved, those fits move on.
    """
    return [p.name for g in form_groups(family) if all(params[p.name] == p.x0 for p in g) for p in g]


def _why_not(family: Family, gc: float, ci: tuple[float, float], dbic: float, imp: dict[str, float],
             relevant: bool, gone: bool, pinned: Sequence[tuple[Param, float]] = ()) -> tuple[str, ...]:
    """The significance tests a candidate failed, in words a report's reader can check against its numbers."""
    out = []
    if gone:
        out.append("its fit left it switched off")
    if pinned:
        out.append("every parameter on a bound of its range (" + ", ".join(
            f"{p.name.split('.', 1)[-1]} {v:.3g} {p.unit}, its {'lower' if abs(v - p.lo) <= abs(v - p.hi) else 'upper'}"
            for p, v in pinned) + "): it mimics a shape it cannot make")
    if dbic <= BIC_STRONG:
        out.append(f"ΔBIC {dbic:.3g} ≤ {BIC_STRONG:g}")
    if ci[0] <= 0.0:
        out.append(f"GC's CI reaches {ci[0]:.3g} ≤ 0")
    if gc < GC_MIN:
        out.append(f"GC {gc:.3g} < {GC_MIN:g}")
    if not relevant:
        best = max(family.channels, key=lambda c: imp[c] - family.relevance.get(c, 0.0))
        out.append(f"RMS gain under what matters on the rig (most: {best} {imp[best]:.3g} ≤ "
                   f"{family.relevance.get(best, 0.0):g})")
    return tuple(out)


def _rebased_gc(family: Family, held: list[Any], ref: Fit, ref_sc: Scores, f: Fit, new: list[Param], norm: _Norm,
                blocks: int) -> float | None:
    """Held-out GC of ``f`` with its last effect taken out: what the values it refitted beside it close alone.

    None when the fit moved none of the reference's values (the reference itself, GC 0).
    """
    names = {p.name for p in new}
    kept = {k: v for k, v in f.params.items() if k not in names}
    if all(kept[k] == ref.params.get(k) for k in kept):
        return None
    return gap_closure(ref_sc, score_at(family, held, kept, f.effects[:-1], blocks), norm)


STATIC_SHARE = 0.9
"""A dynamic effect whose fit keeps this share of its gap closure with its dynamics taken out
(the family's ``static_part``) is credited to its static part, not to the effect."""

OFF_TOLERANCE = 1e-3
"""How near its ``off`` value a fitted parameter counts as there, as a share of its range
(of the log range for a log parameter)."""


def switched_off(new: list[Param], params: dict[str, float]) -> bool:
    """Whether a fit left every parameter of ``new`` at its declared ``off`` value.

    Args:
        new: An effect's parameters; one without a declared ``off`` (an
            effect with no value at which it vanishes) makes the answer False.
        params: The fitted values.
    """
    offs = [(p, p.off) for p in new if p.off is not None]
    if not new or len(offs) < len(new):
        return False

    def there(p: Param, off: float) -> bool:
        v = params[p.name]
        if p.log:
            return abs(math.log(v / off)) <= OFF_TOLERANCE * math.log(p.hi / p.lo)
        return abs(v - off) <= OFF_TOLERANCE * (p.hi - p.lo)

    return all(there(p, off) for p, off in offs)


def _grid_start(family: Family, preps: list[Any], effects: tuple[str, ...], ref: dict[str, float],
                new: list[Param], points: int, scales: dict[str, float], rounds: int = 1) -> dict[str, float]:
    """The best point of a coarse grid over the new effect's parameters (the rest at ``ref``), refined ``rounds`` times.

    See :func:`_grid_best`, which also returns the point's calibration cost.
    """
    return _grid_best(family, preps, effects, ref, new, points, scales, rounds)[0]


def _grid_best(family: Family, preps: list[Any], effects: tuple[str, ...], ref: dict[str, float],
               new: list[Param], points: int, scales: dict[str, float],
               rounds: int = 1, levels: int | None = None) -> tuple[dict[str, float], float]:
    """The best point of a coarse grid over ``new`` (the rest at ``ref``), refined ``rounds`` times, and its cost.

    A replayed simulator with switching elements has a rough cost surface on
    which finite-difference descent from one start stalls; a grid over at
    most three bounded parameters (``points``, ``⌈points/2⌉`` or 3 values per
    axis) finds the right basin first. Each refinement is a grid of as many
    points spanning one step of the previous grid either side of the best:
    valleys narrower than a coarse step (a supply droop's resistance and time
    constant trade along one, a decade apart on the coarse grid) are found
    there. With 3 values per axis a refinement keeps the spacing, so it
    recentres only once. ``levels`` sets the values per axis outright.
    """
    per = levels or {1: points, 2: max(3, (points + 1) // 2)}.get(len(new), 3)
    meas = [family.measured(p) for p in preps]

    def best_of(axes: list[np.ndarray]) -> tuple[dict[str, float], float]:
        costs = _grid_costs(family, preps, meas, effects, ref, new, axes, scales)
        best, best_cost = costs[0][0], math.inf
        for v, cost in costs:
            if cost < best_cost:
                best, best_cost = v, cost
        return best, best_cost

    def axis(p: Param, lo: float, hi: float) -> np.ndarray:
        return _axis(p, lo, hi, per)

    best, best_cost = best_of([axis(p, p.lo, p.hi) for p in new])
    steps = {p.name: ((math.log(p.hi) - math.log(p.lo)) if p.log else (p.hi - p.lo)) / (per - 1) for p in new}
    for _ in range(rounds if per > 3 else 1):
        fine = []
        for p in new:
            v, step = best[p.name], steps[p.name]
            if p.log:
                fine.append(axis(p, max(p.lo, v * math.exp(-step)), min(p.hi, v * math.exp(step))))
            else:
                fine.append(axis(p, max(p.lo, v - step), min(p.hi, v + step)))
            steps[p.name] = 2.0 * step / (per - 1)
        cand, cand_cost = best_of(fine)
        if cand_cost <= best_cost:
            best, best_cost = cand, cand_cost
    return best, best_cost


def _axis(p: Param, lo: float, hi: float, per: int) -> np.ndarray:
    """``per`` values of ``p`` from ``lo`` to ``hi``, evenly spaced (in log space for a log parameter)."""
    return np.exp(np.linspace(math.log(lo), math.log(hi), per)) if p.log else np.linspace(lo, hi, per)


def _grid_costs(family: Family, preps: list[Any], meas: list[dict[str, np.ndarray]], effects: tuple[str, ...],
                ref: dict[str, float], new: list[Param], axes: list[np.ndarray],
                scales: dict[str, float]) -> list[tuple[dict[str, float], float]]:
    """Every point of the grid ``axes`` over ``new`` (the rest at ``ref``) with its cost, ``ref``'s own point first."""
    cands = [ref | {p.name: float(v) for p, v in zip(new, combo, strict=True)} for combo in itertools.product(*axes)]
    # on a tie the reference's own point wins (a form whose parameter has no effect where
    # another puts it, such as a dead band at a centre that leaks, is no other form)
    cands.sort(key=lambda v: v != ref)
    prefetch = getattr(family, "prefetch", None)
    if prefetch is not None:
        prefetch(preps, cands, effects)
    out = []
    for v in cands:
        r = _residuals(family, preps, meas, v, effects, scales)
        out.append((v, float(r @ r)))
    return out


def _weigh(base_sc: Scores, win: Candidate, c: Candidate, norm: _Norm) -> tuple[float, float, bool]:
    """The 90 % CI of GC(win) − GC(c), paired, and whether ``c`` is a plausible rival at all
    (significant, or relevant with a CI reaching ``win``'s)."""
    lo, hi = bootstrap_gc_difference(base_sc, win.scores, c.scores, norm)
    return lo, hi, c.significant or (c.relevant and c.ci[1] >= win.ci[0])


def _alternatives(family: Family, calib: list[Any], held: list[Any], base: Fit, base_sc: Scores,
                  selected: list[Candidate], singles: list[Candidate], norm: _Norm, blocks: int,
                  scales: dict[str, float], stop: threading.Event | None
                  ) -> tuple[list[dict[str, Any]], dict[str, tuple[tuple[str, ...], Scores]]]:
    """Each selected effect against the family's explanations of the same gap that need no effect.

    A family may name, per effect, a baseline of another form that could
    close the same gap (``alternatives(effect)``: a rotary rig's sensor
    offsets against friction levels that differ per direction). Each is
    fitted and scored like a candidate, from the same baseline; it is
    *confusable* with the effect when it is plausible (as for two effects)
    and a paired bootstrap of GC(effect) − GC(alternative) contains 0, and
    *better* when that interval lies below 0. A better alternative is then
    taken as the reference and the effect fitted on top of it: if the
    effect is no longer significant there, it is ``dropped`` from the
    verdict (the gap is the baseline's form, not an unmodelled effect).
    Otherwise the verdict keeps the effect and names the alternative beside
    it, with the step that tells the two apart. When the effect explains
    clearly more and the alternative is significant on its own, the
    alternative is fitted beside the effect: significant there too, both
    are present (``also``), and the joint fit's parameters are reported.

    Returns:
        The rows, and per effect whose verdict the alternatives change, the
        model the verdict then describes (its effects and alternatives) with
        its held-out scores: the alternative alone (dropped), the effect
        beside it (better, not dropped), or both fitted together (``also``).
    """
    alt_of = getattr(family, "alternatives", None)
    if alt_of is None:
        return [], {}
    out: list[dict[str, Any]] = []
    verdict_model: dict[str, tuple[tuple[str, ...], Scores]] = {}
    for s in selected:
        win = next(c for c in singles if c.effect == s.effect)
        for name, info in alt_of(s.effect).items():
            c = _evaluate(family, calib, held, base, base_sc, (name,), norm, blocks, scales, stop)
            lo, hi, plausible = _weigh(base_sc, win, c, norm)
            better = bool(plausible and hi < 0.0)
            row = c.as_dict() | {"explanation": name, "instead_of": s.effect, **info,
                                 "effect_gap_closure": win.gap_closure, "gc_difference_ci90": [lo, hi],
                                 "confusable": bool(plausible and lo <= 0.0 <= hi), "better": better,
                                 "dropped": False, "also": False}
            if better:
                beside = _evaluate(family, calib, held, c.fit, c.scores, (name, s.effect), norm, blocks, scales,
                                   stop)
                row |= {"effect_beside_it": {"gap_closure": beside.gap_closure, "gap_closure_ci90": list(beside.ci),
                                             "delta_bic": beside.delta_bic, "significant": beside.significant},
                        "dropped": not beside.significant}
                verdict_model[s.effect] = ((name,), c.scores) if row["dropped"] else ((name, s.effect),
                                                                                     beside.scores)
            elif not row["confusable"] and c.significant:
                # the effect explains more, but the alternative may be there as well (a rig with sensor
                # offsets whose friction also differs per direction: the torque offset took the
                # friction's share, 0.28 N·m for a true 0.1)
                both = _evaluate(family, calib, held, win.fit, win.scores, (s.effect, name), norm, blocks, scales,
                                 stop)
                # significant without the relevance in RMS: where the two act alike (in motion a torque
                # offset and friction per direction are one constant) the joint fit mostly moves the
                # split between them, which the held-out prediction shows only where they differ
                # (breakaway, the Stribeck range): GC 0.25 and 0.20 of what the offsets left on two such
                # rigs, at most 0.01 on six with offsets alone
                also = (both.delta_bic > BIC_STRONG and both.ci[0] > 0.0 and both.gap_closure >= GC_MIN
                        and not both.switched_off)
                row |= {"beside_effect": {"gap_closure": both.gap_closure, "gap_closure_ci90": list(both.ci),
                                          "delta_bic": both.delta_bic, "significant": bool(also),
                                          "relevant": both.relevant,
                                          "params": {k: v for k, v in both.fit.params.items() if "." in k}},
                        "also": bool(also)}
                if also:
                    verdict_model[s.effect] = ((s.effect, name), both.scores)
            out.append(row)
    return out, verdict_model


def _baseline_beaten(singles: Sequence[Candidate]) -> dict[str, Any] | None:
    """The candidate fit whose refitted baseline values close the most of the gap without its effect (≥ GC_MIN).

    Such a fit found better values of the baseline's own parameters than the
    recalibration did: the reference every effect is judged against was
    beatable without any effect (:func:`_diagnose` then recalibrates from
    there and says so). A fit that left its effect switched off counts with
    its own GC, which is then the baseline values' alone.
    """
    def alone(c: Candidate) -> float:
        return max(-math.inf if c.rebased_gap_closure is None else c.rebased_gap_closure,
                   c.gap_closure if c.switched_off else -math.inf)

    beat = [c for c in singles if alone(c) >= GC_MIN]
    if not beat:
        return None
    c = max(beat, key=alone)
    return {"by": c.effect, "gap_closure": c.gap_closure, "rebased_gap_closure": alone(c),
            "switched_off": c.switched_off,
            "baseline_params": {k: v for k, v in c.fit.params.items() if "." not in k}}


def _summary(selected: list[Candidate], alternatives: list[dict[str, Any]], gap: dict[str, Any],
             beaten: dict[str, Any] | None = None, recal: dict[str, Any] | None = None) -> str:
    """The verdict in one line (``recal``: :func:`recalibration`'s report, whose unaccounted values it names)."""
    beatable = "" if beaten is None else (
        (f"; {beaten['by']}'s fit left the effect switched off and still closed {beaten['gap_closure']:.2f} of the "
         if beaten["switched_off"] else
         f"; {beaten['by']}'s fit, with the effect taken out, still closes {beaten['rebased_gap_closure']:.2f} of the ")
        + "gap: the baseline's own parameters, refitted beside it, did; "
        + ("the baseline was recalibrated from there and every candidate judged against that"
           if beaten.get("rereferenced") else
           # the calibration logs prefer the reference, the held-out ones those values: say what that means
           "a descent of the baseline from there was no cheaper on the calibration logs, so part of the gap may "
           "lie in values the calibration and held-out logs see differently (drift, or a regime only one of them "
           "visits)"))
    if selected:
        out = " + ".join(c.effect for c in selected)
    elif any(a["dropped"] for a in alternatives):
        out = "no significant effect"
    elif not gap["above_noise"]:
        lo, hi = gap["ci90"]
        out = (f"no significant effect: the baseline is not significantly above the noise (E {gap['e']:.3g} "
               f"against a floor of {gap['e_floor']:.3g}; 90 % CI of the difference {lo:.2g} … {hi:.2g})")
    else:
        out = (f"no significant effect: no candidate explains what the baseline leaves (E {gap['e']:.3g}, "
               f"{gap['e'] / gap['e_floor']:.3g} × the noise floor)" if gap["e_floor"] > 0.0 else
               f"no significant effect: no candidate explains what the baseline leaves (E {gap['e']:.3g})")
    # without an effect in the verdict and none dropped, no alternative was weighed: the loop adds nothing
    for a in alternatives:
        if a["dropped"]:
            out += (f"; {a['instead_of']} closed the gap, but {a['explanation']} ({a['description']}) closes more "
                    f"and {a['instead_of']} adds nothing significant beside it; to tell: {a['separate_by']}")
        elif a["better"]:
            out += (f"; {a['explanation']} ({a['description']}) closes more than {a['instead_of']}, which still "
                    f"adds significantly beside it; to tell: {a['separate_by']}")
        elif a["confusable"]:
            out += (f"; or {a['explanation']} instead of {a['instead_of']} ({a['description']}): these logs cannot "
                    f"tell them apart; to tell: {a['separate_by']}")
        elif a["also"]:
            out += (f"; with {a['explanation']} beside {a['instead_of']} ({a['description']}), which adds "
                    f"significantly to it; together: "
                    + ", ".join(f"{k} = {v:.3g}" for k, v in a["beside_effect"]["params"].items()))
    out += beatable
    if recal is not None and recal["unaccounted"]:
        # "no significant effect" with a baseline standing in for something is not the same answer
        # as with one that is not
        label = {r["name"]: r["meaning"] or r["name"] for r in recal["params"]}
        out += ("; the recalibration moved " + ", ".join(label[n] for n in recal["unaccounted"])
                + f" past {FAR_FACTOR:g} × or the end of its range, which nothing in the verdict accounts for: "
                "the baseline is standing in for something (baseline.recalibration)")
    return out


def _far(p: Param, v: float, scaled: bool) -> tuple[bool, bool]:
    """Whether ``v`` sits on an end of ``p``'s range away from nominal, and whether it is *far* (a nominal
    scale, ``scaled``, moved past :data:`FAR_FACTOR` either way or onto an end)."""
    moved = abs(v - p.x0) > 1e-9 * max(1.0, abs(p.x0))
    # within 0.5 % of an end: a descent on a rippled cost stops short of the bound it presses on
    on_end = moved and (abs(v - p.lo) <= 5e-3 * max(1.0, abs(p.lo)) or abs(v - p.hi) <= 5e-3 * max(1.0, abs(p.hi)))
    beyond = p.x0 > 0.0 and not p.x0 / FAR_FACTOR <= v <= p.x0 * FAR_FACTOR
    return on_end, scaled and (beyond or on_end)


def recalibration(family: Family, base: Fit, model: Candidate | None = None) -> dict[str, Any]:
    """What the recalibration made of each baseline parameter, and which it moved further than a tolerance.

    A nominal value scaled by the family's ``nominal_scales`` to more than
    :data:`FAR_FACTOR` × or less than 1 / :data:`FAR_FACTOR` × its nominal,
    or onto an end of its range away from nominal, is *far*: no tolerance
    explains it, so the baseline is absorbing something (an effect the
    model lacks, or a nominal value that is wrong).

    Args:
        family: The family diagnosed (its ``baseline()`` ranges are the ones fitted in).
        base: The baseline every candidate was judged against.
        model: The last effect the verdict keeps (its fit refits the
            baseline's values beside the effect), or ``None``.

    Returns:
        ``params``: per baseline parameter its ``value``, ``nominal``,
        ``range``, ``sd``, ``at_bound`` (on an end of its range, away from
        nominal), ``far``, ``in_model`` (its value in ``model``'s fit, or
        ``None``) and ``in_model_far`` (that value is far by the same
        rule); ``far``: the far ones' names; ``unaccounted``: those
        ``model`` does not bring back within the factor; ``note``: a
        sentence on them (``None`` when none is far).
    """
    scaled = set(getattr(family, "nominal_scales", ()))
    meaning: dict[str, str] = getattr(family, "meaning", {})
    absorbs: dict[str, str] = getattr(family, "absorbs", {})
    rows: list[dict[str, Any]] = []
    far: list[str] = []
    for p in _specs(family, ()):
        v = base.params[p.name]
        on_end, is_far = _far(p, v, p.name in scaled)
        if is_far:
            far.append(p.name)
        m = model.fit.params.get(p.name) if model is not None else None
        rows.append({"name": p.name, "meaning": meaning.get(p.name, ""), "value": v, "nominal": p.x0,
                     "range": [p.lo, p.hi], "unit": p.unit, "sd": base.sd.get(p.name, math.nan), "at_bound": on_end,
                     "far": is_far, "in_model": m,
                     # the verdict's own fit can move a nominal value as far (a leak's fit, the dead volume
                     # it refits beside it): shown as such, not only where the baseline's was far
                     "in_model_far": m is not None and _far(p, m, p.name in scaled)[1]})
    note = None
    back: list[str] = []
    if far:
        by = {r["name"]: r for r in rows}
        what = "; ".join(
            f"{by[n]['meaning'] or n}: {by[n]['value']:.3g} (nominal {by[n]['nominal']:g}"
            + (f", on the end of its range {by[n]['range'][0]:g} … {by[n]['range'][1]:g}" if by[n]["at_bound"] else "")
            + ")" for n in far)
        note = (f"the recalibration moved {what}; that is more than a tolerance on a nominal value explains "
                f"(over {FAR_FACTOR:g} × or under 1/{FAR_FACTOR:g} ×), so the baseline is standing in for something")
        # brought back: the verdict's value is no longer far by the same rule (_far)
        back = [n for n in far if by[n]["in_model"] is not None and not by[n]["in_model_far"]]
        if model is not None and back:
            note += (f". With {model.effect} in the model, " + "; ".join(
                f"{by[n]['meaning'] or n} comes back to {by[n]['in_model']:.3g}" for n in back))
        if len(back) < len(far):
            hints = [absorbs[n] for n in far if n not in back and n in absorbs]
            note += (". What the verdict names does not account for it" if model is not None else
                     ". No effect in the verdict accounts for it")
            note += (f": it may be {'; or '.join(hints)}" if hints else "")
            note += ("; where the quantity was measured, narrowing its range (cwrr diagnose --bound NAME=LO:HI, "
                     "or the diagnosis page's ranges) keeps the baseline from absorbing it")
    return {"params": rows, "far": far, "note": note, "unaccounted": [n for n in far if n not in back]}


def _rank_key(c: Candidate) -> tuple[bool, bool, float]:
    """Significant first; then an effect whose own parameters sit inside their physical
    bounds before one pinned on a bound (pinned, it is mimicking a shape it cannot make);
    then by gap closure."""
    pinned = any(n.startswith(c.effect + ".") for n in c.fit.at_bound)
    return c.significant, not pinned, c.gap_closure


def recalibrate(family: Family, calib: list[Any], scales: dict[str, float] | None = None,
                stop: threading.Event | None = None) -> Fit:
    """The baseline fitted on prepared calibration logs: grid start, descent, and the grid again.

    The fit :func:`recalibrate_forms` ends with (see there).
    """
    return recalibrate_forms(family, calib, scales, stop)[1]


FORM_BEAM = 2
"""Form fits carried from one form group to the next (:func:`recalibrate_forms`)."""
FORM_APART = 0.05
"""Two form fits are two forms where some form parameter differs by more than this share of its range."""


def recalibrate_forms(family: Family, calib: list[Any], scales: dict[str, float] | None = None,
                      stop: threading.Event | None = None) -> tuple[Fit, Fit]:
    """The baseline fitted on prepared calibration logs with its form held, and with the form it may take.

    With the family's form parameters (``form_grids``) held at nominal; then,
    one group after the other, from that group's grid's best, with it free,
    kept only where that lowers some channel's calibration RMS error by more
    than the family's relevance. A group another group follows is descended
    from each level of its first parameter too (:func:`_form_descents`). The
    :data:`FORM_BEAM` cheapest fits of distinct forms so far are each carried
    to the next group, and the cheapest at the end is the one returned.

    Args:
        family: The rig family.
        calib: Prepared calibration logs (``family.prepare``).
        scales: Channel scales of the residuals (default: :func:`channel_scales` of ``calib``).
        stop: Once set, ends the fit at its next cost evaluation with :class:`Cancelled`.

    Returns:
        The baseline's fit (no effects) with every form group held nominal, and
        the one with the groups it kept (the same fit where it kept none).
    """
    scales = scales or channel_scales(family, calib)
    # a rough cost surface stalls the descent near its start: a family may name baseline
    # parameters to search on a grid first (the others at their nominal values)
    nominal = {s.name: s.x0 for s in family.baseline()}
    groups = form_groups(family)
    form = [p for g in groups for p in g]
    nominal_form = _recalibrated(family, calib, nominal, scales, stop, hold=[p.name for p in form])
    at_nominal = {p.name: nominal[p.name] for g in base_groups(family) for p in g}
    # (fit, the form parameters it holds at nominal)
    chains: list[tuple[Fit, list[str]]] = [(nominal_form, [p.name for p in form])]
    for group in groups:
        # The model's form (where a valve starts to open, how its regulator rests) is recalibrated
        # only where that lowers some channel's calibration RMS error by more than what matters on
        # the rig (the family's relevance, as for a candidate). A cheaper fit alone is no evidence
        # of the form: descents on this rippled cost end apart by more than small gains (from
        # neighbouring starts, one on our own tube rig ended at 1.4 × another's), and a small gain
        # bought the form's freedom for something else: on a rig whose friction differs per
        # direction a centre 5 % closed, at 0.98 × the cost, took friction per direction from 0.15
        # to 0.06. A share of the cost would not do either: an effect's own misfit is in both (on
        # a rig written apart from ours, bench/independent_rig.py, the valve's centre gave 0.13 ×
        # the cost without an effect, 0.8 × beside a heat exchange). Each group is judged against
        # the fit with the groups before it as they were kept, so each must earn its own freedom.
        # For the same ripple, the cheapest form of one group need not be the one the next group's
        # form completes: on a rig written apart from ours logged at 1 kHz, the valve's centre
        # descended to 0.63 closed at 0.985 × the cost of 0.75 closed, and from there no regulator
        # form gained what matters; from 0.75 the regulator's took the cost to 0.42 × (the
        # 200 Hz logs of the same rig had chosen 0.75 and both forms). So the cheapest fits of
        # distinct forms are each carried on (docs/diagnosis-record.md, "Two forms carried on").
        # Nor need the group's grid's best be the level the next group's form completes: at
        # 100 Hz every descent of the centre from there ended half closed, where no regulator form
        # paid; the grid's point with the centre shut, descended, ended 0.98 closed, and from there
        # the regulator's form took the cost to 0.17 ×. So a group another group follows is also
        # descended from its grid's cheapest point at each other level of its first parameter
        # (the family puts the form's switch first; "Each level of the valve's centre descended")
        raise_if_stopped(stop)
        names = [p.name for p in group]
        carried: list[tuple[Fit, list[str]]] = []
        for base, held in chains:
            free = [n for n in held if n not in names]
            kept = [d for d in _form_descents(family, calib, base, group, free, at_nominal, nominal, scales, stop,
                                              levels=group is not groups[-1])
                    if d.rss < base.rss and _relevant_gain(family, calib, base, d)]
            carried += [(d, free) for d in kept] or [(base, held)]
        chains = []
        for fit_, held in sorted(carried, key=lambda c: c[0].rss):
            if all(_forms_apart(fit_.params, other.params, form) for other, _ in chains):
                chains.append((fit_, held))
            if len(chains) == FORM_BEAM:
                break
    return nominal_form, chains[0][0]


def _form_descents(family: Family, calib: list[Any], base: Fit, group: list[Param], hold: list[str],
                   at_nominal: dict[str, float], nominal: dict[str, float], scales: dict[str, float],
                   stop: threading.Event | None, levels: bool = False) -> list[Fit]:
    """The fits with ``group`` free descended from its grid's best points (none where no grid point is cheaper),
    the form parameters in ``hold`` held at nominal.

    With ``levels`` (a group another group's form follows), also from the
    cheapest grid point at each other value of the group's first parameter,
    where that is cheaper than ``base``: the form of a later group can make
    another level the right one (see :func:`recalibrate_forms`).

    The form's grid runs from the fit so far (the gains and friction it fitted): from the
    nominal values, a PRV regulator of another form was gridded with the pressure gains at
    1.0 for a true 1.013, and the grid's best was the wrong form. It runs again with the
    gridded parameters (base_grids) back at their nominal values, and each best form is
    descended from both: the flows and volumes the fit so far bent to stand in for the form
    sit in a valley their grid does not leave. Coordinate grids do not always leave it: on
    our own rig with a PRV of another form the fit ends at 1.8 × the calibration cost of a
    descent from the truth (half way to the rig's dead zone), 0.45 × the nominal form's.
    """
    names = [p.name for p in group]
    starts: dict[tuple[float, ...], dict[str, float]] = {}
    start, cost = _grid_best(family, calib, (), base.params, group, 3, scales)
    if cost < base.rss:  # some form on the grid fits better
        starts[tuple(start[n] for n in names)] = start
    again, _ = _grid_best(family, calib, (), base.params | at_nominal, group, 3, scales)
    if any(again[n] != nominal[n] for n in names):
        starts.setdefault(tuple(again[n] for n in names), again)
    if levels:
        lead = group[0]
        per_level: dict[float, tuple[dict[str, float], float]] = {}
        axes = [_axis(p, p.lo, p.hi, 3) for p in group]
        for v, c in _grid_costs(family, calib, [family.measured(p) for p in calib], (), base.params, group, axes,
                                scales):
            if c < base.rss and c < per_level.get(v[lead.name], (v, math.inf))[1]:
                per_level[v[lead.name]] = (v, c)
        for v, _ in per_level.values():
            if all(_forms_apart(v, s, [lead]) for s in starts.values()):
                starts.setdefault(tuple(v[n] for n in names), v)
    # each from there and with the gridded parameters at nominal
    tried = {tuple(sorted(s.items())): s for st in starts.values() for s in (st, st | at_nominal)}
    return sorted(_each(lambda s: _recalibrated(family, calib, s, scales, stop, hold=hold), list(tried.values())),
                  key=lambda f: f.rss)


def _forms_apart(a: dict[str, float], b: dict[str, float], form: list[Param]) -> bool:
    """Whether fits ``a`` and ``b`` hold forms apart: some parameter of ``form`` differs by more than
    :data:`FORM_APART` of its range (of its logarithm's, for one fitted in log space)."""
    for p in form:
        x, y = a[p.name], b[p.name]
        if p.log:
            d = abs(math.log(x) - math.log(y)) / (math.log(p.hi) - math.log(p.lo))
        else:
            d = abs(x - y) / (p.hi - p.lo)
        if d > FORM_APART:
            return True
    return False


def _relevant_gain(family: Family, preps: list[Any], a: Fit, b: Fit) -> bool:
    """Whether ``b`` lowers some channel's RMS error on ``preps`` below ``a``'s by more than the family's relevance."""
    gain = rms_gain(family, score(family, preps, a, 1), score(family, preps, b, 1))
    return any(gain[c] > family.relevance.get(c, 0.0) for c in family.channels)


def rms_gain(family: Family, a: Scores, b: Scores) -> dict[str, float]:
    """Per channel, how far ``b``'s RMS error lies below ``a``'s (pooled over the units)."""
    rms_a, rms_b = (np.sqrt(x.sse.sum(0) / np.maximum(x.cnt.sum(0), 1)) for x in (a, b))
    return {c: float(ra - rb) for c, ra, rb in zip(family.channels, rms_a, rms_b, strict=True)}


def _recalibrated(family: Family, calib: list[Any], start: dict[str, float], scales: dict[str, float],
                  stop: threading.Event | None, hold: Iterable[str] = ()) -> Fit:
    """:func:`recalibrate` from ``start`` (``hold`` kept at its values): grid start, descent, the grid again."""
    groups = base_groups(family)
    levels = [*getattr(family, "base_grid_levels", ()), *[3] * len(groups)][:len(groups)]
    meas = [family.measured(p) for p in calib]

    def gridded(x: dict[str, float], cost: float) -> tuple[dict[str, float], float]:
        # each group's grid from the point before it, kept only where it is cheaper: a start
        # fitted already (the form's, from a recalibration) is often better than every coarse
        # point, and the friction's cost is sharp (on our own rig with a PRV of another form, the
        # friction grid's best had replaced a fitted friction, and the descent stalled at 2.3 × its
        # torque error)
        for group, lv in zip(groups, levels, strict=True):
            cand, c = _grid_best(family, calib, (), x, group, 3, scales, levels=lv)
            if c < cost:
                x, cost = cand, c
        return x, cost

    r0 = _residuals(family, calib, meas, start, (), scales)
    st, _ = gridded(start, float(r0 @ r0))
    base = fit(family, calib, (), scales=scales, starts=[st], stop=stop, hold=hold)
    if groups:
        # That grid held the other parameters (the sensors' gains, the friction levels) at
        # nominal. On two effect-free rigs logged once (docs/diagnosis-record.md, "The recalibration's
        # second grid") it chose the wrong basin, the PRV capacity at 1.0 and 1.25 × nominal for
        # a true 0.81 and 0.88 ×, and the descent, in a rippled valley where capacity and dead
        # volume trade, stayed there at 1.4–1.6 × the calibration cost of a descent from the
        # truth. The same grid with the fit's own values of the others, descended from if lower,
        # ended at 1.08 and 0.95 ×.
        again, again_cost = gridded(base.params, base.rss)
        if again_cost < base.rss:
            raise_if_stopped(stop)
            base = fit(family, calib, (), scales=scales, starts=[again], stop=stop, hold=hold)
    return base


def base_groups(family: Family) -> list[list[Param]]:
    """The family's groups of baseline parameters gridded before the recalibration's descent, one after the other.

    ``base_grids`` if the family has it, else its single ``base_grid``.
    """
    groups = getattr(family, "base_grids", None)
    if groups is None:
        groups = (getattr(family, "base_grid", ()),)
    return [list(g) for g in groups if g]


def diagnose(family: Family, calib_exps: list[Any], held_exps: list[Any],
             candidates: Sequence[str] | None = None, protocol: dict[str, list[str]] | None = None,
             blocks: int | None = None, stop: threading.Event | None = None,
             with_traces: bool = False, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The full diagnosis; returns the report (JSON-able).

    BLAS runs on one thread meanwhile, process-wide (the server runs one
    diagnosis at a time). The diagnosis's matrices are tall and thin
    (least-squares Jacobians of ≈ 10⁵ rows by ≤ 10 columns), and OpenBLAS's
    own threads, spinning between its calls, took the cores the replays run
    on: on a two-core machine they had used half of the diagnosis's CPU
    time. One thread also makes the report the same on any core count, since
    a threaded BLAS sums in an order that depends on it.

    Args:
        family: The rig family.
        calib_exps: Experiments to fit on.
        held_exps: Experiments withheld from every fit, scored only.
        candidates: Effects to try (default: the family's).
        protocol: Effect → experiments that make it visible (for the
            separating-experiment advice).
        blocks: Time blocks per held-out experiment for the bootstrap
            (default 1 when ≥ 4 experiments are held out, else 8).
        stop: Once set, the diagnosis ends at its next cost evaluation with
            :class:`Cancelled` (a server shutting down must not leave it running).
        with_traces: Add ``traces`` (:func:`traces` of the held-out logs under the
            baseline and the verdict's model; ≈ 10⁵ numbers, so only when asked).
        progress: Told in words what the diagnosis is doing as each stage
            starts and each candidate's fit ends (from the fits' threads too), e.g.
            ``"candidate 4 of 9 fitted (heat_transfer)"``; a minute of work on
            ten minutes of logs says where it is.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _diagnose(family, calib_exps, held_exps, candidates, protocol, blocks, stop, with_traces,
                         progress or (lambda _msg: None))


def _diagnose(family: Family, calib_exps: list[Any], held_exps: list[Any],
              candidates: Sequence[str] | None, protocol: dict[str, list[str]] | None,
              blocks: int | None, stop: threading.Event | None,
              with_traces: bool, progress: Callable[[str], None]) -> dict[str, Any]:
    """:func:`diagnose` with BLAS already limited (its only caller gives every argument)."""
    if not calib_exps or not held_exps:
        raise ValueError("need at least one calibration and one held-out experiment")
    cands = checked_candidates(family.name, family.candidates, candidates)
    calib = [family.prepare(e) for e in calib_exps]
    held = [family.prepare(e) for e in held_exps]
    blocks = blocks or (1 if len(held) >= 4 else 8)
    held_meas = [family.measured(p) for p in held]
    # a channel no held-out sample scores (a torque whose handle rests on an end stop throughout)
    # has no error to weigh: it leaves the diagnosis, fit and score alike, and the report says so
    unscored = [c for c in family.channels if not any(np.isfinite(m[c]).any() for m in held_meas)]
    if len(unscored) == len(family.channels):
        raise ValueError("no held-out sample of any channel can be scored")
    if unscored:
        family = copy.copy(family)
        family.channels = tuple(c for c in family.channels if c not in unscored)
    scales = channel_scales(family, calib)
    spread = channel_spread(family, held_meas)
    floor = noise_floor(family, held, held_meas)
    norm = _Norm(spread, floor)

    progress(f"recalibrating the baseline on {len(calib)} log{'s' * (len(calib) != 1)}")
    base, formed = recalibrate_forms(family, calib, scales, stop)
    base_sc = score(family, held, base, blocks)
    counted = threading.Lock()

    def singles_from(refs: list[tuple[Fit, Scores]]) -> list[list[Candidate]]:
        # every candidate beside every reference, all at once (see _each)
        jobs = [(r, r_sc, c) for r, r_sc in refs for c in cands]
        fitted = [0]
        both = " beside each of the two baselines" if len(refs) > 1 else ""
        progress(f"fitting {len(cands)} candidate{'s' * (len(cands) != 1)}{both}")

        def one(job: tuple[Fit, Scores, str]) -> Candidate:
            c = _evaluate(family, calib, held, job[0], job[1], (job[2],), norm, blocks, scales, stop)
            with counted:
                fitted[0] += 1
                progress(f"candidate {fitted[0]} of {len(jobs)} fitted ({job[2]})")
            return c

        done = _each(one, jobs)
        return [done[i * len(cands):(i + 1) * len(cands)] for i in range(len(refs))]

    form = None
    if formed is base:
        singles, = singles_from([(base, base_sc)])
    else:
        # The model's form competes with the effects: the baseline keeps the form the
        # recalibration found only where the model the diagnosis would end with (the best
        # significant effect, or none) predicts the held-out logs better with it than without.
        # A form can stand in for an effect: on our own rig with 2 m of tube, a PRV regulator
        # without hysteresis beside 4 × the dead volume closed 0.67 of the held-out gap the tube
        # closes 0.69 of, and judged against that baseline the tube closed 0.17 (the true model
        # itself 0.14). And an effect can hide a form: on a rig written apart from ours
        # (bench/independent_rig.py) with a heat exchange, the form alone closed 0.08 of the gap,
        # the heat exchange alone 0.22, and together 0.8
        formed_sc = score(family, held, formed, blocks)
        singles, f_singles = singles_from([(base, base_sc), (formed, formed_sc)])

        def ending(ref_sc: Scores, sings: list[Candidate]) -> tuple[Scores, str | None]:
            best = max((c for c in sings if c.significant), key=lambda c: c.gap_closure, default=None)
            return (best.scores, best.effect) if best is not None else (ref_sc, None)

        (sc_without, eff_without), (sc_with, eff_with) = ending(base_sc, singles), ending(formed_sc, f_singles)
        e_without, e_with = _e(sc_without, norm)[0], _e(sc_with, norm)[0]
        # what the form closes of the other ending's gap, with its 90 % CI, is reported, not a rule:
        # required above 0, it kept the nominal form where it had won by a hair on our own rig (a
        # tube's place, E 0.00854 against 0.00873, which then fell under the relevance anyway), and
        # on a rig written apart from ours (bench/independent_rig.py) it turned the larger heat
        # exchange's verdict into vane_leakage (the heat exchange ranked second, GC 0.11 for 0.54)
        ci = bootstrap_gc(sc_without, sc_with, norm)
        form = {"params": {n: formed.params[n] for n in held_form(family, base.params)
                           if formed.params[n] != base.params[n]},
                "gap_closure": gap_closure(base_sc, formed_sc, norm),
                "e_after_with": e_with, "effect_with": eff_with,
                "e_after_without": e_without, "effect_without": eff_without,
                "closes_of_the_rest_ci90": list(ci), "kept": e_with < e_without}
        if form["kept"]:
            base, base_sc, singles = formed, formed_sc, f_singles
    beaten = _baseline_beaten(singles)
    if beaten is not None:
        # A candidate fit's values closed the gap with its effect taken out (or left off): the
        # baseline's own parameters, refitted beside it, did. Every effect would be judged against
        # a reference that is not the baseline's best, so the baseline descends again from those
        # values and, if that is cheaper, the candidates are judged against it instead (once: the
        # report says so).
        again = fit(family, calib, (), scales=scales, starts=[base.params | beaten["baseline_params"]], stop=stop,
                    hold=held_form(family, base.params))
        beaten |= {"calibration_cost_before": base.rss, "calibration_cost_after": again.rss,
                   "rereferenced": again.rss < base.rss}
        if again.rss < base.rss:
            progress("the baseline refitted from a candidate's values was better: judging the candidates again")
            base = again
            base_sc = score(family, held, base, blocks)
            singles, = singles_from([(base, base_sc)])
    singles.sort(key=_rank_key, reverse=True)
    e_base, nr_base = _e(base_sc, norm)
    e_floor = float((floor / spread).mean())
    # "no significant effect" means one of two things, and the report says which: nothing above the
    # noise to explain, or a gap no candidate closes
    g_lo, g_hi = bootstrap_gap(base_sc, norm)
    gap = {"e": e_base, "e_floor": e_floor, "e_minus_floor": e_base - e_floor, "ci90": [g_lo, g_hi],
           "above_noise": g_lo > 0.0}

    selected: list[Candidate] = []
    ref, ref_sc = base, base_sc
    pool = list(singles)
    while pool and len(selected) < MAX_EFFECTS:
        if selected:
            prev = tuple(s.effect for s in selected)
            progress(f"fitting {len(pool)} candidate{'s' * (len(pool) != 1)} beside {' + '.join(prev)}")

            def beside(c: Candidate, r: Fit = ref, r_sc: Scores = ref_sc, pr: tuple[str, ...] = prev) -> Candidate:
                return _evaluate(family, calib, held, r, r_sc, (*pr, c.effect), norm, blocks, scales, stop)

            pool = _each(beside, pool)
            pool.sort(key=_rank_key, reverse=True)
        best = pool[0]
        if not best.significant:
            break
        selected.append(best)
        ref, ref_sc = best.fit, best.scores
        pool = pool[1:]

    confusable: list[str] = []
    separate: list[dict[str, Any]] = []
    if selected:
        win = next(c for c in singles if c.effect == selected[0].effect)
        for c in singles:
            if c is win or c.effect in (s.effect for s in selected):
                continue
            # confusable: it explains the gap too, and the held-out data cannot say which does more
            lo, hi, plausible = _weigh(base_sc, win, c, norm)
            if plausible and lo <= 0.0 <= hi:
                confusable.append(c.effect)
                if protocol:
                    only = [x for x in protocol.get(win.effect, []) if x not in protocol.get(c.effect, [])]
                    separate.append({"effects": [win.effect, c.effect], "experiments": only or
                                     protocol.get(win.effect, [])})
    if selected:
        progress(f"weighing the alternatives to {' + '.join(c.effect for c in selected)}")
    alternatives, verdict_model = _alternatives(family, calib, held, base, base_sc, selected, singles, norm, blocks,
                                                scales, stop)
    dropped: dict[str, list[str]] = {}  # effect → the alternatives that took its place
    for a in alternatives:
        if a["dropped"]:
            dropped.setdefault(a["instead_of"], []).append(a["explanation"])
    kept = [c for c in selected if c.effect not in dropped]
    model = [c.effect for c in kept]
    if len(selected) == 1 and selected[0].effect in verdict_model:
        # how far the gap shrinks with the model the verdict describes (both fitted together, or the
        # alternative in the effect's place); families name alternatives for effects that come alone,
        # and those fits start from the effect's single fit, not from a greedy combination's
        names, ref_sc = verdict_model[selected[0].effect]
        model = list(names)
    elif dropped:
        # what is left is scored as the last effect kept (a later round's fit includes the dropped effect)
        ref_sc = kept[-1].scores if kept else base_sc
    selected = kept
    progress("writing the report")
    e_final, nr_final = _e(ref_sc, norm)
    recal = recalibration(family, base, selected[-1] if selected else None)
    chans = list(family.channels)
    held_names = [getattr(e, "name", str(i)) for i, e in enumerate(held_exps)]
    extra: dict[str, Any] = {}
    if with_traces:
        # the held-out logs as the baseline and the last effect the verdict kept predict them
        fits = {"baseline": base} | ({"after": selected[-1].fit} if selected else {})
        alike = {c.effect: c.fit for c in singles if c.effect in confusable}
        extra["traces"] = {"model": list(selected[-1].fit.effects) if selected else [],
                           "confusable": list(alike),
                           "logs": traces(family, held, fits, held_names, confusable=alike)}
    return extra | {
        "family": family.name,
        "experiments": {"calibration": [getattr(e, "name", "?") for e in calib_exps],
                        "held_out": [getattr(e, "name", "?") for e in held_exps],
                        # logs sampled unevenly (the replays put them on a uniform grid, see
                        # logs.on_uniform_grid): said, not hidden
                        "irregular_sampling": {getattr(e, "name", "?"): info for e in (*calib_exps, *held_exps)
                                               if hasattr(e, "t") and len(e.t) > 2
                                               and (info := sampling_irregularity(np.asarray(e.t))) is not None},
                        # never changes: a quantity that did not, or a sensor reading nothing (bends the fit)
                        "flat_channels": {getattr(e, "name", "?"): flat for e in (*calib_exps, *held_exps)
                                          if isinstance(e, Experiment) and (flat := flat_channels(e))},
                        # channels no held-out sample could score: left out of every fit and E
                        "unscored_channels": unscored},
        "baseline": {"nrmse": dict(zip(chans, map(float, nr_base), strict=True)), "e": e_base,
                     "identifiability": base.identifiability(), "gap": gap,
                     # what the recalibration made of each nominal value, and which it moved past a tolerance
                     "recalibration": recal,
                     # the form the recalibration found beside the nominal one, and whether it was kept
                     "form": form},
        "noise_floor": {"nrmse": dict(zip(chans, map(float, floor / spread), strict=True)), "e": e_floor},
        "where": where(family, held, base, floor, held_names),
        # an effect taken out of the verdict for an alternative keeps its single fit's significance
        # against the baseline here, and says what took its place
        "ranking": [c.as_dict() | ({"dropped_for": dropped[c.effect]} if c.effect in dropped else {})
                    for c in singles],
        "combination": [c.as_dict() for c in selected],
        "alternatives": alternatives,
        "verdict": {"effects": [c.effect for c in selected], "confusable_with": confusable,
                    "separating_experiments": separate,
                    "alternatives": [a["explanation"] for a in alternatives
                                     if a["confusable"] or a["better"] or a["also"]],
                    "baseline_beaten": beaten,
                    "summary": _summary(selected, alternatives, gap, beaten, recal)},
        "how_far": {"before": dict(zip(chans, map(float, nr_base), strict=True)),
                    "after": dict(zip(chans, map(float, nr_final), strict=True)),
                    "model": model, "e_before": e_base, "e_after": e_final, "e_floor": e_floor,
                    "unexplained_share": (e_final - e_floor) / (e_base - e_floor) if e_base - e_floor > 1e-12
                    else 0.0},
    }
