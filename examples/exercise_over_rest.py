"""Run one thesis scenario on the station over its REST API and keep what it measured.

A researcher's script, written against the station's OpenAPI schema (``/openapi.json``, browsable at
``/docs``) with the standard library only (and ``station_client.py`` beside it), so that it runs on any
Python 3.9+ next to the station:

    python examples/exercise_over_rest.py --scenario SC-1 --controller fuzzy --target 1.2 \\
        --person P-017 --csv run.csv

It connects the station if no rig is connected, starts the exercise, prints the interaction torque
while it runs, then the six metrics (thesis Eq 4.1–4.6) and what the station noticed, and saves the
run's log (the station's log format: ``t,z_a,z_b,u_a,u_b,p_a,p_b,p_s,theta,omega,torque``). Ctrl-C stops
the exercise on the station before the script ends. A refused request ends it with the station's own
words (a 422 names the field, a 409 says why the state forbids it) and exit status 1.

On a station with tokens, pass ``--token`` (or set ``CWRR_TOKEN``): the therapist's role may run
exercises.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

from station_client import Refused, Station  # beside this file

METRICS = {"mae": "MAE [N·m]", "iae": "IAE [N·m·s]", "itae": "ITAE [N·m·s²]", "evar": "e_var [N²·m²]",
           "rmse": "RMSE [N·m]", "maxae": "Max AE [N·m]"}


def run_exercise(st: Station, spec: dict[str, Any], csv_path: str = "", quiet: bool = False) -> dict[str, Any]:
    """Run one exercise to its end and return the stored run (``GET /api/runs/{id}``).

    Args:
        st: The station.
        spec: The exercise (``RunRequest``: scenario, controller, target_nm, person, …).
        csv_path: Where to save the run's log; "" keeps none.
        quiet: No printing while it runs.

    Returns:
        The run as stored: status, metrics, result (with its ``warnings``).
    """
    state = st.call("GET", "/api/engine")["state"]
    if state == "fault":  # never cleared by a script: a person looks at why first
        raise Refused("the station has a latched fault; clear it on the dashboard once you know why")
    if state == "disconnected":
        state = st.call("POST", "/api/engine/connect", {})["state"]
    run_id = st.call("POST", "/api/engine/start", spec)["run_id"]
    if not quiet:
        print(f"run {run_id} started: {spec['scenario']}, {spec['controller']}, {spec['target_nm']} N·m")
    since, shown = 0.0, -1.0
    try:
        while (run := st.call("GET", f"/api/runs/{run_id}"))["status"] == "running":
            live = st.call("GET", f"/api/live?since={since}")
            since = live["t_last"]
            if live["rows"] and not quiet and since - shown >= 1.0:
                shown = since
                torque = live["rows"][-1][live["columns"].index("torque")]
                print(f"  t = {since:5.1f} s   interaction torque {torque:+.3f} N·m", flush=True)
            time.sleep(0.25)
    except KeyboardInterrupt:
        st.call("POST", "/api/engine/stop")
        raise
    if csv_path:
        with open(csv_path, "wb") as f:
            f.write(st.raw("GET", f"/api/runs/{run_id}/export?fmt=csv"))
    return dict(run)


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, run the exercise, print its result."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--station", default="http://127.0.0.1:8000", help="the station's address")
    ap.add_argument("--token", default=os.environ.get("CWRR_TOKEN", ""), help="API token (or CWRR_TOKEN)")
    ap.add_argument("--scenario", default="SC-1", help="SC-1 … SC-4")
    ap.add_argument("--controller", default="fuzzy", help="fuzzy, pid or default")
    ap.add_argument("--target", type=float, default=1.2, help="target torque [N·m], + pronation")
    ap.add_argument("--person", default="", help="pseudonymous person id, e.g. P-017 (no names)")
    ap.add_argument("--workout-id", type=int, help="a stored exercise shape (GET /api/params?kind=workout)")
    ap.add_argument("--csv", default="", help="save the run's log here")
    ap.add_argument("--json", action="store_true", help="print the stored run as JSON instead")
    args = ap.parse_args(argv)
    spec: dict[str, Any] = {"scenario": args.scenario, "controller": args.controller, "target_nm": args.target,
                            "person": args.person}
    if args.workout_id is not None:
        spec["workout_id"] = args.workout_id
    st = Station(args.station, args.token)
    try:
        run = run_exercise(st, spec, args.csv, quiet=args.json)
    except Refused as e:
        print(f"refused: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stopped: the exercise was stopped on the station", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(run, indent=1))
        return 0
    print(f"run {run['id']}: {run['status']}")
    for key, name in METRICS.items():
        value = (run.get("metrics") or {}).get(key)
        print(f"  {name:15s} {'–' if value is None else f'{value:.4g}'}")
    result = run.get("result") or {}
    lo_hi = result.get("angle_range_deg")
    if lo_hi:
        print(f"  range of motion {lo_hi[0]:.0f}° … {lo_hi[1]:.0f}° (positive: pronation)")
    for warning in result.get("warnings", []):
        print(f"  note: {warning}")
    if args.csv:
        print(f"log saved to {args.csv}")
    return 0 if run["status"] == "complete" else 2


if __name__ == "__main__":
    sys.exit(main())
