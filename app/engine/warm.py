"""Compile the numba kernels ahead of their first use: ``python -m app.engine.warm [PART ...]``.

The kernels are cached on disk (``NUMBA_CACHE_DIR``, see :mod:`app`), but a
fresh install or checkout has to compile them once: on the 2-core station
about 50 s for the simulator (the plant inlined into its loops) and 35 s for
the diagnosis replay. Whoever meets that first waits: the first
``cwrr serve`` answers its health check only after it, and every test
process that starts at the same time compiles a copy of its own. So the
Docker image runs this at build time, ``./dev test`` runs its parts
beside ruff and mypy before the tests start, and ``cwrr serve`` runs the
``sim`` part itself when it is cold, before the server starts (see
:func:`cold`).

A part that ran to its end leaves a marker in the cache directory, so
whoever comes next can tell a warm cache from a cold one without
compiling anything.

Parts (each compiles what its workloads call; given several, each runs in a
process of its own, so that they compile on several cores at once):

- ``sim``: the station's simulated rig (a period's advance and sensors), the
  controller pipeline with the fuzzy gains, the autotuner's PRV controller
  and the compiled workout loop;
- ``replay``: the diagnosis replay (pneumatic network along a measured
  motion, the friction law), the linear friction fit's onset model and the
  valve identification's pressure integrator.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path


def _sim() -> None:
    from app.engine.control.blocks import PRVController
    from app.engine.control.interaction import InteractionController
    from app.engine.hardware.sim import SimulatedRig
    from app.engine.loop import SimClock
    from app.engine.sim import run_workout

    run_workout(duration=0.05)
    clock = SimClock()
    rig = SimulatedRig(clock, period=0.005)
    rig.activate()
    clock.sleep_until(0.005)
    InteractionController().step(rig.read(), 0.005)
    PRVController("a", "pid")  # the pressure-loop autotuner's controller (compiles its entry point)


def _replay() -> None:
    import numpy as np

    from app.engine.constants import P_ATM_BAR
    from app.engine.diagnosis.logs import Experiment
    from app.engine.diagnosis.rotary import RotaryFamily
    from app.engine.ident.dcv import compile_integrator
    from app.engine.ident.fitting import compile_onset_model

    # a made-up log (not the simulator's: that is the other part's to compile): 2 s at 200 Hz of
    # the handle swung at 0.5 Hz with noisy pressures and torque, DCVs shut
    t = np.arange(400) * 0.005
    rng = np.random.default_rng(0)
    theta = np.round(0.3 * np.sin(np.pi * t) / 1.5e-3) * 1.5e-3

    def noisy(v: float, sd: float) -> np.ndarray:
        return v + sd * rng.standard_normal(t.size)

    exp = Experiment("warm", t, {"z_a": np.full_like(t, 2.0), "z_b": np.full_like(t, 2.0),
                                 "u_a": np.full_like(t, 5.0), "u_b": np.full_like(t, 5.0)},
                     {"p_a": noisy(3.0, 0.003), "p_b": noisy(3.0, 0.003), "p_s": noisy(7.0, 0.003),
                      "theta": theta, "omega": np.gradient(theta, t), "torque": noisy(0.0, 0.01)},
                     {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": P_ATM_BAR, "working_pressure_bar": 3.0,
                      "experiment": "warm", "human": True})
    fam = RotaryFamily()
    fam.predict(fam.prepare(exp), {s.name: s.x0 for s in fam.baseline()}, ())
    compile_onset_model()
    compile_integrator()


PARTS: dict[str, Callable[[], None]] = {"sim": _sim, "replay": _replay}
"""Part name → what it runs."""


def _marker(part: str) -> Path | None:
    """The file that says ``part`` ran to its end against this cache (None: no cache directory set)."""
    cache = os.environ.get("NUMBA_CACHE_DIR")  # set on importing app, keyed by the sources' hash
    return Path(cache) / f"warm-{part}.done" if cache else None


def cold(parts: Sequence[str] = tuple(PARTS)) -> list[str]:
    """The parts of ``parts`` that have not run against the current kernel cache.

    The cache directory is keyed by a hash of the sources (:mod:`app`), so
    after any change to the code every part is cold again.
    """
    return [p for p in parts if (m := _marker(p)) is None or not m.exists()]


def warm(parts: Sequence[str] = tuple(PARTS)) -> dict[str, float]:
    """Run ``parts``, one process each when there are several; the compiled kernels land in the on-disk cache.

    Args:
        parts: Names from :data:`PARTS`.

    Returns:
        Seconds per part (a few when the cache was already warm).

    Raises:
        ValueError: An unknown part.
        RuntimeError: A part's process failed (its error output is in the message).
    """
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise ValueError(f"no warm-up part {', '.join(unknown)}; known: {', '.join(PARTS)}")
    if len(parts) == 1:
        t = time.perf_counter()
        PARTS[parts[0]]()
        if (m := _marker(parts[0])) is not None:
            try:
                m.touch()
            except OSError:  # a cache others wrote and this user may only read: it stays "cold"
                pass
        return {parts[0]: time.perf_counter() - t}
    # one process per part: numba compiles on one core per process, and the parts share nothing
    t = time.perf_counter()
    procs = {p: subprocess.Popen([sys.executable, "-m", "app.engine.warm", p], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True) for p in parts}
    out = {}
    for p, proc in procs.items():
        _, err = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"warm-up part {p} failed: {err[-2000:]}")
        out[p] = time.perf_counter() - t
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m app.engine.warm [PART ...]`` (default: every part, each in a process of its own)."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        took = warm(args or tuple(PARTS))
    except ValueError as exc:
        print(f"warm: {exc}", file=sys.stderr)
        return 2
    print("compiled: " + ", ".join(f"{p} {s:.1f} s" for p, s in took.items()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
