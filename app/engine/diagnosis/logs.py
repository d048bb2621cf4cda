"""Experiment logs for the gap diagnosis: the station's fixed format, its checks, and adapters.

The station's format (issue 6) is a pair ``NAME.csv`` + ``NAME.json``. The
CSV header is exactly :data:`~app.engine.sim.LOG_COLUMNS`; the JSON holds at
least :data:`REQUIRED_META`. :func:`read_log` refuses a malformed log with a
:class:`LogFormatError` that names the problem (missing column, a NaN and
where, time going backwards, a channel whose magnitude says it was written
in the wrong unit).

Data from elsewhere enters through adapters that build the same
:class:`Experiment` with the channels they have: :func:`read_chamber_leak`
(closed-chamber pressure decays, ``refdata/chamber_leak``) and
:func:`read_emps` (the EMPS electro-mechanical drive, ``refdata/emps``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.sim import LOG_COLUMNS

REQUIRED_META: tuple[str, ...] = ("rig", "sample_rate_hz", "p_atm_bar", "working_pressure_bar", "experiment",
                                  "human")
INPUTS: tuple[str, ...] = ("z_a", "z_b", "u_a", "u_b")
MEASURED: tuple[str, ...] = ("p_a", "p_b", "p_s", "theta", "omega", "torque")

# plausible magnitudes in the log's units; a channel far outside was written in another unit
_RANGES: dict[str, tuple[float, float, str]] = {
    "z_a": (-0.5, 10.5, "V"), "z_b": (-0.5, 10.5, "V"), "u_a": (-0.5, 10.5, "V"), "u_b": (-0.5, 10.5, "V"),
    "p_a": (0.2, 12.0, "bar abs"), "p_b": (0.2, 12.0, "bar abs"), "p_s": (0.2, 12.0, "bar abs"),
    "theta": (-2 * math.pi, 2 * math.pi, "rad"), "omega": (-60.0, 60.0, "rad/s"), "torque": (-60.0, 60.0, "N·m"),
}
_LIKELY: dict[str, list[tuple[float, str]]] = {
    "bar abs": [(1e5, "Pa"), (1e2, "kPa"), (14.5, "psi"), (1e-1, "MPa")],
    "rad": [(180 / math.pi, "degrees")],
    "rad/s": [(180 / math.pi, "deg/s"), (60 / (2 * math.pi), "rpm")],
    "N·m": [(1e3, "N·mm")],
    "V": [(1e3, "mV")],
}


_PEAKED = ("rad", "rad/s", "N·m")  # units whose channels rest near 0: a wrong unit shows in the peak, not the median


class LogFormatError(ValueError):
    """A log that cannot be used, with what is wrong and where."""


@dataclass
class Experiment:
    """One experiment: time, the commands that drove it, what was measured, and how.

    Attributes:
        name: Log name (file stem).
        t: Sample times from 0 [s].
        inputs: Commands [V] by name (``z_a``, ``z_b``, ``u_a``, ``u_b``;
            adapters may have others).
        channels: Measured channels by name in the log's units.
        meta: The JSON metadata.
        filled: Per sample, True where :func:`on_uniform_grid` made the
            sample up (no measurement within half an interval); None: all
            measured.
    """

    name: str
    t: np.ndarray
    inputs: dict[str, np.ndarray] = field(default_factory=dict)
    channels: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    filled: np.ndarray | None = None  # per sample: made up by on_uniform_grid, not measured

    @property
    def dt(self) -> float:
        """Median sample period [s]."""
        return float(np.median(np.diff(self.t)))

    @property
    def duration(self) -> float:
        """Length [s]."""
        return float(self.t[-1] - self.t[0])


# a sample interval further than this from the median is irregular [fraction of the median]: a
# paced engine's start jitter stays well inside it, a period it skipped after an overrun does not
IRREGULAR = 0.1


def sampling_irregularity(t: np.ndarray) -> dict[str, float] | None:
    """How irregular a log's sampling is, or None if every interval is within :data:`IRREGULAR` of the median.

    Returns:
        ``irregular_intervals`` (count), ``largest_interval_s`` and
        ``median_interval_s`` [s].
    """
    dt = np.diff(t)
    med = float(np.median(dt))
    off = np.abs(dt - med) > IRREGULAR * med
    if not off.any():
        return None
    return {"irregular_intervals": int(off.sum()), "largest_interval_s": float(dt.max()), "median_interval_s": med}


def flat_channels(exp: Experiment) -> dict[str, float]:
    """The measured channels that read one value throughout the log, with that value.

    A sensor that reads nothing (unplugged, or a channel a rig model does not
    produce) is fitted as if it measured a constant: the baseline bends its
    parameters to match it, and every other channel pays. Whether the
    quantity simply did not change (a clamped handle's encoder, an ideal
    supply in a noise-free model) only the user can say, so the report
    names such channels rather than refusing the log.
    """
    return {c: float(v[0]) for c, v in exp.channels.items()
            if len(v) > 1 and np.all(np.isfinite(v)) and float(np.ptp(v)) == 0.0}


def on_uniform_grid(exp: Experiment) -> Experiment:
    """The experiment on a uniform time grid at its median interval (itself if already uniform).

    The replays and the zero-phase filters step sample by sample; a log
    with gaps (a rig's engine skips the periods it overran) or uneven
    intervals would put every later sample at the wrong time. Commands are
    held from their sample to the next (as the engine applied them: a
    skipped period changed nothing); measured channels are interpolated
    linearly, and a grid point with no measurement within half an interval
    is marked in ``filled`` so that the families leave it unscored.
    """
    if sampling_irregularity(exp.t) is None:
        return exp
    med = exp.dt
    n = int(math.floor((exp.t[-1] - exp.t[0]) / med + 1e-6)) + 1
    t = exp.t[0] + med * np.arange(n)
    # rounding: a measurement a hair after its grid point belongs to it
    held = np.clip(np.searchsorted(exp.t, t + 1e-3 * med, side="right") - 1, 0, len(exp.t) - 1)
    nxt = np.minimum(held + 1, len(exp.t) - 1)
    nearest = np.minimum(np.abs(exp.t[held] - t), np.abs(exp.t[nxt] - t))
    return Experiment(exp.name, t, {k: np.asarray(v)[held] for k, v in exp.inputs.items()},
                      {k: np.interp(t, exp.t, v) for k, v in exp.channels.items()}, dict(exp.meta),
                      nearest > 0.5 * med)


def unscored_near_fills(filled: np.ndarray | None, margin: int) -> np.ndarray | None:
    """Samples of a filtered channel that a made-up stretch reaches (None if nothing was made up).

    A single made-up sample between two measured ones is a straight line
    over one interval, below a low-pass's resolution; a run of two or more
    is not, and the filter spreads it ``margin`` samples either way.
    """
    if filled is None or not filled.any():
        return None
    out = filled.copy()
    runs = np.flatnonzero(np.diff(np.concatenate(([0], filled.astype(np.int8), [0]))))
    for a, b in zip(runs[::2], runs[1::2], strict=True):
        if b - a >= 2:
            out[max(0, a - margin): b + margin] = True
    return out


SPEED_RATIO_RANGE = (0.5, 2.0)
"""omega / (dθ/dt) outside this is another unit or sign; a log written right reads 1.00–1.02 (ours and the
independent rig's), and a speed filtered hard enough to halve it measures something else."""
SPEED_RATIO_MIN_SAMPLES = 100
"""Fewer samples in motion than this decide nothing about omega's unit or sign."""


def angle_rate(t: np.ndarray, theta: np.ndarray, half_window_s: float = 0.025) -> np.ndarray:
    """dθ/dt as the centred difference over ±``half_window_s`` [s] (an encoder's counts are too coarse for
    one sample's), one-sided at the ends."""
    if t.size < 3:
        return np.zeros_like(theta)
    k = max(1, min(int(round(half_window_s / float(np.median(np.diff(t))))), (t.size - 1) // 2))
    rate = np.empty_like(theta, dtype=float)
    rate[k:-k] = (theta[2 * k:] - theta[:-2 * k]) / (t[2 * k:] - t[:-2 * k])
    rate[:k] = (theta[k] - theta[0]) / (t[k] - t[0])
    rate[-k:] = (theta[-1] - theta[-1 - k]) / (t[-1] - t[-1 - k])
    return rate


def speed_of(e: Experiment) -> np.ndarray:
    """The vane's speed [rad/s]: the log's omega, or where it reads one value throughout (not measured),
    the angle's rate of change."""
    w = e.channels["omega"]
    return angle_rate(e.t, e.channels["theta"]) if w.size > 1 and float(np.ptp(w)) == 0.0 else w


def speed_ratio(t: np.ndarray, theta: np.ndarray, omega: np.ndarray, half_window_s: float = 0.025,
                moving: float = 0.2) -> tuple[float, int]:
    """How omega compares with the rate of change of theta: the least-squares slope of one on the other.

    The rate is the centred difference over ±``half_window_s`` [s] (an
    encoder's counts are too coarse for one sample's), taken where it
    exceeds ``moving`` [rad/s]. A flat omega (not measured) decides nothing.

    Returns:
        The slope, and over how many samples (1.0 and 0 when none).
    """
    if t.size < 3 or float(np.ptp(omega)) == 0.0:
        return 1.0, 0
    rate = angle_rate(t, theta, half_window_s)
    use = np.abs(rate) > moving
    x, y = rate[use], omega[use]
    return (float(x @ y / (x @ x)) if x.size else 1.0), int(x.size)


def check_frame(name: str, columns: list[str], data: np.ndarray, meta: dict[str, Any]) -> None:
    """Refuse a log whose columns, values or metadata are unusable.

    Raises:
        LogFormatError: Naming the log and the first problem found.
    """
    if list(columns) != list(LOG_COLUMNS):
        missing = [c for c in LOG_COLUMNS if c not in columns]
        extra = [c for c in columns if c not in LOG_COLUMNS]
        what = (f"missing column(s) {', '.join(missing)}" if missing else
                f"unknown column(s) {', '.join(extra)}" if extra else "columns in the wrong order")
        raise LogFormatError(f"{name}: {what}; the header must be exactly {','.join(LOG_COLUMNS)}")
    missing = [k for k in REQUIRED_META if k not in meta]
    if missing:
        raise LogFormatError(f"{name}.json: missing key(s) {', '.join(missing)}")
    if meta["rig"] not in ("rotary", "linear"):
        raise LogFormatError(f"{name}.json: rig = {meta['rig']!r} must be 'rotary' or 'linear'")
    for key, lo, hi in (("sample_rate_hz", 1.0, 1e5), ("p_atm_bar", 0.5, 1.2), ("working_pressure_bar", 1.0, 8.0)):
        v = meta[key]
        if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= float(v) <= hi:
            raise LogFormatError(f"{name}.json: {key} = {v!r} must be a number in {lo:g}–{hi:g}")
    if not isinstance(meta["human"], bool):
        raise LogFormatError(f"{name}.json: human = {meta['human']!r} must be true or false")
    if not isinstance(meta["experiment"], str):
        raise LogFormatError(f"{name}.json: experiment must be a string")
    if data.ndim != 2 or data.shape[0] < 10:
        raise LogFormatError(f"{name}: needs at least 10 rows, has {data.shape[0] if data.ndim == 2 else 0}")
    bad = ~np.isfinite(data)
    if bad.any():
        r, c = (int(v) for v in np.argwhere(bad)[0])
        raise LogFormatError(f"{name}: row {r + 1}, column {LOG_COLUMNS[c]} is {data[r, c]} (NaN or infinite)")
    dt = np.diff(data[:, 0])
    if (dt <= 0).any():
        i = int(np.argmax(dt <= 0)) + 1
        # repr, not :g — a clock counted from 1970 needs all its digits to show the two differ or not
        raise LogFormatError(f"{name}: time is not increasing at row {i + 1} (t = {float(data[i, 0])!r} s after "
                             f"{float(data[i - 1, 0])!r} s)")
    rate = 1.0 / float(np.median(dt))
    if abs(rate - float(meta["sample_rate_hz"])) > 0.05 * float(meta["sample_rate_hz"]):
        raise LogFormatError(f"{name}: samples come at {rate:.4g} Hz but the metadata says "
                             f"sample_rate_hz = {meta['sample_rate_hz']}; is t in seconds?")
    for j, col in enumerate(LOG_COLUMNS[1:], start=1):
        lo, hi, unit = _RANGES[col]
        v = data[:, j]
        med = float(np.median(np.abs(v)))
        if v.min() >= lo and v.max() <= hi:
            continue
        if unit in _PEAKED:
            # an angle, a speed or a torque rests near 0 much of a log, so its median says little of its
            # unit: the peak, rescaled, must land inside the range (deg/s read 85.6 for 1.5 rad/s); where
            # more than one unit would, each is named
            peak = float(np.max(np.abs(v)))
            guess = " or ".join(u for f, u in _LIKELY[unit] if 0.01 * hi <= peak / f <= hi) or None
        else:
            guess = next((u for f, u in _LIKELY.get(unit, []) if med > hi and 0.05 * hi <= med / f <= hi), None)
        hint = f" — looks like {guess}" if guess else ""
        atm = float(meta["p_atm_bar"])
        if unit == "bar abs" and not guess and v.min() < lo and lo <= v.min() + atm and v.max() + atm <= hi:
            # a sensor read against the room: its zero is the atmosphere
            hint = f" — looks like gauge pressure (bar g); add the atmosphere, p_atm_bar = {atm:g}"
        raise LogFormatError(f"{name}: column {col} spans {v.min():.4g} … {v.max():.4g}, outside the plausible "
                             f"{lo:g} … {hi:g} {unit}{hint}; the format wants {unit}")
    k, n = speed_ratio(data[:, 0], data[:, LOG_COLUMNS.index("theta")], data[:, LOG_COLUMNS.index("omega")])
    if n >= SPEED_RATIO_MIN_SAMPLES and not SPEED_RATIO_RANGE[0] <= k <= SPEED_RATIO_RANGE[1]:
        guess = next((why for f, why in ((-1.0, "omega written with the other sign than theta"),
                                         (180 / math.pi, "omega in deg/s"), (60 / (2 * math.pi), "omega in rpm"),
                                         (math.pi / 180, "theta in degrees"))
                      if 0.8 <= k / f <= 1.25), "")
        raise LogFormatError(f"{name}: omega is not the rate of change of theta: omega ≈ {k:.3g} × dθ/dt over {n} "
                             f"samples in motion{f' — looks like {guess}' if guess else ''}; the format wants "
                             "theta [rad] and omega [rad/s], CCW positive both")


def header_columns(name: str, line: str) -> list[str]:
    """The column names of a log's header line (blanks around a name are not part of it).

    Raises:
        LogFormatError: The header is separated by semicolons or tabs, which a spreadsheet set to a
            locale with decimal commas writes; the error had been "a row is not 1 numbers".
    """
    cols = [c.strip() for c in line.split(",")]
    if len(cols) == 1:
        for sep, what in ((";", "semicolons"), ("\t", "tabs")):
            if line.count(sep) >= len(LOG_COLUMNS) - 1:
                raise LogFormatError(f"{name}: the columns are separated by {what}; the format wants commas, and "
                                     "decimal points (a spreadsheet set to a locale with decimal commas writes both)")
    return cols


def log_paths(path: str | Path) -> tuple[Path, Path]:
    """The ``NAME.csv`` and ``NAME.json`` of a log given by either file or its stem.

    Only a final ``.csv`` or ``.json`` is taken off: a name may hold dots of its
    own (``sweep.rep2``), which ``Path.with_suffix`` would have cut.
    """
    p = Path(path)
    stem = p.name[: -len(p.suffix)] if p.suffix in (".csv", ".json") else p.name
    return p.with_name(stem + ".csv"), p.with_name(stem + ".json")


def read_log(path: str | Path) -> Experiment:
    """Read and check one ``NAME.csv`` + ``NAME.json`` pair (give either file or the stem)."""
    csv_path, json_path = log_paths(path)
    name = csv_path.stem
    if not csv_path.is_file():
        raise LogFormatError(f"{name}: {csv_path} does not exist")
    if not json_path.is_file():
        raise LogFormatError(f"{name}: {json_path} does not exist (every log is a .csv + .json pair)")
    try:
        # utf-8-sig: a byte-order mark (Windows tools write one) is not part of the first key
        meta = json.loads(json_path.read_text(encoding="utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{name}.json: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise LogFormatError(f"{name}.json: must hold an object")
    with open(csv_path, encoding="utf-8-sig") as fh:
        header = header_columns(name, fh.readline())
        try:
            data = np.loadtxt(fh, delimiter=",", ndmin=2)
        except ValueError as exc:
            cut = (" — its JSON still says \"running\": a writer that died mid-row leaves a partial last row; "
                   "the station repairs its own logs when it next starts (runlog.repair_log)"
                   if meta.get("status") == "running" else "")
            raise LogFormatError(f"{name}: a row is not {len(header)} numbers ({exc}){cut}") from None
    if data.size and data.shape[1] != len(header):
        raise LogFormatError(f"{name}: rows have {data.shape[1]} values, the header {len(header)}")
    check_frame(name, header, data, meta)
    t = data[:, 0] - data[0, 0]
    cols = {c: data[:, i] for i, c in enumerate(LOG_COLUMNS)}
    return Experiment(name, t, {c: cols[c] for c in INPUTS}, {c: cols[c] for c in MEASURED}, meta)


def read_logdir(directory: str | Path) -> list[Experiment]:
    """Every log pair in ``directory`` (sorted by name); refuses the first bad one."""
    d = Path(directory)
    if not d.is_dir():
        raise LogFormatError(f"{d}: not a directory")
    csvs = sorted(d.glob("*.csv"))
    if not csvs:
        raise LogFormatError(f"{d}: no NAME.csv + NAME.json logs")
    return [read_log(c) for c in csvs]


def write_log(directory: str | Path, name: str, data: np.ndarray, meta: dict[str, Any]) -> Path:
    """Write an (n, 11) array in the fixed format (checked first); returns the CSV path."""
    from app.engine.runlog import RunLogWriter

    check_frame(name, list(LOG_COLUMNS), np.asarray(data, dtype=float), meta)
    w = RunLogWriter(directory, name, meta)
    w.append_many(np.asarray(data, dtype=float))
    w.close("complete")
    if w.error:
        raise OSError(f"{name}: the log could not be written: {w.error}")
    return w.csv_path


# --------------------------------------------------------------------------- adapters


def read_chamber_leak(path: str | Path) -> Experiment:
    """A closed-chamber decay of ``refdata/chamber_leak`` (';'-separated, 10 Hz).

    Columns: t [ms, '.' as thousands separator], p [V], p [bar gauge]. The
    experiment holds one channel, ``p`` [bar abs] (gauge + 1.01325), and no
    inputs: the chamber is closed.
    """
    p = Path(path)
    t_ms, bar = [], []
    for i, line in enumerate(p.read_text(encoding="utf-8").splitlines()):
        if not line.strip():
            continue
        parts = line.strip().split(";")
        if len(parts) != 3:
            raise LogFormatError(f"{p.name}: line {i + 1} has {len(parts)} fields, expected 3 (t;p_V;p_bar)")
        try:
            t_ms.append(float(parts[0].replace(".", "")) / 1000.0)  # '151.303.000' → 151303.000 ms
            bar.append(float(parts[2]))
        except ValueError:
            raise LogFormatError(f"{p.name}: line {i + 1} is not numeric: {line!r}") from None
    t = np.asarray(t_ms) / 1000.0
    if t.size < 10 or np.any(np.diff(t) <= 0):
        raise LogFormatError(f"{p.name}: time must increase over at least 10 samples")
    return Experiment(p.stem, t - t[0], {}, {"p": np.asarray(bar) + 1.01325},
                      {"rig": "chamber", "sample_rate_hz": 1.0 / float(np.median(np.diff(t))),
                       "p_atm_bar": 1.01325, "experiment": "closed_chamber_decay", "human": False,
                       "source": str(p)})


def read_emps(path: str | Path) -> Experiment:
    """A run of the EMPS drive (``refdata/emps``, 1 kHz; Janot, Gautier, Brunot 2019).

    Channels: ``q`` motor position [m] and ``force`` = vir·gtau [N]; input
    ``q_ref`` [m].
    """
    from scipy.io import loadmat

    p = Path(path)
    try:
        d = loadmat(p)
    except (OSError, ValueError) as exc:
        raise LogFormatError(f"{p.name}: not a MATLAB file ({exc})") from None
    missing = [k for k in ("t", "qm", "qg", "vir", "gtau") if k not in d]
    if missing:
        raise LogFormatError(f"{p.name}: lacks {', '.join(missing)}")
    t = np.asarray(d["t"], dtype=float).ravel()
    force = (np.asarray(d["vir"], dtype=float) * float(np.asarray(d["gtau"]).ravel()[0])).ravel()
    return Experiment(p.stem, t - t[0], {"q_ref": np.asarray(d["qg"], dtype=float).ravel()},
                      {"q": np.asarray(d["qm"], dtype=float).ravel(), "force": force},
                      {"rig": "emps", "sample_rate_hz": 1.0 / float(np.median(np.diff(t))),
                       "experiment": "emps", "human": False, "source": str(p)})
