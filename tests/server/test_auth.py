"""Tokens and roles through the real app: bearer check, role matrix, hashed storage, bootstrap."""

from __future__ import annotations

import logging
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
        change = ("POST", "/api/v1/recipes/floor_panel/versions/1/activate", None)
        calls = [("GET", "/api/v1/measurements", None), ("GET", "/api/v1/measurements/chain", None),
                 ("GET", "/api/v1/recipes", None), ("GET", "/api/v1/measurements/export", None),
                 change, ("GET", "/api/v1/tokens", None),
                 # the station's operations: without a station process they answer 503 once the
                 # role is allowed (403 before that)
                 ("POST", "/api/v1/station/trigger", {"part_id": "P1"}),
                 ("POST", "/api/v1/station/teach", {}),
                 ("POST", "/api/v1/station/recipe", {"name": "floor_panel"})]
        expected = {  # read (MES) reads; operators trigger and teach; changes need the engineer
            "read": [200, 200, 200, 200, 403, 403, 403, 403, 403],
            "operator": [200, 200, 200, 200, 403, 403, 503, 503, 503],
            "engineer": [200, 200, 200, 200, 200, 200, 503, 503, 503],
        }
        for role, secret in secrets.items():
            got = []
            for method, url, body in calls:
                r = await admin.request(method, url, json=body,
                                        headers={"Authorization": f"Bearer {secret}"})
                got.append(r.status_code)
                if r.status_code == 403:
                    needed = "'operator'" if "/station/" in url else "'engineer'"
                    assert f"role {role!r}" in r.json()["detail"]
                    assert needed in r.json()["detail"], r.json()["detail"]
                if r.status_code == 503:
                    assert "without a station process" in r.json()["detail"]
            assert got == expected[role], role


async def test_activating_a_recipe_version_through_the_station_needs_the_engineer(
    tmp_path: Path,
) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (admin, _):
        secrets = {}
        for role in ("operator", "engineer"):
            r = await admin.post("/api/v1/tokens", json={"name": f"t-{role}", "role": role})
            secrets[role] = r.json()["token"]

        async def select(role: str, body: dict[str, object]) -> tuple[int, str]:
            r = await admin.post("/api/v1/station/recipe", json=body,
                                 headers={"Authorization": f"Bearer {secrets[role]}"})
            return r.status_code, r.json()["detail"]

        # an operator selects among the active recipes (503 here: no station process) ...
        code, _detail = await select("operator", {"name": "floor_panel"})
        assert code == 503
        # ... but activating a stored version is the engineer's, as under /recipes
        code, detail = await select("operator", {"name": "floor_panel", "version": 1})
        assert code == 403
        assert "role 'operator'" in detail and "'engineer'" in detail
        code, detail = await select("engineer", {"name": "floor_panel", "version": 1})
        assert code == 503 and "without a station process" in detail


async def test_a_401_never_echoes_what_was_sent(tmp_path: Path) -> None:
    secret = "mvp_0123456789abcdefghijklmnopqrstuvwxyzABCDEFG"
    async with running(create_app(settings(tmp_path))) as (client, _):
        for value in (secret, f"{secret} trailing", f"Token{secret}", f"Bearer{secret}",
                      f"Basic {secret}"):
            r = await client.get("/api/v1/measurements", headers={"Authorization": value})
            assert r.status_code == 401, value
            shown = r.text + " ".join(f"{k}: {v}" for k, v in r.headers.items())
            for k in range(len(secret) - 4):  # not even a piece of it
                assert secret[k:k + 5] not in shown, (value, shown)
            assert "Bearer <token>" in r.json()["detail"]
        r = await client.get("/api/v1/measurements", headers={"Authorization": secret})
        assert "without the Bearer scheme" in r.json()["detail"]


async def test_the_last_engineer_token_cannot_be_revoked(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (admin, _):
        r = await admin.delete("/api/v1/tokens/bootstrap")
        assert r.status_code == 409 and r.headers["content-type"] == PROBLEM
        assert "last live engineer token" in r.json()["detail"]
        assert "create another engineer token" in r.json()["detail"]
        assert (await admin.get("/api/v1/tokens")).status_code == 200  # still in

        second = (await admin.post("/api/v1/tokens", json={"name": "eng2", "role": "engineer"})
                  ).json()["token"]
        reader = await admin.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
        assert reader.status_code == 201
        assert (await admin.delete("/api/v1/tokens/bootstrap")).status_code == 200
        eng2 = {"Authorization": f"Bearer {second}"}
        r = await admin.delete("/api/v1/tokens/eng2", headers=eng2)
        assert r.status_code == 409, r.text  # read tokens do not count
        assert (await admin.delete("/api/v1/tokens/mes", headers=eng2)).status_code == 200
        r = await admin.delete("/api/v1/tokens/bootstrap", headers=eng2)
        assert r.status_code == 404 and "no live token named 'bootstrap'" in r.json()["detail"]


async def test_a_revoked_token_name_can_be_used_again(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (admin, _):
        old = (await admin.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
               ).json()["token"]
        r = await admin.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
        assert r.status_code == 409 and "live token named 'mes'" in r.json()["detail"]
        assert (await admin.delete("/api/v1/tokens/mes")).status_code == 200
        r = await admin.post("/api/v1/tokens", json={"name": "mes", "role": "operator"})
        assert r.status_code == 201, r.text
        new = r.json()["token"]
        assert r.json()["info"]["revoked_at"] is None and r.json()["info"]["role"] == "operator"
        r = await admin.get("/api/v1/measurements", headers={"Authorization": f"Bearer {old}"})
        assert r.status_code == 401  # the old secret stays refused
        r = await admin.get("/api/v1/measurements", headers={"Authorization": f"Bearer {new}"})
        assert r.status_code == 200
        listing = (await admin.get("/api/v1/tokens")).json()
        assert [(t["name"], t["role"]) for t in listing] == [("bootstrap", "engineer"),
                                                             ("mes", "operator")]


async def test_start_up_without_any_engineer_token_warns_how_to_make_one(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="server.auth"):
        async with running(create_app(settings(tmp_path, bootstrap_token=None))):
            pass
    (warning,) = [r.getMessage() for r in caplog.records if r.name == "server.auth"]
    assert "MVPOSE_BOOTSTRAP_TOKEN is not set" in warning
    assert "mvpose token create NAME --role engineer" in warning
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="server.auth"):
        async with running(create_app(settings(tmp_path))):  # with the bootstrap token: quiet
            pass
        async with running(create_app(settings(tmp_path, bootstrap_token=None))):
            pass  # the bootstrap token made then is still there: nothing to warn about
    assert [r for r in caplog.records if r.name == "server.auth"] == []


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
