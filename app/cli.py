"""The ``cwrr`` command line."""

from __future__ import annotations

import argparse
import faulthandler
import math
import os
import signal
import socket
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.storage import strict_json

if TYPE_CHECKING:
    from app.api.settings import Settings


# the scenarios' and controllers' names as app.engine.scenarios holds them (tests/test_cli_api.py), written
# out so that `cwrr --help` and the server's start do not import the simulator to build the parser
SIM_SCENARIOS = ("SC-1", "SC-2", "SC-3", "SC-4")
SIM_CONTROLLERS = ("default", "pid", "fuzzy")


def seed_arg(text: str) -> int:
    """``--seed``: a whole number ≥ 0 (numpy's generators take no negative seed)."""
    try:
        v = int(text)
    except ValueError:
        v = -1
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed: give a whole number, 0 or more")
    return v


def port_arg(text: str) -> int:
    """A TCP port: a whole number from 1 to 65535."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a TCP port: give a whole number from 1 to 65535")
    return v


def writable_file(flag: str, path: str) -> None:
    """Refuse output file ``path`` (given as ``flag``) before the work runs: a folder, or one in a folder
    that is missing or cannot be written (the work can take minutes, and its result would be lost)."""
    out = Path(path)
    if out.is_dir():
        raise ValueError(f"{flag} {out}: a folder; give a file name, e.g. {out / 'report.json'}")
    if not out.parent.is_dir() or not os.access(out.parent, os.W_OK):
        raise ValueError(f"{flag} {out}: the folder {out.parent} does not exist or cannot be written")


def writable_dir(flag: str, path: str) -> None:
    """Refuse output folder ``path`` (given as ``flag``) before the work runs: a file, or under one, or under
    a folder that cannot be written (a missing folder is made, with its parents)."""
    d = Path(path)
    have = next(p for p in (d, *d.parents) if p.exists())
    if not have.is_dir() or not os.access(have, os.W_OK):
        raise ValueError(f"{flag} {d}: {have} is not a folder that can be written")


def _sim_scenario(args: argparse.Namespace) -> int:
    """One of the thesis's scenarios (SPEC §5) with one controller, scored as ``bench thesis`` scores it."""
    from app.engine.params import check_range
    from app.engine.scenarios import Case, ScenarioSettings, run_case

    if args.duration is not None or args.direction is not None:
        raise ValueError("--duration and --direction do not go with --scenario: the scenario sets its length, "
                         "and the sign of --target the direction (positive: pronation, FP)")
    target = 1.2 if args.target is None else args.target
    if target == 0.0:
        raise ValueError("--target 0 N·m: an isotonic exercise needs a torque to work against")
    check_range("target", abs(target), 0.0, 8.0, lo_open=True, unit="N·m")
    on = args.scenario != "SC-1"  # SPEC §5: PDRA and TDRA on in SC-2 to SC-4
    case = Case(args.scenario, target, on, on)
    w0 = time.perf_counter()
    run = run_case(case, args.controller or "fuzzy", seed=args.seed, settings=ScenarioSettings(pw_bar=args.pw))
    wall = time.perf_counter() - w0
    rec = run.record()
    out: dict[str, object] = {**rec, "working_pressure_bar": args.pw, "seed": args.seed,
                              "sim_s": float(run.result.column("t")[-1]), "wall_s": wall}
    return _sim_report(args, out, run.result.log, {**run.result.meta, **rec})


def _sim_report(args: argparse.Namespace, summary: dict[str, object], log: np.ndarray, meta: dict[str, Any]) -> int:
    """Write the run's log where ``--log-dir`` asks (its path joins the summary), then print the summary."""
    if args.log_dir:
        from app.engine.runlog import RunLogWriter

        w = RunLogWriter(args.log_dir, args.name, meta)
        w.append_many(log)
        w.close()
        summary["log"] = str(w.csv_path)
    print(strict_json(summary) if args.json else human(summary))
    return 0


def _sim(args: argparse.Namespace) -> int:
    from app.engine.human import isotonic
    from app.engine.params import PlantParams, check_working_pressure
    from app.engine.sim import run_workout

    check_working_pressure(args.pw)
    if args.log_dir:
        writable_dir("--log-dir", args.log_dir)
    if args.scenario:
        return _sim_scenario(args)
    if args.controller is not None or args.target is not None:
        raise ValueError("--controller and --target go with --scenario (the default workout runs the Default "
                         "controller at 1.2 N·m)")
    args.duration = 60.0 if args.duration is None else args.duration
    args.direction = args.direction or "FP"
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
    return _sim_report(args, summary, res.log, res.meta)


def _bench(args: argparse.Namespace) -> int:
    from app.benchmarks import perf

    if args.which == "thesis":
        from pathlib import Path

        from app.thesis_bench import run_thesis_bench

        if not args.out:
            raise ValueError("bench thesis needs --out DIR (where results.json and the charts go)")
        writable_dir("--out", args.out)
        records = run_thesis_bench(Path(args.out), seed=args.seed, plots=not args.no_plots)
        if args.json:
            print(strict_json(records))
        else:
            print((Path(args.out) / "results.md").read_text())
        return 0
    if not (0.0 < args.duration <= 3600.0):
        raise ValueError(f"--duration {args.duration} is outside its allowed range (0, 3600] s")
    res = perf(duration=args.duration)
    print(strict_json(res) if args.json else human(res))
    return 0


def _progress_printer(enabled: bool) -> Callable[[object], None] | None:
    last = [""]

    def show(pr: object) -> None:
        msg = getattr(pr, "message", "")
        if enabled and msg and msg != last[0]:
            print(f"  {msg}", file=sys.stderr, flush=True)
            last[0] = msg

    return show if enabled else None


def human(obj: Any, indent: int = 0) -> str:
    """A result as a person reads it (``--json`` gives the same as JSON): one ``key: value`` per line,
    nested results indented, numbers to four significant digits, text as written (JSON escapes ω as \\u03c9)."""

    def cell(v: Any) -> str:
        if isinstance(v, bool) or v is None:
            return str(v).lower() if v is not None else "—"
        if isinstance(v, float):  # large ones whole (94934, not 9.493e+04)
            return "—" if not math.isfinite(v) else f"{v:.0f}" if 1e4 <= abs(v) < 1e12 else f"{v:.4g}"
        if isinstance(v, list | tuple) and all(not isinstance(x, dict | list | tuple) for x in v):
            return ", ".join(cell(x) for x in v)
        return str(v)

    pad = "  " * indent
    lines = []
    for k, v in (obj.items() if isinstance(obj, dict) else enumerate(obj)):
        if isinstance(v, dict) or (isinstance(v, list | tuple) and any(isinstance(x, dict | list | tuple) for x in v)):
            lines.append(f"{pad}{k}:")
            lines.append(human(v, indent + 1))
        else:
            lines.append(f"{pad}{k}: {cell(v)}")
    return "\n".join(lines)


def sweep_table(table: dict[str, Any]) -> str:
    """A friction sweep's table laid out as the thesis's Table 4.2: a row per working pressure, each
    direction's T_s, T_c, ω_s and B across (CCW +, CW −)."""
    params = (("ts", "T_s", "N·m"), ("tc", "T_c", "N·m"), ("ws", "ω_s", "rad/s"), ("b", "B", "N·m·s/rad"))
    cols = [("pw_bar", "P_w [bar]")] + [(f"{k}_{d}", f"{label}{sign} [{unit}]")
                                         for d, sign in (("ccw", "+"), ("cw", "−")) for k, label, unit in params]
    width = [max(len(h), 9) for _, h in cols]
    lines = ["  ".join(h.rjust(w) for (_, h), w in zip(cols, width, strict=True))]
    for i in range(len(table["pw_bar"])):
        lines.append("  ".join(f"{table[k][i]:.4g}".rjust(w) for (k, _), w in zip(cols, width, strict=True)))
    return "\n".join(lines)


def friction_summary(detail: dict[str, Any], rotary: bool) -> str:
    """An identification's fit per direction as a person reads it: each parameter with its 95 % interval,
    the tests behind it and the model chosen (``--json`` prints the contract, ``--out`` keeps everything).

    Args:
        detail: Direction → :meth:`~app.engine.ident.fitting.FrictionFit.as_dict` (and, on the linear
            rig, ``moving_mass_kg``).
        rotary: Torques and angular speeds (N·m, rad/s), else forces and speeds (N, m/s).
    """
    force, speed, damping = ("N·m", "rad/s", "N·m·s/rad") if rotary else ("N", "m/s", "N·s/m")
    rows = (("fs", "T_s" if rotary else "F_s", force), ("fc", "T_c" if rotary else "F_c", force),
            ("vs", "ω_s" if rotary else "v_s", speed), ("b", "B", damping))
    lines = []
    for key, d in detail.items():
        if not isinstance(d, dict):
            continue
        ch = d["choice"]
        model = "Stribeck" if ch["selected"] == "stribeck" else "Coulomb + viscous"
        lines.append(f"{key} ({d['direction']}): {d['n_static']} static and {d['n_dynamic']} dynamic tests, "
                     f"RMSE {d['rmse']:.3g} {force}; {model} chosen by AICc (Stribeck {ch['aicc_stribeck']:.1f}, "
                     f"Coulomb + viscous {ch['aicc_cv']:.1f}; the thesis's rule: {ch['thesis_rule']})")
        for k, label, unit in rows:
            ci = d["ci"][k]
            why = "  the interval reaches its search bound: these tests do not pin it down" if ci["at_bound"] else ""
            lines.append(f"  {label:4s} {d[k]:10.4g} {unit:10s} 95 % [{ci['lo']:.4g}, {ci['hi']:.4g}] "
                         f"({ci['method']}){why}")
    if detail.get("moving_mass_kg"):  # 0: no inertia correction asked for
        lines.append(f"moving mass fitted for the inertia correction: {detail['moving_mass_kg']:.4g} kg")
    return "\n".join(lines)


def _identify(args: argparse.Namespace) -> int:
    from app.engine.ident import runner
    from app.engine.ident.gui_rules import MSG_N, MSG_PW, LinearInputs, RotaryInputs
    from app.engine.params import ParameterError, check_working_pressure

    # the thesis GUIs' rules and messages, before anything runs; and where the results go
    if args.out:
        writable_dir("--out", args.out)
    if args.rig == "sweep" and args.table:
        writable_file("--table", args.table)
    if args.rig == "seal":
        from pathlib import Path

        from app.engine.ident.seal import fit_seals, seal_plot

        if not args.files:
            raise ParameterError("identify seal: give one or more data files")
        result = fit_seals([Path(f) for f in args.files])
        if args.out:
            d = Path(args.out)
            d.mkdir(parents=True, exist_ok=True)
            (d / "seal_friction.json").write_text(strict_json(result, indent=1))
            if not args.no_plots:
                seal_plot(result, d / "seal_friction.png")
        print(strict_json(result) if args.json else human(result["seals"]))
        return 0
    if args.rig == "dcv":
        return _identify_dcv(args)
    if args.rig == "pid":
        return _identify_pid(args)
    if args.rig == "closedloop":
        from app.engine.ident.rotary import closed_loop_validation
        from app.engine.ident.sweep import load_table

        check_working_pressure(args.pw)
        table = load_table(args.table) if args.table else None
        res = {k: v for k, v in closed_loop_validation(args.target, args.pw, table, args.seed).items()
               if k not in ("t", "torque", "moving")}
        print(strict_json(res) if args.json else human(res))
        return 0
    if args.ns < 30 or args.nd < 30:
        raise ParameterError(f"{'ns' if args.ns < 30 else 'nd'}: {MSG_N}")
    out: dict[str, object]
    if args.rig == "rotary":
        if not (1.0 <= args.pw <= 8.0):
            raise ParameterError(f"pw_bar: {MSG_PW}")
        RotaryInputs(ns=args.ns, nd=args.nd, pw_bar=args.pw)
        res, run = runner.identify_rotary_sim(args.pw, args.ns, args.nd, seed=args.seed,
                                              on_progress=_progress_printer(args.progress))
        out = res.contract()
        detail = {"ccw": res.ccw.as_dict(), "cw": res.cw.as_dict()}
    elif args.rig == "linear":
        from app.engine.params import DCVParams, PlantParams

        plant = PlantParams.linear_rig(args.cylinder,  # type: ignore[arg-type]
                                       dcv=DCVParams.without_null_zone() if args.no_null_zone else DCVParams())
        cyl = plant.linear
        assert cyl is not None
        LinearInputs(cyl.stroke * 1e3, cyl.bore * 1e3, cyl.rod * 1e3, args.ns, args.nd)
        res, run = runner.identify_linear_sim(args.cylinder, args.ns, args.nd, seed=args.seed, params=plant,
                                              on_progress=_progress_printer(args.progress))
        out = res.contract()
        detail = {"extension": res.extension.as_dict(), "retraction": res.retraction.as_dict(),
                  "moving_mass_kg": res.moving_mass_kg}
    else:
        from app.engine.ident.sweep import save_table, sweep_rotary_sim

        pressures = [float(x) for x in args.pressures.split(",")]
        for pw in pressures:
            if not (1.0 <= pw <= 8.0):
                raise ParameterError(f"pw_bar: {MSG_PW}")
        import time

        w0 = time.perf_counter()
        sw = sweep_rotary_sim(pressures, args.ns, args.nd, seed=args.seed)
        wall = time.perf_counter() - w0
        out = sw.as_dict()["table"]
        detail = sw.as_dict()
        detail["timing"] = {"wall_seconds": wall, "rig_seconds": sum(p.sim_seconds for p in sw.points)}
        if args.table:
            save_table(sw.to_table(), args.table)
        if args.out:
            from pathlib import Path

            from app.engine.ident.plots import friction_surface_plot

            d = Path(args.out)
            d.mkdir(parents=True, exist_ok=True)
            (d / "sweep.json").write_text(strict_json(detail, indent=1, default=float))
            if not args.no_plots:
                friction_surface_plot(sw.to_table(), d / "friction_surface.png")
        print(f"sweep: {detail['timing']['rig_seconds']:.0f} s of rig time simulated in {wall:.1f} s",
              file=sys.stderr)
        if args.json:
            print(strict_json(out))
        else:
            print(sweep_table(out))
            print("--json prints the table, --table FILE saves it for the controllers, --out DIR keeps every fit",
                  file=sys.stderr)
        return 0
    if args.out:
        from pathlib import Path

        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "result.json").write_text(strict_json({"contract": out, "detail": detail,
                                                    "data": run.procedure.data.as_dict(),
                                                    "sim_seconds": run.summary.sim_seconds,
                                                    "wall_seconds": run.summary.wall_seconds}, default=float))
        if not args.no_plots:
            from app.engine.ident.plots import friction_curve_plot

            friction_curve_plot(run.procedure.data, res, d / "friction_curve.png")
    if args.json:
        print(strict_json(out))
    else:
        print(friction_summary(detail, rotary=args.rig == "rotary"))
        print(f"rig time {run.summary.sim_seconds:.0f} s, computed in {run.summary.wall_seconds:.1f} s; "
              "--json prints the estimates, --out DIR keeps every test and fit", file=sys.stderr)
    return 0


def _identify_dcv(args: argparse.Namespace) -> int:
    """CPR maps, new-flow-model fit and validation against the literature models (thesis 4.1)."""
    from pathlib import Path

    from app.engine.ident import runner
    from app.engine.ident.dcv import THESIS_VALIDATION

    est, run, vrun, cases = runner.identify_dcv_sim(args.dcv_model, seed=args.seed, null_zone=not args.no_null_zone,
                                                    on_progress=_progress_printer(args.progress))
    n_thesis = len(THESIS_VALIDATION)

    def mean_err(rows: list[Any]) -> dict[str, float]:
        return {m: float(sum(c.mape_pct[m] for c in rows) / len(rows)) for m in rows[0].mape_pct} if rows else {}

    summary = {
        "plant_dcv_model": args.dcv_model,
        "plant_null_zone": not args.no_null_zone,
        "fit": est.as_dict(),
        "validation": {"thesis_points": [c.summary() for c in cases[:n_thesis]],
                       "held_out": [c.summary() for c in cases[n_thesis:]],
                       "mean_mape_pct": {"thesis_points": mean_err(cases[:n_thesis]),
                                         "held_out": mean_err(cases[n_thesis:])}},
        "timing": {"rig_seconds": run.summary.sim_seconds + vrun.summary.sim_seconds,
                   "wall_seconds": run.summary.wall_seconds + vrun.summary.wall_seconds},
    }
    if args.out:
        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "dcv.json").write_text(strict_json(summary | {"cpr_tests": run.procedure.data.as_dict()["tests"]},
                                                indent=1, default=float))
        if not args.no_plots:
            from app.engine.ident.plots import cpr_plot, flow_fit_plot, validation_plot

            cpr_plot(est, d / "cpr.png")
            flow_fit_plot(est, run.procedure.data, d / "flow_fit.png")
            validation_plot(cases[:n_thesis], d / "validation_thesis.png")
            validation_plot(cases[n_thesis:], d / "validation_held_out.png")
    if args.json:
        print(strict_json(summary, default=float))
    else:
        print("mean absolute percentage error of each flow model [%]:")
        print(human(summary["validation"]["mean_mape_pct"], 1))
        print(f"rig time {summary['timing']['rig_seconds']:.0f} s, computed in "
              f"{summary['timing']['wall_seconds']:.1f} s", file=sys.stderr)
    return 0


def _identify_pid(args: argparse.Namespace) -> int:
    """Frequency-response PID autotune of one PRV loop (thesis 3.6.2), beside the thesis's gains."""
    from dataclasses import asdict
    from pathlib import Path

    from app.engine.ident.pid_tune import THESIS_FINAL, THESIS_TUNED, AutotuneSpec, autotune_sim

    spec = AutotuneSpec(side=args.side, pw_bar=args.pw, bandwidth_rad_s=args.bandwidth, phase_margin_deg=args.pm)
    r = autotune_sim(spec, seed=args.seed)
    t = r["tuning"]
    out = {"side": args.side, "tuned": {"Kp": t.kp, "Ki": t.ki, "Kd": t.kd, "N": t.n_filter,
                                        "crossover_rad_s": t.crossover_rad_s, "phase_margin_deg": t.phase_margin_deg,
                                        "targets_met": t.exact, "note": t.note},
           "thesis_autotuner": dict(zip(("Kp", "Ki", "Kd"), THESIS_TUNED[args.side], strict=True)),
           "thesis_eq_3_26": dict(zip(("Kp", "Ki", "Kd"), THESIS_FINAL[args.side], strict=True)),
           "thesis_margins_on_this_plant": {k: {"crossover_rad_s": v[0], "phase_margin_deg": v[1]}
                                            for k, v in r["thesis_margins"].items()},
           "frf": r["frf"].as_dict(), "steps": [s.summary() for s in r["steps"]], "spec": asdict(spec),
           "rig_seconds": r["rig_seconds"]}
    if args.out:
        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        (d / f"pid_{args.side}.json").write_text(strict_json(out, indent=1, default=float))
        if not args.no_plots:
            from app.engine.ident.plots import autotune_plot

            autotune_plot(r, d / f"pid_{args.side}.png")
    print(strict_json(out, default=float) if args.json else human(out["tuned"]))
    return 0


def _serve(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from app.api.settings import Settings
    from app.engine.params import validation_reasons

    try:
        # a flag given wins over its CWRR_* environment variable; one not given leaves that in force
        # (the address flags defaulted to 127.0.0.1:8000 and overrode CWRR_HOST / CWRR_PORT, which the
        # docs list as settings, without a word)
        given = (("host", args.host), ("port", args.port), ("viser_port", args.viser_port),
                 ("hardware", args.hardware), ("data_dir", args.data_dir),
                 ("viser_public_url", args.viser_public_url))
        settings = Settings(**{k: v for k, v in given if v not in (None, "")})
    except ValidationError as exc:
        raise ValueError(validation_reasons(exc, "settings")) from None
    # before the minute of compiling and the station's start, not after them: a second server on a
    # port in use had built its station and then left with uvicorn's bare "address already in use"
    for flag, port in (("--port", settings.port), ("--viser-port", settings.viser_port)):
        if port and (why := _port_taken(settings.host, port)):
            raise ValueError(f"{flag} {port}: cannot listen on {settings.host}:{port} ({why}); is another "
                             f"cwrr serve running? Stop it or choose another port")
    from app.storage import DataDirInUse, check_database, claim_data_dir, release_data_dir

    check_database(settings.db_url)  # a database that cannot be reached, told before compiling too
    if settings.hardware:  # and a hardware configuration that is missing or wrong
        from app.engine.hardware.config import load_config

        load_config(settings.hardware)
    # one station per data folder, told before the minute of compiling too
    try:
        claim_data_dir(settings.data_dir)  # held while the server runs; the lifespan's claim nests in it
    except DataDirInUse as exc:
        raise ValueError(str(exc)) from None
    try:
        return _serve_claimed(settings)
    finally:
        release_data_dir(settings.data_dir)


def _serve_claimed(settings: Settings) -> int:
    """Compile if need be and run uvicorn (the data folder is claimed)."""
    import uvicorn

    from app.api.main import create_app

    if settings.start_engine and settings.auto_connect:
        _compile_first()
    if settings.realtime:
        from app.engine.loop import make_server_realtime

        # before uvicorn starts any thread, so they all inherit it (see make_server_realtime)
        why = make_server_realtime()
        if why:
            print(f"cwrr serve: normal scheduling ({why}); /api/health reports the loop's jitter", file=sys.stderr)
    print(serve_banner(settings), file=sys.stderr, flush=True)
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")
    return 0


def serve_banner(settings: Settings) -> str:
    """What ``cwrr serve`` is about to start, in one line: where the dashboard and the live plots answer,
    which rig it drives and where the runs are kept (a database URL's password left out).

    Args:
        settings: The server's :class:`~app.api.settings.Settings`.
    """
    from app.storage import database_dialect, redact_url, sqlite_path

    wildcard = settings.host in ("0.0.0.0", "::", "")
    host = "<this station>" if wildcard else f"[{settings.host}]" if ":" in settings.host else settings.host
    parts = [f"the dashboard at http://{host}:{settings.port}/"]
    if settings.viser_port:
        parts.append(f"the live plots at {settings.viser_public_url or f'http://{host}:{settings.viser_port}'}/")
    if not settings.start_engine:
        parts.append("no engine")
    elif settings.hardware:
        parts.append(f"the rig configured in {settings.hardware}")
    else:
        parts.append("the simulated rig" + ("" if settings.auto_connect else " (connected from the dashboard)"))
    url = settings.db_url
    parts.append(f"runs kept in {sqlite_path(url)} (SQLite)" if database_dialect(url) == "sqlite"
                 else f"runs kept in {redact_url(url)}")
    if settings.auth_enabled:
        parts.append("tokens required")
    return "cwrr serve: " + ", ".join(parts) + "; Ctrl-C stops it"


def _port_taken(host: str, port: int) -> str | None:
    """Why a TCP server could not listen on ``host:port`` now, or None when it could.

    Binds as uvicorn does (SO_REUSEADDR, so a port left in TIME_WAIT by a
    server just stopped counts as free) and closes at once.
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError as exc:
        return f"host not resolved: {exc}"
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(addr)
        except OSError as exc:
            return exc.strerror or str(exc)
    return None


def _compile_first() -> None:
    """Compile the engine's kernels before the server starts, if this version has not yet; Ctrl-C exits 130.

    Otherwise the lifespan's connect would compile them (about a minute on
    the 2-core station, once per version): uvicorn acts on a SIGTERM or
    Ctrl-C only after its startup ends, so a stop asked for meanwhile waited
    that long. Here nothing has started yet, and a signal ends the process
    at once.
    """
    from app.engine.warm import cold, warm

    if not cold(["sim"]):
        return
    print("cwrr serve: compiling the simulator and controllers for this version (once; about a minute "
          "on two cores) ...", file=sys.stderr, flush=True)
    # Ctrl-C exits from its handler: a KeyboardInterrupt raised where numba's
    # LLVM calls back through ctypes is printed and dropped ("Exception ignored
    # on calling ctypes callback"), and the compile then fails with exit 1
    # instead (seen once in CI). Nothing is open yet and numba writes each
    # cache file by rename, so leaving at once loses nothing.
    def _stop(signum: int, frame: object) -> None:
        print("cwrr serve: stopped while compiling", file=sys.stderr, flush=True)
        os._exit(130)

    previous = signal.signal(signal.SIGINT, _stop)
    try:
        took = warm(["sim"])
    finally:
        signal.signal(signal.SIGINT, previous)
    print(f"cwrr serve: compiled in {took['sim']:.0f} s", file=sys.stderr, flush=True)


def _backup(args: argparse.Namespace) -> int:
    """Back up the data folder (``cwrr backup OUT``)."""
    from app.api.settings import Settings
    from app.storage import backup_data_dir

    settings = Settings(**({"data_dir": args.data_dir} if args.data_dir else {}))
    res = backup_data_dir(settings.data_dir, args.out, settings.db_url)
    copied = res["runs"] is not None  # the SQLite store; a PostgreSQL database is pg_dump's
    print(strict_json(res) if args.json else
          f"cwrr backup: {res['out']}: the database {res['database']}"
          + (f" ({res['runs']} runs)" if copied else "")
          + f", and {res['files']} files ({res['bytes'] / 1e6:.1f} MB)"
          + (f"; a station started on it (--data-dir {res['out']}) has every run" if copied else ""))
    return 0


def _modbus_plant(args: argparse.Namespace) -> int:
    from app.engine.hardware.config import HardwareConfig, load_config
    from app.engine.hardware.modbus import serve_simulated_plant

    cfg = load_config(args.hardware) if args.hardware else HardwareConfig(backend="modbus")
    # `kill -USR1 PID` prints every thread's stack to stderr: a plant that stops answering can be
    # looked into without stopping it
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    server = serve_simulated_plant(cfg, host=args.host, port=args.port)
    print(f"cwrr modbus-plant: the simulated rotary rig on modbus://{server.host}:{server.port} "
          f"(register layout: app/engine/hardware/modbus.py); Ctrl-C stops", flush=True)
    try:
        # short sleeps: a Ctrl-C the kernel hands to one of the server's threads only sets Python's
        # flag, which the main thread reads when it next wakes (once, in a loaded parallel test run,
        # the plant did not stop within 20 s of its SIGINT; not reproduced since)
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0


def _diagnose(args: argparse.Namespace) -> int:
    """Diagnose the logs in ``args.logdir`` and print the verdict (issue 6)."""
    from app.engine.diagnosis.run import diagnose_dir
    from app.engine.params import EFFECT_MEANING

    bounds = {}
    for text in args.bound:
        name, eq, rng = text.partition("=")
        lo, colon, hi = rng.partition(":")
        try:
            if not (eq and colon):
                raise ValueError
            bounds[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise ValueError(f"--bound {text!r}: expected NAME=LO:HI, e.g. dead_volume_scale=0.9:1.1") from None
    if args.traces and not args.json_out:
        raise ValueError("--traces: the traces go into the report's JSON; give --json OUT.json too")
    # where the results go is checked before the diagnosis runs (a minute on ten minutes of logs)
    if args.json_out:
        writable_file("--json", args.json_out)
    if args.plots:
        writable_dir("--plots", args.plots)
    # on a terminal, one line kept up to date says where the diagnosis is
    live = sys.stderr.isatty()

    def progress(msg: str) -> None:
        print(f"\r\033[K{msg}…", end="", file=sys.stderr, flush=True)

    try:
        report = diagnose_dir(args.logdir, adapter=args.adapter, held_out=args.held_out, bounds=bounds,
                              traces=args.traces or bool(args.plots), candidates=args.effects,
                              progress=progress if live else None)
    finally:
        if live:
            print("\r\033[K", end="", file=sys.stderr, flush=True)
    if args.plots:
        from app.engine.diagnosis.plots import diagnosis_plots

        files = diagnosis_plots(report, args.plots)
        print(f"figures: {len(files)} in {args.plots} (how far, and each held-out log's prediction errors)")
    if not args.traces:  # drawn, not asked for in the JSON
        report.pop("traces", None)
        for r in report.get("reports", {}).values():
            r.pop("traces", None)
    if args.json_out:
        # strict JSON (a held parameter's SD is NaN): the report is read by other tools
        Path(args.json_out).write_text(strict_json(report, indent=1))
    for name, r in (report["reports"].items() if "reports" in report else [("", report)]):
        v = r["verdict"]
        print(f"{name + ': ' if name else ''}{v['summary']}"
              + (f" (confusable with {', '.join(v['confusable_with'])})" if v["confusable_with"] else "")
              + f"; E {r['how_far']['e_before']:.3g} → {r['how_far']['e_after']:.3g} "
              + (f"with {' + '.join(m)} " if (m := r["how_far"].get("model", v["effects"])) != v["effects"] else "")
              + f"(floor {r['how_far']['e_floor']:.3g})")
        if report.get("adapter") == "station":  # the plain words are the rotary rig's (a drive has no vane)
            for e in v["effects"]:
                print(f"  {e}: {EFFECT_MEANING[e]}")
        # where the baseline's error lies: each channel against its floor, and the held-out log most of it is in
        parts = []
        for w in r["where"]:
            logs = w.get("experiments", {})
            top = max(logs.items(), key=lambda kv: kv[1]["share"]) if len(logs) > 1 else None
            parts.append(f"{w['channel']} {w['rms']:.3g} (floor {w['floor']:.3g}"
                         + (f"; {100 * top[1]['share']:.0f} % in {top[0]})" if top else ")"))
        print("  baseline RMS: " + ", ".join(parts))
        recal = r["baseline"].get("recalibration") or {}
        if recal.get("note"):
            print(f"  recalibration: {recal['note']}")
        for title, rows in (("each candidate against the baseline (GC, its 90 % CI, ΔBIC):", r["ranking"]),
                            ("added one by one, each against the model with those above it:",
                             r.get("combination", []))):
            print("  " + title)
            for c in rows:
                lo, hi = c["gap_closure_ci90"]
                print(f"    {c['effect']:<20} GC {c['gap_closure']:7.3f} [{lo:.3f}, {hi:.3f}]  "
                      f"ΔBIC {c['delta_bic']:9.4g}  "
                      + ("significant" if c["significant"] else "no: " + "; ".join(c["not_significant_because"])))
        leak = r.get("leak_on_the_rig")
        if leak:
            tau = leak["tau_s"]
            print(f"  the leak on the rig: τ {tau:.0f} s" if tau >= 100.0 else f"  the leak on the rig: τ {tau:.3g} s",
                  f"closed at {leak['working_pressure_bar']:g} bar abs, the chamber would lose "
                  f"{leak['loss_bar']:.2g} bar in {leak['horizon_s']:g} s: {leak['on_the_rig']}", sep="; ")
        split = r["experiments"].get("split")
        if split:
            print(f"  held out: {', '.join(r['experiments']['held_out'])} ({split})")
        uneven = r["experiments"].get("irregular_sampling", {})
        if uneven:
            print("  sampled unevenly (replayed on their own clock, samples missing from a log not scored): "
                  + ", ".join(f"{n} ({u['irregular_intervals']} interval{'' if u['irregular_intervals'] == 1 else 's'}"
                              " off the median "
                              f"{1e3 * u['median_interval_s']:.3g} ms, "
                              f"the longest {1e3 * u['largest_interval_s']:.3g} ms)" for n, u in uneven.items()))
        flat = r["experiments"].get("flat_channels", {})
        if flat:
            print("  read one value throughout (fine where the quantity did not change, a clamped handle or an "
                  "ideal supply; a sensor reading nothing bends the fit to match it): "
                  + ", ".join(f"{n} ({', '.join(f'{c} = {v:g}' for c, v in chans.items())})"
                              for n, chans in flat.items()))
        unmeasured = r["experiments"].get("unmeasured_channels", {})
        if unmeasured:
            print("  not measured: " + ", ".join(f"{c} (reads {v:g} in every log)" for c, v in unmeasured.items())
                  + "; left out of every fit and of E")
        unscored = r["experiments"].get("unscored_channels", [])
        if unscored:
            print(f"  not scored: {', '.join(unscored)} (no held-out sample could be, e.g. a handle resting on an end "
                  "stop throughout); left out of every fit and of E")
    return 0


def _protocol(args: argparse.Namespace) -> int:
    """Run the diagnosis protocol on the simulated rig and write its logs (issue 6 §6)."""
    from app.engine.diagnosis.protocol import DESCRIPTION, VISIBLE, run_protocol
    from app.engine.diagnosis.suite import simulated_rig

    if not 0.0 <= args.param_error <= 0.5:
        raise ValueError(f"--param-error {args.param_error} is outside its allowed range [0, 0.5]")
    if not 0.2 <= args.scale <= 10.0:
        raise ValueError(f"--scale {args.scale} is outside its allowed range [0.2, 10]")
    effects: dict[str, int] = {}
    for spec in args.effect or []:
        name, _, mag = spec.partition(":")
        if mag not in ("", "1", "2"):
            raise ValueError(f"--effect {spec}: magnitude must be 1 (smaller) or 2 (larger)")
        effects[name] = int(mag or 1)
    try:
        rig = simulated_rig(args.seed, args.param_error, args.errors, effects)
    except ValueError as exc:
        raise ValueError(f"--effect: {exc}") from exc
    exps = run_protocol(rig, seed=args.seed, scale=args.scale, outdir=args.outdir)
    for kind in VISIBLE:
        print(f"{kind:15s} {DESCRIPTION[kind]}; shows {', '.join(VISIBLE[kind])}")
    print(f"{len(exps)} logs written to {args.outdir} (effects on the simulated rig: "
          f"{', '.join(rig.effects.active()) or 'none'})")
    if args.scale < 1.0:
        # said where the length is chosen, as the diagnosis page does: on a 0.3 × run with a vane leak
        # the recalibration took the dead volumes to 4.99 × nominal (the leak was still named)
        print(f"note: a protocol {args.scale:g} × as long pins the model's nominal values down less; the "
              "recalibration may take values far from nominal (the report flags them). 1 or more for a "
              "diagnosis to act on.")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``cwrr`` command line: one subcommand per job, each calling its function (``fn``)."""
    ap = argparse.ArgumentParser(prog="cwrr", description="CWRR lab station")
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sim", help="simulate a default isotonic workout, or one of the thesis's scenarios with one "
                                   "controller, faster than real time")
    s.add_argument("--scenario", choices=SIM_SCENARIOS, default="",
                   help="run this scenario (SPEC §5) and print its six metrics; without it, a default workout")
    s.add_argument("--controller", choices=SIM_CONTROLLERS, default=None, help="with --scenario (default: fuzzy)")
    s.add_argument("--target", type=float, default=None,
                   help="with --scenario: target torque [N·m], positive pronation (FP), negative supination "
                        "(FS); default 1.2")
    s.add_argument("--duration", type=float, default=None, help="default workout: simulated time [s] (60)")
    s.add_argument("--pw", type=float, default=3.0, help="working pressure [bar abs]")
    s.add_argument("--direction", choices=("FP", "FS"), default=None, help="default workout: direction (FP)")
    s.add_argument("--seed", type=seed_arg, default=0)
    s.add_argument("--log-dir", default="", help="write the run log (CSV + JSON) here")
    s.add_argument("--name", default="workout")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=_sim)
    b = sub.add_parser("bench", help="benchmarks")
    b.add_argument("which", choices=("perf", "thesis"))
    b.add_argument("--duration", type=float, default=60.0, help="perf: simulated workout length [s]")
    b.add_argument("--out", default="", help="thesis: output directory")
    b.add_argument("--seed", type=seed_arg, default=0, help="thesis: base seed of the sensor noise")
    b.add_argument("--no-plots", action="store_true", help="thesis: skip the figures")
    b.add_argument("--json", action="store_true")
    b.set_defaults(fn=_bench)
    i = sub.add_parser("identify", help="automated identification on the simulated rig (thesis 3.2.3–3.2.4)")
    i.add_argument("rig", choices=("rotary", "linear", "sweep", "seal", "dcv", "pid", "closedloop"),
                   help="dcv: CPR maps and flow-model fit of the directional valve (thesis 4.1); "
                        "pid: frequency-response autotune of a PRV loop (thesis 3.6.2); "
                        "closedloop: loaded friction validation with Table 4.3's PID gains (4.2.1, Table 4.4); "
                        "seal: fit pressure-dependent Coulomb + viscous friction to constant-speed strokes "
                        "(Zillen format: t ms, laser V, p V, F V, x mm, p bar gauge, F N)")
    i.add_argument("files", nargs="*", help="seal: data files")
    i.add_argument("--pw", type=float, default=3.0, help="rotary: working pressure P_w [bar abs], 1–8")
    i.add_argument("--pressures", default="1,2,3,4,5,6", help="sweep: working pressures [bar abs], comma-separated")
    i.add_argument("--cylinder", choices=("C1", "C2", "C3"), default="C3", help="linear: thesis cylinder")
    i.add_argument("--side", choices=("a", "b"), default="a", help="pid: which PRV loop")
    i.add_argument("--target", type=float, default=0.75, help="closedloop: target torque [N·m] (thesis 0.75, 1.5)")
    i.add_argument("--bandwidth", type=float, default=2.0, help="pid: target crossover [rad/s]")
    i.add_argument("--pm", type=float, default=60.0, help="pid: target phase margin [deg]")
    i.add_argument("--dcv-model", choices=("new", "iso"), default="iso",
                   help="dcv: the simulated valve (iso: ISO 6358 with underlaps; new: Eq 3.10–3.11 with known maps)")
    i.add_argument("--no-null-zone", action="store_true",
                   help="linear, dcv: simulate the plain ISO valve, without the null zone calibrated on "
                        "thesis 3.2.4's speeds (the default valve has it)")
    i.add_argument("--ns", type=int, default=100, help="static experiments per direction (>= 30)")
    i.add_argument("--nd", type=int, default=100, help="dynamic experiments per direction (>= 30)")
    i.add_argument("--seed", type=seed_arg, default=0)
    i.add_argument("--out", default="", help="write result.json (per-test data) and the friction plot here")
    i.add_argument("--table", default="", help="sweep: write the controllers' friction table (JSON) here; "
                   "closedloop: the table under test (default Table 4.2)")
    i.add_argument("--no-plots", action="store_true")
    i.add_argument("--progress", action="store_true", help="print 'experiment k of N' to stderr")
    i.add_argument("--json", action="store_true", help="print only the contract JSON")
    i.set_defaults(fn=_identify)
    g = sub.add_parser("diagnose", help="sim-to-real gap diagnosis of a directory of logs")
    g.add_argument("logdir", help="directory of logs (NAME.csv + NAME.json; or an adapter's files)")
    g.add_argument("--json", dest="json_out", default="", help="write the report here")
    g.add_argument("--adapter", choices=("auto", "station", "chamber_leak", "emps"), default="auto",
                   help="log format (auto: by the files found)")
    g.add_argument("--held-out", nargs="*", default=None,
                   help="experiment names to withhold from fitting (default, station logs: the last "
                        "repetition of every experiment run more than once; logs run once: a third of them, "
                        "only where the rest excite the same regimes; other adapters: the last third by "
                        "name; one experiment: its last 40 %%)")
    g.add_argument("--bound", action="append", default=[], metavar="NAME=LO:HI",
                   help="station logs: the recalibration's range for one baseline parameter, replacing the wide "
                        "default (e.g. dead_volume_scale=0.9:1.1 for measured dead volumes); repeatable; the "
                        "report lists every range under baseline.bounds")
    g.add_argument("--effects", nargs="+", default=None, metavar="EFFECT",
                   help="try only these candidate effects (default: all the logs' family has; station logs: "
                        "inertia vane_leakage external_leakage heat_transfer tube_dynamics presliding_friction "
                        "sensor_bias supply_droop valve_dynamics); the baseline's recalibration is the same")
    g.add_argument("--traces", action="store_true",
                   help="with --json: add each held-out log's measured and predicted channels over time "
                        "(traces: the baseline's and the verdict model's predictions, 300 block means per log)")
    g.add_argument("--plots", default="", metavar="DIR",
                   help="write the figures here: how far the gap shrinks per channel, and each held-out log's "
                        "prediction errors over time against the noise floor (PNG)")
    g.set_defaults(fn=_diagnose)
    q = sub.add_parser("protocol", help="run the diagnosis protocol on the simulated rig and write its logs")
    q.add_argument("outdir", help="directory for the logs (NAME.csv + NAME.json)")
    q.add_argument("--effect", nargs="*", default=None,
                   help="effects to switch on in the simulated rig, NAME or NAME:1|2 (magnitude)")
    q.add_argument("--param-error", type=float, default=0.0,
                   help="random error on the recalibratable nominal parameters, e.g. 0.2 for ±20 %%")
    q.add_argument("--errors", choices=("grouped", "each"), default="grouped",
                   help="one error per group the baseline recalibrates (all friction levels by one factor, "
                        "both PRV capacities by one), or one per parameter (default: grouped)")
    q.add_argument("--scale", type=float, default=1.0,
                   help="duration factor (1: ≈ 83 s of logs per repetition; under 1 the logs pin the model's "
                        "nominal values down less)")
    q.add_argument("--seed", type=seed_arg, default=0)
    q.set_defaults(fn=_protocol)
    v = sub.add_parser("serve", help="start the lab station server (on the simulated plant unless a hardware "
                       "configuration names the rig)")
    v.add_argument("--host", default=None, help="bind address (default: $CWRR_HOST, else 127.0.0.1; any other "
                   "than loopback needs a token, see CWRR_ADMIN_TOKEN)")
    v.add_argument("--port", type=int, default=None, help="HTTP port (default: $CWRR_PORT, else 8000)")
    v.add_argument("--viser-port", type=int, default=None,
                   help="port of the live plots, 0 for none (default: $CWRR_VISER_PORT, else 8080)")
    v.add_argument("--hardware", default="", help="YAML hardware configuration (default: $CWRR_HARDWARE, else the "
                   "simulator)")
    v.add_argument("--data-dir", default="", help="where run logs and the SQLite store live (default: "
                   "$CWRR_DATA_DIR, else ./data)")
    v.add_argument("--viser-public-url", default="", help="where browsers reach the live plots when that is not "
                   "this host's --viser-port, e.g. behind a port mapping (default: $CWRR_VISER_PUBLIC_URL)")
    v.set_defaults(fn=_serve)
    k = sub.add_parser("backup", help="copy the station's data folder (runs, logs, sessions) to a new folder, "
                       "consistently, also while the station runs")
    k.add_argument("out", help="the backup's folder (new, outside the data folder)")
    k.add_argument("--data-dir", default="", help="the station's data folder (default: $CWRR_DATA_DIR, else ./data)")
    k.add_argument("--json", action="store_true", help="print the summary as JSON")
    k.set_defaults(fn=_backup)
    mp = sub.add_parser("modbus-plant", help="serve the simulated rig over Modbus TCP (hardware-in-the-loop)")
    mp.add_argument("--host", default="127.0.0.1")
    mp.add_argument("--port", type=port_arg, default=5020)
    mp.add_argument("--hardware", default="", help="YAML hardware configuration (register layout and scaling)")
    mp.set_defaults(fn=_modbus_plant)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cwrr`` and ``python -m app``."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.fn(args))
    except ValueError as exc:  # includes ParameterError: the message names the parameter
        print(f"cwrr: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a path that cannot be read or written: its message names it
        print(f"cwrr {args.cmd}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C: a line, not a traceback from wherever the work was waiting
        print(f"cwrr {args.cmd}: stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
