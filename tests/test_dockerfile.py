"""Issue 5: the Dockerfile's install steps work in a fresh virtual environment.

No Docker engine runs here, so the image is not built. Instead this replays
the Dockerfile itself: its COPY steps into a scratch folder, its ``pip
install`` steps into a new venv (Python 3.11, as the base image), then its
CMD with the ENV it sets, and finally its HEALTHCHECK command against that
server. ``--no-cache-dir`` is dropped so pip may reuse this machine's wheel
cache, and ``--no-compile`` added, as the installed modules' bytecode is no
part of what is checked (the test took 53 CPU-s with it, 59 without, on the
fiftieth session's VM); resolution and installation are otherwise the image's.
"""

from __future__ import annotations

import os
import shlex
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow


def _instructions() -> list[tuple[str, str]]:
    out = []
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, arg = line.partition(" ")
            out.append((op.upper(), arg.strip()))
    return out


def user_of(ins: list[tuple[str, str]]) -> str:
    """The last USER instruction's argument."""
    return [a for op, a in ins if op == "USER"][-1]


def test_the_dockerfile_promises_what_the_issue_asks() -> None:
    ins = _instructions()
    ops = {op for op, _ in ins}
    assert dict(ins)["FROM"].startswith("python:3.11-slim")
    user = [a for op, a in ins if op == "USER"]
    assert user and user[-1] not in ("root", "0")  # runs as a non-root user
    assert any(op == "VOLUME" and "/data" in a for op, a in ins)
    assert {"HEALTHCHECK", "EXPOSE", "CMD"} <= ops
    exposed = " ".join(a for op, a in ins if op == "EXPOSE").split()
    assert "8000" in exposed and "8080" in exposed  # the API and the viser port
    cmd = [a for op, a in ins if op == "CMD"][-1]
    assert '"cwrr", "serve"' in cmd and '"--viser-port", "8080"' in cmd
    # the tested versions, not the newest the day it is built
    pip = [a for op, a in ins if op == "RUN" and a.startswith("pip install")]
    assert pip and all("-c constraints.txt" in a for a in pip), pip


def test_every_dependency_is_pinned_to_a_version_its_range_admits() -> None:
    """``constraints.txt`` (what ./dev, CI and the image install) pins each requirement of
    ``pyproject.toml``, the test extras' included, inside the range the project declares."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not NAME==VERSION"
            pins[canonicalize_name(name)] = version.strip()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in project["dependencies"] + project["optional-dependencies"]["test"]]
    for req in reqs:
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not pinned in constraints.txt"
        assert req.specifier.contains(pins[name], prereleases=True), (str(req), pins[name])
    assert pins["numpy"] and pins["viser"] and pins["websockets"]


def test_the_install_steps_work_in_a_fresh_venv(tmp_path: Path) -> None:
    import json

    from app.engine.warm import PARTS

    ins = _instructions()
    work = tmp_path / "image"
    work.mkdir()
    env_vars: dict[str, str] = {}
    for op, arg in ins:
        if op == "COPY":  # Docker's rules: a folder's contents go to dest; files go into dest/ or become dest
            *srcs, dest = shlex.split(arg)
            dst = work / dest
            for src in srcs:
                path = ROOT / src
                if path.is_dir():
                    shutil.copytree(path, dst, dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__"))
                elif dest.endswith("/") or len(srcs) > 1:
                    dst.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(path, dst / path.name)
                else:
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(path, dst)
        elif op == "ENV":
            for kv in shlex.split(arg):
                k, _, v = kv.partition("=")
                env_vars[k] = v
    assert (work / "pyproject.toml").is_file() and (work / "app" / "cli.py").is_file()
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip_steps = [a for op, a in ins if op == "RUN" and a.startswith("pip install")]
    assert pip_steps, "the Dockerfile installs the project with pip"
    for step in pip_steps:
        argv = [a for a in shlex.split(step) if a != "--no-cache-dir"]
        r = subprocess.run([str(venv / "bin" / "pip"), *argv[1:2], "--no-compile", *argv[2:]], cwd=work,
                           capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr[-3000:]
    env = {**os.environ, **env_vars, "CWRR_DATA_DIR": str(tmp_path / "data"), "NUMBA_CACHE_DIR": str(tmp_path / "nb"),
           "PATH": f"{venv / 'bin'}:{os.environ.get('PATH', '')}"}
    env.pop("PYTHONPATH", None)  # the installed package, not this checkout
    # the build compiles the numba kernels into the image's cache, as the user the container runs as
    warm_steps = [a for op, a in ins if op == "RUN" and a.startswith("python -m app.engine.warm")]
    assert warm_steps and ins.index(("RUN", warm_steps[0])) > ins.index(("USER", user_of(ins)))
    for step in warm_steps:
        argv = shlex.split(step)[1:]
        # the build compiles its parts side by side. Here only the simulator's, which the CMD's
        # health check needs: beside this test another one may pace a station, and in one CI run,
        # with both parts compiling here, that station's loop stalled past its watchdog (1 s). The
        # replay's part runs in every `./dev test` before the tests and in tests/test_engine.py
        parts = [p for p in argv[2:] or list(PARTS) if p == "sim"]
        assert parts, argv
        for part in parts:
            r = subprocess.run([str(venv / "bin" / "python"), *argv[:2], part], cwd=tmp_path, env=env,
                               capture_output=True, text=True, timeout=900)
            assert r.returncode == 0 and f"compiled: {part}" in r.stdout, r.stderr[-3000:]
    cached = {p.name.split(".")[0] for p in (tmp_path / "nb").rglob("*.nbi")}
    assert {"sim", "plant", "pipeline"} <= cached, cached  # the simulator's and the controllers' kernels

    # the image's CMD with its ENV (the /data volume becomes a scratch folder), then its HEALTHCHECK
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    cmd = json.loads([a for op, a in ins if op == "CMD"][-1])
    assert cmd[:2] == ["cwrr", "serve"]
    # the CMD as written (it binds all interfaces), on a free port and without viser
    argv = [str(venv / "bin" / "cwrr"), *cmd[1:]]
    argv[argv.index("--port") + 1] = str(port)
    argv[argv.index("--viser-port") + 1] = "0"
    assert argv[argv.index("--host") + 1] == "0.0.0.0"
    for k in ("CWRR_ADMIN_TOKEN", "CWRR_THERAPIST_TOKEN"):
        env.pop(k, None)
    # a container without a token must not open the rig to the network: it exits and says why
    refused = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and "CWRR_ADMIN_TOKEN" in refused.stderr
    env["CWRR_ADMIN_TOKEN"] = "docker-test-token-" + "0123456789"
    server = subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        health = [a for op, a in ins if op == "HEALTHCHECK"][-1]
        check = health.split(" CMD ", 1)[1].replace("127.0.0.1:8000", f"127.0.0.1:{port}")
        deadline = time.monotonic() + 180
        ok = False
        while time.monotonic() < deadline and server.poll() is None:
            probe = subprocess.run(check.replace("python ", f"{venv / 'bin' / 'python'} ", 1), shell=True, env=env,
                                   capture_output=True, timeout=10)
            if probe.returncode == 0:
                ok = True
                break
            time.sleep(1.0)
        assert ok, (server.stdout.read().decode() if server.poll() is not None and server.stdout else "no answer")
        mod = subprocess.run([str(venv / "bin" / "python"), "-c", "import app; print(app.__file__)"], env=env,
                             cwd=tmp_path, capture_output=True, text=True, check=True).stdout
        assert str(venv) in mod  # served from the installed package
        # the dashboard's pages and every file they load come with the package (its package data)
        import urllib.request

        for url in ("/", "/static/diagnosis.html", "/static/station.css", "/static/station.js",
                    "/static/dashboard.js", "/static/diagnosis.js", "/static/favicon.svg",
                    "/docs", "/static-docs/swagger-ui-bundle.js"):  # the API's reference, offline too
            with urllib.request.urlopen(f"http://127.0.0.1:{port}{url}", timeout=10) as r:
                assert r.status == 200 and r.read(), url
    finally:
        server.terminate()
        server.wait(30)
