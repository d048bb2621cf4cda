"""Issue 7 item 6: who may drive the station — bind rule, tokens and roles, CORS, body limit, no secrets in logs."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from app.api.main import create_app
from app.api.settings import Settings
from app.cli import main as cli_main
from tests.conftest import free_port

ADMIN = "adm-" + "a1b2c3d4e5f6a7b8c9d0"
THERAPIST = "thr-" + "0f9e8d7c6b5a4f3e2d1c"
PUBLIC = {("GET", "/api/health"), ("POST", "/api/engine/estop"), ("GET", "/api/auth")}
THERAPIST_OK = {("POST", "/api/engine/connect"), ("POST", "/api/engine/disconnect"), ("POST", "/api/engine/start"),
                ("POST", "/api/engine/stop"), ("POST", "/api/engine/clear"), ("POST", "/api/sessions"),
                ("PATCH", "/api/sessions/{session_id}"), ("PATCH", "/api/runs/{run_id}")}


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture()
def secured(tmp_path: Path) -> Iterator[TestClient]:
    s = Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False, host="0.0.0.0",
                 admin_token=ADMIN, therapist_token=THERAPIST)  # type: ignore[arg-type]
    with TestClient(create_app(s)) as c:
        yield c


def _api_routes(c: TestClient) -> list[tuple[str, str]]:
    # from the OpenAPI document, so an endpoint added later is checked without editing this test
    paths = c.app.openapi()["paths"]  # type: ignore[attr-defined]
    return [(m.upper(), p) for p, ops in paths.items() if p.startswith("/api") for m in ops]


def _concrete(path: str) -> str:
    for name, value in (("{run_id}", "1"), ("{set_id}", "1"), ("{session_id}", "1"), ("{rig}", "rotary")):
        path = path.replace(name, value)
    return path


# ------------------------------------------------------------------ the bind rule


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.20", "::"])
def test_a_non_local_bind_without_tokens_refuses_to_start(host: str) -> None:
    with pytest.raises(ValidationError, match="without authentication"):
        Settings(host=host)


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost", "::1", "127.0.0.2", "::ffff:127.0.0.1"])
def test_loopback_binds_need_no_token(host: str) -> None:
    assert not Settings(host=host).auth_enabled


@pytest.mark.parametrize("kw, msg", [
    ({"admin_token": "short"}, "at least 16"),
    ({"admin_token": " " + ADMIN}, "surrounding spaces"),
    ({"admin_token": ADMIN, "therapist_token": ADMIN}, "must differ"),
    ({"cors_origins": ["*"]}, "any web page"),
    # refused before the server compiles for a minute, and the URL (it may hold a password) not echoed
    ({"database_url": "mysql://lab:s3cret-pw@db/cwrr"}, "database_url: scheme 'mysql' is not supported"),
])
def test_weak_settings_are_refused_without_echoing_the_secret(kw: dict[str, Any], msg: str) -> None:
    with pytest.raises(ValidationError, match=msg) as info:
        Settings(**kw)
    for v in kw.values():
        if isinstance(v, str):
            assert v.strip() not in str(info.value)


def test_cwrr_serve_on_all_interfaces_without_a_token_exits_with_the_reason(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CWRR_ADMIN_TOKEN", raising=False)
    monkeypatch.delenv("CWRR_THERAPIST_TOKEN", raising=False)
    assert cli_main(["serve", "--host", "0.0.0.0", "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert "without authentication" in err and "CWRR_ADMIN_TOKEN" in err


def test_cwrr_serve_with_a_database_or_rig_configuration_it_cannot_use_exits_before_compiling(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """It had compiled for a minute, then failed in the lifespan with a traceback."""
    from app import cli

    monkeypatch.setenv("CWRR_DATABASE_URL", "postgresql://lab:s3cret@127.0.0.1:1/cwrr")
    monkeypatch.setattr(cli, "_compile_first", lambda: pytest.fail("compiled before the database was checked"))
    assert cli_main(["serve", "--port", "1", "--viser-port", "0", "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the database at postgresql://lab:***@127.0.0.1:1/cwrr" in err and "s3cret" not in err
    monkeypatch.delenv("CWRR_DATABASE_URL")
    (tmp_path / "hw.yaml").write_text("backend: modbus\nrate_hz: 5\n")  # so is a wrong hardware configuration
    assert cli_main(["serve", "--port", "1", "--viser-port", "0", "--data-dir", str(tmp_path),
                     "--hardware", str(tmp_path / "hw.yaml")]) == 2
    assert "rate_hz: Input should be greater than or equal to 10" in capsys.readouterr().err


def test_cwrr_serve_takes_its_address_from_the_environment_unless_a_flag_names_it(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """CWRR_HOST, CWRR_PORT and CWRR_VISER_PORT are settings like the others; the flags' own defaults
    (127.0.0.1, 8000, 8080) had overridden them without a word."""
    import uvicorn

    served: list[tuple[str, int, int]] = []
    monkeypatch.setattr(uvicorn, "run", lambda app, host, port, log_level: served.append(
        (host, port, app.state.settings.viser_port)))
    monkeypatch.setenv("CWRR_AUTO_CONNECT", "false")  # nothing to compile or connect: only the address is looked at
    monkeypatch.setenv("CWRR_REALTIME", "false")
    monkeypatch.setenv("CWRR_DATA_DIR", str(tmp_path))
    for k in ("CWRR_ADMIN_TOKEN", "CWRR_THERAPIST_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("CWRR_HOST", "0.0.0.0")
    assert cli_main(["serve"]) == 2 and served == []  # the environment's all-interfaces bind, refused without a token
    assert "without authentication" in capsys.readouterr().err
    monkeypatch.setenv("CWRR_ADMIN_TOKEN", ADMIN)
    env_port, port, viser_port = free_port(), free_port(), free_port()  # serve checks that each is free
    monkeypatch.setenv("CWRR_PORT", str(env_port))
    monkeypatch.setenv("CWRR_VISER_PORT", "0")
    assert cli_main(["serve"]) == 0
    assert cli_main(["serve", "--host", "127.0.0.1", "--port", str(port), "--viser-port", str(viser_port)]) == 0
    assert served == [("0.0.0.0", env_port, 0), ("127.0.0.1", port, viser_port)]  # flags win
    # each start says in one line where the station answers, what it drives and where the runs go
    err = capsys.readouterr().err.splitlines()
    assert f"cwrr serve: the dashboard at http://<this station>:{env_port}/, the simulated rig (connected from " \
           f"the dashboard), runs kept in {tmp_path}/cwrr.sqlite3 (SQLite), tokens required; Ctrl-C stops it" in err
    assert f"cwrr serve: the dashboard at http://127.0.0.1:{port}/, the live plots at " \
           f"http://127.0.0.1:{viser_port}/, the simulated rig (connected from the dashboard), runs kept in " \
           f"{tmp_path}/cwrr.sqlite3 (SQLite), tokens required; Ctrl-C stops it" in err


def test_the_start_up_line_names_a_database_without_its_password() -> None:
    from app.api.settings import Settings
    from app.cli import serve_banner

    line = serve_banner(Settings(database_url="postgresql://lab:s3cret-pw@db.example:5432/cwrr", viser_port=0,
                                 hardware=""))
    assert "s3cret-pw" not in line and "runs kept in postgresql://lab:***@db.example:5432/cwrr" in line, line
    assert "live plots" not in line  # viser off


@pytest.mark.parametrize("flag", ["--port", "--viser-port"])
def test_cwrr_serve_on_a_port_in_use_exits_at_once_with_the_reason(
        flag: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A second server on a taken port had compiled, built its station, and left with uvicorn's bare
    "address already in use" (exit 3)."""
    import socket

    import uvicorn

    served: list[int] = []
    monkeypatch.setattr(uvicorn, "run", lambda app, host, port, log_level: served.append(port))
    monkeypatch.setenv("CWRR_AUTO_CONNECT", "false")
    monkeypatch.setenv("CWRR_REALTIME", "false")
    monkeypatch.setenv("CWRR_DATA_DIR", str(tmp_path))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        ports = {"--port": str(free_port()), "--viser-port": str(free_port())} | {flag: str(busy)}
        assert cli_main(["serve", *[x for kv in ports.items() for x in kv]]) == 2
    err = capsys.readouterr().err
    assert f"{flag} {busy}: cannot listen on 127.0.0.1:{busy}" in err and "another cwrr serve" in err, err
    assert served == []
    # once the port is free again, the same command serves
    assert cli_main(["serve", *[x for kv in ports.items() for x in kv]]) == 0 and served == [int(ports["--port"])]


def test_cwrr_serve_on_a_data_folder_another_station_holds_exits_at_once_with_the_reason(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Two stations on one folder would each mark the other's running run interrupted, cut back its
    log as a dead one, and on a rig's configuration both drive it."""
    import subprocess
    import sys

    import uvicorn

    served: list[int] = []
    monkeypatch.setattr(uvicorn, "run", lambda app, host, port, log_level: served.append(port))
    monkeypatch.setenv("CWRR_AUTO_CONNECT", "false")
    monkeypatch.setenv("CWRR_REALTIME", "false")
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from app.storage import claim_data_dir; "
                               "claim_data_dir(sys.argv[1]); print('held', flush=True); time.sleep(60)",
                               str(tmp_path)], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parents[1])
    argv = ["serve", "--port", str(free_port()), "--viser-port", "0", "--data-dir", str(tmp_path)]
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert cli_main(argv) == 2 and served == []
        err = capsys.readouterr().err
        assert f"in use by another station (pid {holder.pid})" in err and "CWRR_DATA_DIR" in err, err
    finally:
        holder.kill()
        holder.wait(10)
    assert cli_main(argv) == 0 and len(served) == 1


def test_cwrr_serve_refuses_a_bad_public_url_flag_with_the_reason(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["serve", "--port", "1", "--viser-public-url", "ftp://station:9080"]) == 2
    err = capsys.readouterr().err
    assert "viser_public_url" in err and "http://host:port" in err


def test_tokens_come_from_the_environment_and_never_show_in_repr(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CWRR_ADMIN_TOKEN", ADMIN)
    s = Settings(host="0.0.0.0")
    assert s.auth_enabled and s.admin_token is not None and s.admin_token.get_secret_value() == ADMIN
    assert ADMIN not in repr(s) and ADMIN not in str(s.model_dump())


# ------------------------------------------------------------------ tokens and roles


def test_every_api_endpoint_but_health_estop_and_auth_refuses_a_caller_without_a_token(
        secured: TestClient) -> None:
    routes = _api_routes(secured)
    assert len(routes) > 20
    for method, path in routes:
        r = secured.request(method, _concrete(path), json={})
        if (method, path) in PUBLIC:
            assert r.status_code == 200, (method, path, r.text)
        else:
            assert r.status_code == 401, (method, path, r.status_code)
            assert r.headers.get("www-authenticate") == "Bearer"
            assert "Bearer" in r.json()["detail"]
        # a wrong token is no token
        if (method, path) not in PUBLIC:
            wrong = _bearer(ADMIN[:-1] + "x")
            assert secured.request(method, _concrete(path), json={}, headers=wrong).status_code == 401


def test_the_openapi_document_declares_the_tokens_so_docs_can_send_one(secured: TestClient, tmp_path: Path) -> None:
    """/docs had no Authorize button on a station with tokens (no security scheme in the document): a
    researcher's "Try it out" got 401 with no way to sign in, and a generated client had no token
    parameter. The bearer scheme is declared, on exactly the operations that refuse a caller without one."""
    spec = secured.app.openapi()  # type: ignore[attr-defined]
    scheme = spec["components"]["securitySchemes"]["token"]
    assert scheme["type"] == "http" and scheme["scheme"] == "bearer"
    assert "CWRR_ADMIN_TOKEN" in scheme["description"]
    declared = {(m.upper(), p) for p, ops in spec["paths"].items() for m, op in ops.items()
                if {"token": []} in op.get("security", [])}
    assert declared == set(_api_routes(secured)) - PUBLIC
    # declared, not enforced twice: a header that is not a bearer token gets the station's own answer
    r = secured.get("/api/engine", headers={"Authorization": "Basic eDp5"})
    assert r.status_code == 401 and "Bearer" in r.json()["detail"]
    # a station without tokens serves its own machine and checks none: its document asks for none
    local = create_app(Settings(data_dir=str(tmp_path / "local"), viser_port=0, auto_connect=False)).openapi()
    assert "securitySchemes" not in local.get("components", {})
    assert not [p for p, ops in local["paths"].items() for op in ops.values() if "security" in op]


def test_a_refused_motion_command_moves_nothing(secured: TestClient) -> None:
    a = _bearer(ADMIN)
    assert secured.post("/api/engine/connect", headers=a).json()["state"] == "idle"
    assert secured.post("/api/engine/start", json={}).status_code == 401
    assert secured.get("/api/engine", headers=a).json()["state"] == "idle"
    assert secured.get("/api/runs", headers=a).json() == []


def test_a_therapist_runs_exercises_but_only_an_admin_identifies_tunes_and_stores_parameters(
        secured: TestClient) -> None:
    t, a = _bearer(THERAPIST), _bearer(ADMIN)
    for method, path in _api_routes(secured):
        if method not in ("POST", "PATCH") or (method, path) in PUBLIC or path == "/api/forms/{rig}":
            continue
        r = secured.request(method, _concrete(path), json={}, headers=t)
        if (method, path) in THERAPIST_OK:
            assert r.status_code != 403, (path, r.text)
        else:
            assert r.status_code == 403 and "admin role" in r.json()["detail"], (path, r.status_code)
    # and reading is open to both, the diagnosis protocol's table too (a stored report's plain words)
    for h in (t, a):
        assert secured.get("/api/runs", headers=h).status_code == 200
        assert secured.get("/api/diagnoses/protocol", headers=h).status_code == 200
        assert secured.post("/api/forms/rotary", json={"values": {}}, headers=h).status_code == 200
    assert secured.get("/api/auth", headers=t).json() == {"required": True, "role": "therapist"}
    assert secured.get("/api/auth", headers=a).json() == {"required": True, "role": "admin"}
    assert secured.get("/api/auth").json() == {"required": True, "role": None}


def test_a_therapist_token_drives_a_workout_end_to_end(secured: TestClient) -> None:
    t = _bearer(THERAPIST)
    assert secured.post("/api/engine/connect", headers=t).json()["state"] == "idle"
    r = secured.post("/api/engine/start", json={"scenario": "SC-1"}, headers=t)
    assert r.status_code == 200, r.text
    assert r.json()["status"]["state"] == "running"
    assert secured.post("/api/engine/stop", headers=t).json()["state"] == "idle"


def test_the_emergency_stop_needs_no_token(secured: TestClient) -> None:
    secured.post("/api/engine/connect", headers=_bearer(ADMIN))
    r = secured.post("/api/engine/estop")
    assert r.status_code == 200 and r.json()["state"] == "fault"
    assert r.json()["safety"]["fault"]["code"] == "estop"


def test_without_tokens_a_remote_caller_is_refused_even_if_the_server_was_started_by_hand(
        tmp_path: Path) -> None:
    # uvicorn started directly on 0.0.0.0 bypasses Settings' bind rule; the requests themselves are checked
    app = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False))
    with TestClient(app, client=("10.1.2.3", 40000)) as remote:
        assert remote.get("/api/engine").status_code == 403
        assert "this machine only" in remote.post("/api/engine/connect").json()["detail"]
        assert remote.get("/api/health").status_code == 200
        assert remote.get("/api/auth").json() == {"required": False, "role": None}
    with TestClient(app, client=("127.0.0.1", 40000)) as local:
        assert local.get("/api/engine").status_code == 200
        assert local.get("/api/auth").json() == {"required": False, "role": "admin"}


# ------------------------------------------------------------------ CORS, body size, logs


def test_cors_is_closed_by_default_and_open_only_to_configured_origins(tmp_path: Path) -> None:
    origin = {"Origin": "http://evil.example", "Access-Control-Request-Method": "POST"}
    with TestClient(create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False))) as c:
        assert "access-control-allow-origin" not in c.get("/api/health", headers=origin).headers
        assert "access-control-allow-origin" not in c.options("/api/engine/start", headers=origin).headers
    s = Settings(data_dir=str(tmp_path / "b"), viser_port=0, auto_connect=False, cors_origins=["http://lab.example"])
    with TestClient(create_app(s)) as c:
        ok = {"Origin": "http://lab.example", "Access-Control-Request-Method": "POST"}
        assert c.options("/api/engine/start", headers=ok).headers["access-control-allow-origin"] == "http://lab.example"
        assert "access-control-allow-origin" not in c.options("/api/engine/start", headers=origin).headers


def test_an_oversized_body_gets_413_and_stores_nothing(tmp_path: Path) -> None:
    s = Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False, max_body_bytes=4096)
    with TestClient(create_app(s)) as c:
        big = {"kind": "gains", "name": "x", "values": {}, "pad": "z" * 10_000}
        r = c.post("/api/params", json=big)
        assert r.status_code == 413 and "4096" in r.json()["detail"]
        # a chunked body declares no length; it is counted as it arrives
        r = c.post("/api/sessions", content=iter([b'{"person": "p1", "notes": "', b"n" * 8000, b'"}']),
                   headers={"content-type": "application/json"})
        assert r.status_code == 413
        assert c.get("/api/params").json() == [] and c.get("/api/sessions").json() == []
        assert c.post("/api/sessions", json={"person": "p1"}).status_code == 201


def test_tokens_never_reach_a_log(secured: TestClient, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    secured.get("/api/engine", headers=_bearer(ADMIN))
    secured.post("/api/engine/connect", headers=_bearer(THERAPIST))
    secured.get("/api/engine", headers=_bearer("wrong-token-0123456789"))
    text = caplog.text + repr(secured.app.state.settings)  # type: ignore[attr-defined]
    assert ADMIN not in text and THERAPIST not in text
