"""The ``cwrr`` command line."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence

import numpy as np


def _sim(args: argparse.Namespace) -> int:
    from app.engine.human import isotonic
    from app.engine.params import PlantParams, check_working_pressure
    from app.engine.sim import run_workout

    check_working_pressure(args.pw)
    if not (0.0 < args.duration <= 3600.0):
        raise ValueError(f"--duration {args.duration} is outside its allowed range (0, 3600] s")
    direction = -1 if args.direction == "FS" else 1
    reps = max(1, math.ceil(args.duration / 9.0))
    prog = isotonic(direction, repetitions=reps)
    import time

    t0 = time.perf_counter()
    res = run_workout(PlantParams(), prog, duration=args.duration, seed=args.seed, pw_bar=args.pw)
    wall = time.perf_counter() - t0
    tq = res.column("torque")
    mode = res.column("mode")
    active = mode > 0
    err = tq[active] - np.sign(tq[active]) * 1.2 if active.any() else np.zeros(1)
    summary = {
        "duration_s": args.duration, "samples": int(res.log.shape[0]), "wall_s": wall,
        "real_time_factor": args.duration / wall, "working_pressure_bar": args.pw,
        "direction": args.direction, "seed": args.seed,
        "theta_range_deg": [float(np.degrees(res.column("theta").min())), float(np.degrees(res.column("theta").max()))],
        "torque_abs_mean_active_nm": float(np.abs(tq[active]).mean()) if active.any() else 0.0,
        "torque_rmse_active_nm": float(np.sqrt(np.mean(err**2))),
        "active_fraction": float(active.mean()),
        "p_a_mean_bar": float(res.column("p_a").mean()), "p_b_mean_bar": float(res.column("p_b").mean()),
    }
    if args.log_dir:
        from app.engine.runlog import RunLogWriter

        w = RunLogWriter(args.log_dir, args.name, res.meta)
        w.append_many(res.log)
        w.close()
        summary["log"] = str(w.csv_path)
    if args.json:
        print(json.dumps(summary))
    else:
        for k_, v in summary.items():
            print(f"{k_:28s} {v}")
    return 0


def _bench(args: argparse.Namespace) -> int:
    from app.benchmarks import perf

    if args.which == "thesis":
        from pathlib import Path

        from app.thesis_bench import run_thesis_bench

        if not args.out:
            raise ValueError("bench thesis needs --out DIR (where results.json and the charts go)")
        records = run_thesis_bench(Path(args.out), seed=args.seed, plots=not args.no_plots)
        if args.json:
            print(json.dumps(records))
        else:
            print((Path(args.out) / "results.md").read_text())
        return 0
    if not (0.0 < args.duration <= 3600.0):
        raise ValueError(f"--duration {args.duration} is outside its allowed range (0, 3600] s")
    res = perf(duration=args.duration)
    print(json.dumps(res) if args.json else "\n".join(f"{k}: {v}" for k, v in res.items()))
    return 0


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from app.api.main import create_app
    from app.api.settings import Settings

    settings = Settings(host=args.host, port=args.port, viser_port=args.viser_port)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="info")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cwrr`` and ``python -m app``."""
    ap = argparse.ArgumentParser(prog="cwrr", description="CWRR lab station")
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sim", help="simulate a default isotonic workout faster than real time")
    s.add_argument("--duration", type=float, default=60.0, help="simulated time [s]")
    s.add_argument("--pw", type=float, default=3.0, help="working pressure [bar abs]")
    s.add_argument("--direction", choices=("FP", "FS"), default="FP")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--log-dir", default="", help="write the run log (CSV + JSON) here")
    s.add_argument("--name", default="workout")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=_sim)
    b = sub.add_parser("bench", help="benchmarks")
    b.add_argument("which", choices=("perf", "thesis"))
    b.add_argument("--duration", type=float, default=60.0, help="perf: simulated workout length [s]")
    b.add_argument("--out", default="", help="thesis: output directory")
    b.add_argument("--seed", type=int, default=0, help="thesis: base seed of the sensor noise")
    b.add_argument("--no-plots", action="store_true", help="thesis: skip the figures")
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=_bench)
    v = sub.add_parser("serve", help="start the lab station server on the simulated plant")
    v.add_argument("--host", default="127.0.0.1")
    v.add_argument("--port", type=int, default=8000)
    v.add_argument("--viser-port", type=int, default=8080)
    v.set_defaults(fn=_serve)
    args = ap.parse_args(argv)
    try:
        return int(args.fn(args))
    except ValueError as exc:  # includes ParameterError: the message names the parameter
        print(f"cwrr: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
