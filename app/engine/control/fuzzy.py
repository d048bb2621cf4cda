"""Fuzzy gain scheduler of the Cascade Fuzzy Adaptive PID (thesis 3.7).

Two inputs (pressure error e_p [bar] and its rate ė_p [bar/s]), seven
triangular membership functions each (NS, NM, N, Z, P, PM, PB, most negative
first — SPEC §4), three outputs ([K_p]^f, [K_i]^f, [K_d]^f on [0, 1]) with
five triangular MFs each (Z, PVL, P, PM, PB), the 49-rule tables 3.8–3.10,
Mamdani min inference with max aggregation, and either

* ``"wavg"`` — Eq 3.27, the weighted average of the output MF peaks weighted
  by their aggregated firing strength (what the thesis uses, and what runs in
  the loop: ~0.3 µs per evaluation), or
* ``"centroid"`` — the exact centre of gravity of the clipped, aggregated
  output MFs (the textbook Mamdani defuzzifier; scikit-fuzzy's
  ``ControlSystem`` computes the same number, which the tests check).

The thesis shows the MF universes only in figures (3.42–3.43). Defaults,
chosen from the pressure-error scale of the rig: e_p ∈ [−1, 1] bar and
ė_p ∈ [−10, 10] bar/s, MFs evenly spaced with shoulders at the ends (inputs
beyond the universe saturate), output MFs peaking at 0, ¼, ½, ¾, 1. All of it
is configuration (:class:`FuzzyConfig`).

Hand-written rather than scikit-fuzzy at run time: skfuzzy's
``ControlSystemSimulation`` takes about a millisecond per evaluation (it
re-samples universes in Python), far too slow for a 200 Hz loop that also
runs 1000× faster than real time in batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from app.engine.params import ParameterError, check_range

INPUT_LABELS: tuple[str, ...] = ("NS", "NM", "N", "Z", "P", "PM", "PB")
OUTPUT_LABELS: tuple[str, ...] = ("Z", "PVL", "P", "PM", "PB")
GAINS: tuple[str, ...] = ("kp", "ki", "kd")

# Tables 3.8–3.10 (SPEC §4): rows ė_p NS..PB, columns e_p NS..PB.
RULE_TEXT: dict[str, str] = {
    "kp": """PB PB PM P PVL PVL Z | PB P P PVL PVL Z Z | P P PVL PVL PVL Z Z |
             PVL PVL PVL PVL PVL P PM | PVL PVL Z PVL P PM PB | Z Z Z PVL PM PB PB |
             Z Z Z PVL PB PB PB""",
    "ki": """P P PM P PVL PVL Z | PVL PVL P PVL PVL Z Z | P P Z Z Z Z Z |
             PVL PVL Z Z Z P PM | PVL PVL Z Z Z PM PB | Z Z Z PVL PM PVL PVL |
             Z Z Z PVL PB PVL PVL""",
    "kd": """PVL PVL PB PVL Z Z Z | Z Z PVL Z Z Z Z | PVL PVL Z Z Z Z Z |
             Z Z Z Z Z PVL PB | Z Z Z Z Z PB PB | Z Z Z Z PB Z Z |
             Z Z Z Z PB Z Z""",
}


def parse_rules(text: str) -> np.ndarray:
    """A 7×7 rule table in the SPEC's text form → output-MF indices.

    Raises:
        ParameterError: On a wrong shape or an unknown label.
    """
    rows = [r.split() for r in text.split("|")]
    if len(rows) != 7 or any(len(r) != 7 for r in rows):
        raise ParameterError("a rule table needs 7 rows of 7 labels")
    out = np.zeros((7, 7), dtype=np.int64)
    for i, r in enumerate(rows):
        for j, lab in enumerate(r):
            if lab not in OUTPUT_LABELS:
                raise ParameterError(f"rule label {lab!r} must be one of {', '.join(OUTPUT_LABELS)}")
            out[i, j] = OUTPUT_LABELS.index(lab)
    return out


RULES: np.ndarray = np.stack([parse_rules(RULE_TEXT[g]) for g in GAINS])
"""(3, 7, 7) output-MF index per gain, rule row (ė_p) and column (e_p)."""


def even_triangles(lo: float, hi: float, n: int) -> np.ndarray:
    """``n`` evenly spaced triangles covering [lo, hi], shoulders at the ends.

    Returns:
        (n, 3) array of (a, b, c) feet and peak, a ≤ b ≤ c.
    """
    c = np.linspace(lo, hi, n)
    tri = np.empty((n, 3))
    tri[:, 1] = c
    tri[:, 0] = np.concatenate([[c[0]], c[:-1]])
    tri[:, 2] = np.concatenate([c[1:], [c[-1]]])
    return tri


@dataclass(frozen=True)
class FuzzyConfig:
    """Membership functions and defuzzifier of the gain scheduler.

    Attributes:
        e_range: Half-width of the e_p universe [bar].
        de_range: Half-width of the ė_p universe [bar/s].
        defuzz: ``"wavg"`` (Eq 3.27) or ``"centroid"``.
        e_mfs: Optional explicit (7, 3) triangles on e_p [bar] (overrides
            ``e_range``).
        de_mfs: Optional explicit (7, 3) triangles on ė_p [bar/s].
        out_mfs: (5, 3) output triangles on [0, 1].
    """

    e_range: float = 1.0
    de_range: float = 10.0
    defuzz: str = "wavg"
    e_mfs: np.ndarray | None = None
    de_mfs: np.ndarray | None = None
    out_mfs: np.ndarray = field(default_factory=lambda: even_triangles(0.0, 1.0, 5))

    def __post_init__(self) -> None:
        check_range("e_range", self.e_range, 0.0, 10.0, lo_open=True, unit="bar")
        check_range("de_range", self.de_range, 0.0, 1000.0, lo_open=True, unit="bar/s")
        if self.defuzz not in ("wavg", "centroid"):
            raise ParameterError(f"defuzz = {self.defuzz!r} must be 'wavg' (Eq 3.27) or 'centroid'")
        for name, arr, n in (("e_mfs", self.e_mfs, 7), ("de_mfs", self.de_mfs, 7), ("out_mfs", self.out_mfs, 5)):
            if arr is None:
                continue
            a = np.asarray(arr, dtype=float)
            if a.shape != (n, 3):
                raise ParameterError(f"{name} must be a ({n}, 3) array of triangles, got shape {a.shape}")
            if np.any(np.diff(a, axis=1) < 0):
                raise ParameterError(f"{name}: each triangle needs a ≤ b ≤ c")
            if np.any(np.diff(a[:, 1]) <= 0):
                raise ParameterError(f"{name}: peaks must be strictly increasing")
        o = np.asarray(self.out_mfs)
        if o.min() < 0.0 or o.max() > 1.0:
            raise ParameterError("out_mfs must lie on [0, 1]")

    def input_mfs(self) -> tuple[np.ndarray, np.ndarray]:
        """The (7, 3) triangles on e_p [bar] and ė_p [bar/s]."""
        e = even_triangles(-self.e_range, self.e_range, 7) if self.e_mfs is None else np.asarray(self.e_mfs, float)
        de = (even_triangles(-self.de_range, self.de_range, 7) if self.de_mfs is None
              else np.asarray(self.de_mfs, float))
        return e, de

    def pack(self) -> np.ndarray:
        """Everything the compiled evaluator needs, in one float array.

        Layout: e MFs (21), ė MFs (21), output MFs (15), rules (147), method (1).
        """
        e, de = self.input_mfs()
        return np.concatenate([e.ravel(), de.ravel(), np.asarray(self.out_mfs, float).ravel(),
                               RULES.ravel().astype(float), [0.0 if self.defuzz == "wavg" else 1.0]])


FZ_E, FZ_DE, FZ_OUT, FZ_RULES, FZ_METHOD = 0, 21, 42, 57, 204
FZ_SIZE = 205


@njit(cache=True, inline="always", error_model="numpy")
def _tri(x: float, a: float, b: float, c: float) -> float:
    # same conventions as skfuzzy.trimf: exactly 1 at the peak, shoulders allowed
    if x == b:
        return 1.0
    if a < x < b:
        return (x - a) / (b - a)
    if b < x < c:
        return (c - x) / (c - b)
    return 0.0


@njit(cache=True, error_model="numpy")
def fuzzify(x: float, fz: np.ndarray, off: int, mu: np.ndarray) -> None:
    """Membership of ``x`` in the 7 input MFs starting at ``fz[off]``; ``x``
    is clipped to the universe first (outer MFs saturate)."""
    lo = fz[off + 1]
    hi = fz[off + 6 * 3 + 1]
    x = min(max(x, lo), hi)
    for k in range(7):
        mu[k] = _tri(x, fz[off + 3 * k], fz[off + 3 * k + 1], fz[off + 3 * k + 2])


@njit(cache=True, inline="always", error_model="numpy")
def _sort_inplace(a: np.ndarray, n: int) -> None:
    """Insertion sort of ``a[:n]`` (n ≤ 25: no allocation, unlike ``np.sort``)."""
    for i in range(1, n):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v


NWS_CENTROID = 25 + 16 + 5 + 5
"""Scratch floats :func:`_centroid` uses (corners, sub-pieces, two line ends)."""


@njit(cache=True, error_model="numpy")
def _centroid(act: np.ndarray, fz: np.ndarray, ws: np.ndarray) -> float:
    """Exact centre of gravity of max_k min(act_k, MF_k(y)) on the output axis.

    Between consecutive MF corners and cut crossings every clipped MF is a
    line, so the aggregate is the upper envelope of at most five lines there;
    adding the lines' pairwise crossings makes it linear piece by piece, and
    each piece's area and moment are integrated exactly.
    """
    pts = ws[0:25]
    n = 0
    for k in range(5):
        if act[k] <= 0.0:
            continue
        a = fz[FZ_OUT + 3 * k]
        b = fz[FZ_OUT + 3 * k + 1]
        c = fz[FZ_OUT + 3 * k + 2]
        pts[n] = a
        pts[n + 1] = b
        pts[n + 2] = c
        pts[n + 3] = a + act[k] * (b - a)
        pts[n + 4] = c - act[k] * (c - b)
        n += 5
    if n == 0:
        return 0.0
    _sort_inplace(pts, n)
    xs = pts
    sub = ws[25:41]
    v1 = ws[41:46]
    v2 = ws[46:51]
    num = 0.0
    den = 0.0
    for i in range(n - 1):
        x1 = xs[i]
        x2 = xs[i + 1]
        if x2 <= x1:
            continue
        # each clipped MF is linear on [x1, x2]: its values at the ends (an
        # MF that is zero at both ends of a corner-free interval is zero inside)
        for k in range(5):
            if act[k] > 0.0:
                a = fz[FZ_OUT + 3 * k]
                b = fz[FZ_OUT + 3 * k + 1]
                c = fz[FZ_OUT + 3 * k + 2]
                xm = 0.5 * (x1 + x2)
                vm = min(act[k], _tri(xm, a, b, c))
                # evaluate through the midpoint so a shoulder's jump at a
                # corner does not leak into the neighbouring interval
                s = 0.0
                if a < xm < b:
                    s = 1.0 / (b - a) if act[k] > (xm - a) / (b - a) else 0.0
                elif b < xm < c:
                    s = -1.0 / (c - b) if act[k] > (c - xm) / (c - b) else 0.0
                v1[k] = vm + s * (x1 - xm)
                v2[k] = vm + s * (x2 - xm)
            else:
                v1[k] = 0.0
                v2[k] = 0.0
        m = 0
        sub[m] = x1
        m += 1
        for k in range(5):
            for q in range(k + 1, 5):
                d1 = v1[k] - v1[q]
                d2 = v2[k] - v2[q]
                if d1 * d2 < 0.0:
                    xc = x1 + (x2 - x1) * d1 / (d1 - d2)
                    if x1 < xc < x2 and m < 15:
                        sub[m] = xc
                        m += 1
        sub[m] = x2
        m += 1
        _sort_inplace(sub, m)
        ss = sub
        for j in range(m - 1):
            u1 = ss[j]
            u2 = ss[j + 1]
            w = u2 - u1
            if w <= 0.0:
                continue
            # envelope value at the piece ends, from the lines
            y1 = 0.0
            y2 = 0.0
            for k in range(5):
                f1 = v1[k] + (v2[k] - v1[k]) * (u1 - x1) / (x2 - x1)
                f2 = v1[k] + (v2[k] - v1[k]) * (u2 - x1) / (x2 - x1)
                t1 = 0.5 * (f1 + f2)
                # the line on top over this piece is the one highest at its middle
                if k == 0 or t1 > 0.5 * (y1 + y2):
                    y1 = f1
                    y2 = f2
            if y1 < 0.0:
                y1 = 0.0
            if y2 < 0.0:
                y2 = 0.0
            area = 0.5 * w * (y1 + y2)
            if area > 0.0:
                num += w * (y1 * (2.0 * u1 + u2) + y2 * (u1 + 2.0 * u2)) / 6.0
                den += area
    return num / den if den > 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def fuzzy_gains(e: float, de: float, fz: np.ndarray, out: np.ndarray) -> None:
    """Scheduled gains [K_p]^f, [K_i]^f, [K_d]^f ∈ [0, 1] (thesis Fig 3.41).

    Args:
        e: Pressure error e_p [bar].
        de: Its rate ė_p [bar/s].
        fz: Packed configuration (:meth:`FuzzyConfig.pack`).
        out: Three outputs, written.
    """
    # one scratch block per call: the per-array allocations cost more than the inference
    ws = np.empty(7 + 7 + 5 + NWS_CENTROID)
    mu_e = ws[0:7]
    mu_d = ws[7:14]
    act = ws[14:19]
    cws = ws[19:]
    fuzzify(e, fz, FZ_E, mu_e)
    fuzzify(de, fz, FZ_DE, mu_d)
    centroid = fz[FZ_METHOD] > 0.5
    for g in range(3):
        for k in range(5):
            act[k] = 0.0
        for r in range(7):
            if mu_d[r] <= 0.0:
                continue
            for c in range(7):
                w = min(mu_d[r], mu_e[c])
                k = int(fz[FZ_RULES + 49 * g + 7 * r + c])
                if w > act[k]:
                    act[k] = w
        if centroid:
            out[g] = _centroid(act, fz, cws)
        else:
            num = 0.0
            den = 0.0
            for k in range(5):
                num += fz[FZ_OUT + 3 * k + 1] * act[k]
                den += act[k]
            out[g] = num / den if den > 0.0 else 0.0


class FuzzyScheduler:
    """Python face of the compiled scheduler (dashboard, tests, benchmarks).

    Args:
        config: Membership functions and defuzzifier.
    """

    def __init__(self, config: FuzzyConfig | None = None) -> None:
        self.config = config or FuzzyConfig()
        self.packed = self.config.pack()
        self._out = np.zeros(3)

    def __call__(self, e: float, de: float) -> tuple[float, float, float]:
        """([K_p]^f, [K_i]^f, [K_d]^f) for error ``e`` [bar] and rate ``de`` [bar/s]."""
        fuzzy_gains(float(e), float(de), self.packed, self._out)
        return float(self._out[0]), float(self._out[1]), float(self._out[2])
