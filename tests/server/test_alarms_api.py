"""Alarms over REST on the real app and store: the standing list, history and filters, the
counts, one alarm with its transitions, and acknowledge by role with the acknowledging token's
name recorded."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

from apps import ENGINEER, settings
from asgi import running
from records import T0

from server.app import create_app


async def test_list_filter_acknowledge_and_history(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        tokens = {}
        for role in ("read", "operator"):
            r = await client.post("/api/v1/tokens", json={"name": f"shift-{role}", "role": role})
            assert r.status_code == 201, r.text
            tokens[role] = {"Authorization": f"Bearer {r.json()['token']}"}
        alarms = state["services"].store.alarms
        link, _ = alarms.raise_("link:modbus", "LINK_DOWN", "high", "link modbus is down",
                                {"link": "modbus"}, at=T0)
        cam, _ = alarms.raise_("camera:left1", "CAMERA_RECONNECTED", "low", "camera left1 "
                               "reconnected", at=T0 + timedelta(hours=1))
        alarms.clear("camera:left1", "CAMERA_RECONNECTED", at=T0 + timedelta(hours=1))

        r = await client.get("/api/v1/alarms", params={"standing": "true"},
                             headers=tokens["read"])
        assert r.status_code == 200, r.text
        items = r.json()["items"]
        assert [a["id"] for a in items] == [cam.id, link.id]
        assert items[1] | {"raised_at": None} == {
            "id": link.id, "station": "station1", "source": "link:modbus", "code": "LINK_DOWN",
            "priority": "high", "text": "link modbus is down", "text_key": "alarm.LINK_DOWN",
            "text_args": {"link": "modbus"}, "raised_at": None, "cleared_at": None,
            "acked_at": None, "acked_by": None, "active": True, "acknowledged": False}
        summary = (await client.get("/api/v1/alarms/summary", headers=tokens["read"])).json()
        assert summary == {"active": 1, "unacknowledged": 2, "highest": "high"}

        # a read token may not acknowledge; an operator may, and is named
        url = f"/api/v1/alarms/{cam.id}/acknowledge"
        assert (await client.post(url, headers=tokens["read"])).status_code == 403
        r = await client.post(url, headers=tokens["operator"])
        assert r.status_code == 200, r.text
        assert r.json()["acked_by"] == "shift-operator" and r.json()["acknowledged"]
        again = await client.post(url, headers={"Authorization": f"Bearer {ENGINEER}"})
        assert again.json()["acked_by"] == "shift-operator"  # the first is kept
        r = await client.get(f"/api/v1/alarms/{cam.id}", headers=tokens["read"])
        assert [(e["kind"], e["by"]) for e in r.json()["events"]] == [
            ("raised", None), ("cleared", None), ("acknowledged", "shift-operator")]

        # standing now: only the active link alarm; history keeps both
        standing = await client.get("/api/v1/alarms?standing=true", headers=tokens["read"])
        assert [a["id"] for a in standing.json()["items"]] == [link.id]
        history = await client.get("/api/v1/alarms", params={"active": "false"},
                                   headers=tokens["read"])
        assert [a["id"] for a in history.json()["items"]] == [cam.id]
        for params, want in (({"source": "link:"}, [link.id]), ({"priority": "low"}, [cam.id]),
                             ({"acknowledged": "true"}, [cam.id]),
                             ({"since": "2026-11-02T06:30:00Z"}, [cam.id]),
                             ({"until": (T0 + timedelta(minutes=1)).isoformat()}, [link.id])):
            got = await client.get("/api/v1/alarms", params=params, headers=tokens["read"])
            assert [a["id"] for a in got.json()["items"]] == want, (params, got.text)
        page = (await client.get("/api/v1/alarms?limit=1", headers=tokens["read"])).json()
        assert [a["id"] for a in page["items"]] == [cam.id]
        rest = await client.get("/api/v1/alarms", params={"before_id": page["next_before_id"]},
                                headers=tokens["read"])
        assert [a["id"] for a in rest.json()["items"]] == [link.id]

        # bad input: named, never a 500
        for params in ({"since": "yesterday"}, {"since": "2026-11-02T06:00:00"},
                       {"priority": "urgent"}, {"limit": "0"}):
            r = await client.get("/api/v1/alarms", params=params, headers=tokens["read"])
            assert r.status_code in (400, 422), (params, r.text)
        assert (await client.post("/api/v1/alarms/999999/acknowledge",
                                  headers=tokens["operator"])).status_code == 404
        assert (await client.get("/api/v1/alarms", headers={"Authorization": "Bearer mvp_x"})
                ).status_code == 401
