"""Send a rig's logs to the station and ask it where its simulator and the rig disagree.

The same diagnosis as ``cwrr diagnose LOGDIR``, run by a station elsewhere (the one beside the rig, say)
over its REST API, with the standard library only (and ``station_client.py`` beside it):

    python examples/diagnose_over_rest.py LOGDIR --station http://station:8000 --token $ADMIN \\
        --json report.json

Each ``NAME.csv`` + ``NAME.json`` pair in LOGDIR (the station's log format) is checked and stored as a
run (``POST /api/runs``; a log the station refuses stops the script with its reason before anything is
diagnosed), then diagnosed (``POST /api/diagnoses``). While it runs, what it is doing is printed; at the
end, the verdict, how far the gap shrinks and the ranking. Ctrl-C stops the diagnosis on the station.
Storing logs and diagnosing are an admin's, so a station with tokens needs the admin token.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from station_client import Refused, Station  # beside this file


def upload(st: Station, logdir: Path) -> list[int]:
    """Store each log pair of ``logdir`` as a run; their ids, in the folder's name order.

    Raises:
        Refused: A pair is incomplete or the station refuses a log (its reason).
    """
    names = sorted(p.stem for p in logdir.glob("*.csv"))
    if len(names) < 2:
        raise Refused(f"{logdir}: {len(names)} log(s); a diagnosis needs at least two (some are held out)")
    ids = []
    for name in names:
        meta = logdir / f"{name}.json"
        if not meta.is_file():
            raise Refused(f"{logdir / name}.csv has no {meta.name} beside it")
        run = st.call("POST", "/api/runs", {"name": name, "csv": (logdir / f"{name}.csv").read_text(),
                                            "meta": json.loads(meta.read_text())})
        ids.append(int(run["id"]))
    return ids


def diagnose(st: Station, run_ids: list[int], effects: list[str] | None = None,
             quiet: bool = False) -> dict[str, Any]:
    """Diagnose stored runs and return the report (``GET /api/runs/{id}/report``).

    Args:
        st: The station.
        run_ids: Runs with logs (at least two).
        effects: The candidate effects to try; None: all nine.
        quiet: No printing while it runs.
    """
    body: dict[str, Any] = {"run_ids": run_ids}
    if effects:
        body["effects"] = effects
    rid = st.call("POST", "/api/diagnoses", body)["run_id"]
    said = ""
    try:
        while (run := st.call("GET", f"/api/runs/{rid}"))["status"] == "running":
            if not quiet and run.get("progress") and run["progress"] != said:
                said = run["progress"]
                print(f"  {said}", flush=True)
            time.sleep(1.0)
    except KeyboardInterrupt:
        st.call("POST", f"/api/diagnoses/{rid}/stop")
        raise
    if run["status"] != "complete":
        raise Refused(f"diagnosis {rid} ended {run['status']}: {(run.get('result') or {}).get('error', '')}")
    return dict(st.call("GET", f"/api/runs/{rid}/report")) | {"run_id": rid}


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, upload, diagnose, print the verdict."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logdir", type=Path, help="a folder of NAME.csv + NAME.json logs")
    ap.add_argument("--station", default="http://127.0.0.1:8000", help="the station's address")
    ap.add_argument("--token", default=os.environ.get("CWRR_TOKEN", ""), help="admin token (or CWRR_TOKEN)")
    ap.add_argument("--effects", default="", help="comma-separated candidates to try (default: all nine)")
    ap.add_argument("--json", default="", help="save the whole report here")
    args = ap.parse_args(argv)
    st = Station(args.station, args.token)
    try:
        ids = upload(st, args.logdir)
        print(f"{len(ids)} logs stored as runs {ids[0]}–{ids[-1]}; diagnosing", flush=True)
        rep = diagnose(st, ids, [e for e in args.effects.split(",") if e] or None)
    except Refused as e:
        print(f"refused: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stopped: the diagnosis was stopped on the station", file=sys.stderr)
        return 130
    if args.json:
        Path(args.json).write_text(json.dumps(rep, indent=1))
    verdict, far = rep["verdict"], rep["how_far"]
    named = verdict.get("summary") or ", ".join(verdict["effects"]) or "no significant effect"
    print(f"diagnosis {rep['run_id']}: {named}")
    print(f"  error before {far['e_before']:.4g}, after {far['e_after']:.4g}, noise floor {far['e_floor']:.4g}; "
          f"unexplained {100 * far['unexplained_share']:.0f} % of the gap")
    for c in rep["ranking"][:3]:
        said = "significant" if c["significant"] else "not significant"
        print(f"  {c['effect']:20s} GC {c['gap_closure']:+.3f}  {said}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
