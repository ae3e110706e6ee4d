"""Tokens and roles through the real app: bearer check, role matrix, hashed storage, bootstrap."""

from __future__ import annotations

from pathlib import Path

import pytest
import sqlalchemy as sa
from apps import ENGINEER, settings
from asgi import StartupFailedError, running

from server.app import create_app
from server.auth import hash_secret
from server.settings import Settings

PROBLEM = "application/problem+json"


async def test_requests_without_a_valid_token_are_401(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        cases = [({}, "missing Authorization"),
                 ({"Authorization": f"Basic {ENGINEER}"}, "'Basic'"),
                 ({"Authorization": "Bearer "}, "Bearer"),
                 ({"Authorization": "Bearer mvp_not-a-token"}, "unknown or revoked")]
        for headers, words in cases:
            r = await client.get("/api/v1/measurements", headers=headers)
            assert r.status_code == 401, headers
            assert r.headers["content-type"] == PROBLEM
            assert r.headers["www-authenticate"] == "Bearer"
            assert words in r.json()["detail"]
        # health and metrics are open (container probes, Prometheus)
        assert (await client.get("/api/v1/health/live")).status_code == 200
        assert (await client.get("/api/v1/metrics")).status_code == 200


async def test_role_matrix(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (admin, _):
        secrets = {}
        for role in ("read", "operator", "engineer"):
            r = await admin.post("/api/v1/tokens", json={"name": f"t-{role}", "role": role})
            assert r.status_code == 201
            secrets[role] = r.json()["token"]
        change = ("POST", "/api/v1/recipes/floor_panel/versions/1/activate")
        calls = [("GET", "/api/v1/measurements"), ("GET", "/api/v1/measurements/chain"),
                 ("GET", "/api/v1/recipes"), ("GET", "/api/v1/measurements/export"),
                 change, ("GET", "/api/v1/tokens")]
        expected = {  # read (MES) reads; changes and tokens need the engineer
            "read": [200, 200, 200, 200, 403, 403],
            "operator": [200, 200, 200, 200, 403, 403],
            "engineer": [200, 200, 200, 200, 200, 200],
        }
        for role, secret in secrets.items():
            got = []
            for method, url in calls:
                r = await admin.request(method, url, headers={"Authorization": f"Bearer {secret}"})
                got.append(r.status_code)
                if r.status_code == 403:
                    assert f"role {role!r}" in r.json()["detail"]
                    assert "'engineer'" in r.json()["detail"]
            assert got == expected[role], role


async def test_tokens_are_stored_hashed_shown_once_and_revocable(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (admin, state):
        r = await admin.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
        secret = r.json()["token"]
        assert secret.startswith("mvp_") and len(secret) > 40
        assert (await admin.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
                ).status_code == 409
        listing = (await admin.get("/api/v1/tokens")).text
        assert secret not in listing and "mes" in listing

        engine = state["services"].store.engine
        with engine.connect() as conn:
            dump = " ".join(str(v) for row in conn.execute(sa.text("SELECT * FROM tokens"))
                            for v in row)
        assert secret not in dump and ENGINEER not in dump
        assert hash_secret(secret) in dump and hash_secret(ENGINEER) in dump

        mes = {"Authorization": f"Bearer {secret}"}
        assert (await admin.get("/api/v1/measurements", headers=mes)).status_code == 200
        r = await admin.delete("/api/v1/tokens/mes")
        assert r.status_code == 200 and r.json()["revoked_at"] is not None
        r = await admin.get("/api/v1/measurements", headers=mes)
        assert r.status_code == 401 and "revoked" in r.json()["detail"]


async def test_bootstrap_token_comes_from_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # set after server.settings was imported: settings are read when built, not at import
    monkeypatch.setenv("MVPOSE_DATA_DIR", str(tmp_path / "envvar"))
    monkeypatch.setenv("MVPOSE_BOOTSTRAP_TOKEN", "first-bootstrap-secret-0001")
    monkeypatch.setenv("MVPOSE_IMAGES_OK_EVERY", "7")
    s = Settings()
    assert s.data_dir == tmp_path / "envvar" and s.images_ok_every == 7
    async with running(create_app(s), "first-bootstrap-secret-0001") as (client, _):
        r = await client.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
        assert r.status_code == 201
    assert (tmp_path / "envvar" / "mvpose.db").exists()

    # a new bootstrap secret replaces the old one at the next start
    monkeypatch.setenv("MVPOSE_BOOTSTRAP_TOKEN", "second-bootstrap-secret-002")
    async with running(create_app(Settings())) as (client, _):
        old = await client.get("/api/v1/tokens",
                               headers={"Authorization": "Bearer first-bootstrap-secret-0001"})
        new = await client.get("/api/v1/tokens",
                               headers={"Authorization": "Bearer second-bootstrap-secret-002"})
        assert old.status_code == 401 and new.status_code == 200
        assert [t["name"] for t in new.json()] == ["bootstrap", "mes"]


async def test_a_short_bootstrap_token_stops_start_up(tmp_path: Path) -> None:
    with pytest.raises(StartupFailedError, match="at least 16 characters"):
        async with running(create_app(settings(tmp_path, bootstrap_token="short"))):
            pass


def test_settings_refuse_unknown_database_urls(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mysql://x"):
        Settings(database_url="mysql://x")
    assert Settings(data_dir=tmp_path).resolved_database_url == f"sqlite:///{tmp_path}/mvpose.db"
