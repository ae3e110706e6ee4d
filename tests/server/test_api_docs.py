"""Runs every curl example of docs/rest-api.md (and docs/users.md) against a real app and checks
status and keys."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path
from typing import Any

from apps import ENGINEER, ROOT, record_some, settings
from asgi import running

from mvpose_core.reasons import Reason
from server.app import create_app

DOC = ROOT / "docs" / "rest-api.md"
BLOCK = re.compile(r"```(sh|json)\n(.*?)```", re.S)


def examples(doc: Path = DOC) -> list[tuple[int, list[str], Any]]:
    """(expected status, curl argv, documented response or None) per curl line, in order."""
    out: list[tuple[int, list[str], Any]] = []
    for kind, text in BLOCK.findall(doc.read_text()):
        if kind == "json":
            assert out, "a response example before any request"
            status, argv, _ = out[-1]
            out[-1] = (status, argv, json.loads(text))
            continue
        expected = None
        for line in text.replace("\\\n", " ").splitlines():
            line = line.strip()
            if m := re.fullmatch(r"# expect (\d{3})", line):
                expected = int(m.group(1))
            elif line.startswith("curl "):
                assert expected is not None, f"no '# expect' before {line!r}"
                out.append((expected, shlex.split(line)[1:], None))
                expected = None
    return out


def request_of(argv: list[str], env: dict[str, str]) -> tuple[str, str, dict[str, str], str | None]:
    """Method, URL, headers and body of a curl command line, with $VARIABLES from ``env``."""

    def sub(text: str) -> str:
        for k, v in env.items():
            text = text.replace(f"${k}", v)
        return text

    method, headers, data, url = None, {}, None, None
    it = iter(argv)
    for arg in it:
        if arg == "-X":
            method = next(it)
        elif arg == "-H":
            key, _, value = sub(next(it)).partition(": ")
            headers[key] = value
        elif arg in ("-d", "--data"):
            data = next(it)
        elif arg == "-o":
            next(it)  # the output file does not matter here
        elif arg != "-s":
            url = sub(arg)
    assert url is not None, argv
    return method or ("POST" if data else "GET"), url, headers, data


def assert_keys(doc: Any, real: Any, where: str = "") -> None:
    """Every key the documentation shows exists in the real response (recursively)."""
    if isinstance(doc, dict):
        assert isinstance(real, dict), f"{where}: documented an object, got {real!r}"[:200]
        missing = set(doc) - set(real)
        assert not missing, f"{where}: documented keys {sorted(missing)} not in the response"
        for k, v in doc.items():
            if real[k] is not None:
                assert_keys(v, real[k], f"{where}.{k}")
    elif isinstance(doc, list) and doc and real:
        assert isinstance(real, list), f"{where}: documented a list"
        assert_keys(doc[0], real[0], f"{where}[0]")


async def test_every_documented_example_runs(tmp_path: Path) -> None:
    cases = examples()
    assert len(cases) >= 20
    async with running(create_app(settings(tmp_path))) as (client, state):  # no default token
        await record_some(state["services"], [Reason.OK, Reason.MARKS_MISSING,
                                              Reason.OK])
        r = await client.post("/api/v1/tokens", json={"name": "mes", "role": "read"},
                              headers={"Authorization": f"Bearer {ENGINEER}"})
        env = {"MVPOSE": "http://station", "ENGINEER_TOKEN": ENGINEER,
               "MES_TOKEN": r.json()["token"]}
        for expected, argv, documented in cases:
            method, url, headers, data = request_of(argv, env)
            r = await client.request(method, url, headers=headers,
                                     content=data.encode() if data else None)
            assert r.status_code == expected, (method, url, r.text[:300])
            if documented is not None:
                assert_keys(documented, r.json(), url)


async def test_every_example_of_the_users_page_runs(tmp_path: Path) -> None:
    cases = examples(ROOT / "docs" / "users.md")
    assert len(cases) >= 9
    async with running(create_app(settings(tmp_path))) as (client, _):
        env = {"MVPOSE": "http://station", "ENGINEER_TOKEN": ENGINEER}
        for expected, argv, documented in cases:
            method, url, headers, data = request_of(argv, env)
            r = await client.request(method, url, headers=headers,
                                     content=data.encode() if data else None)
            assert r.status_code == expected, (method, url, r.text[:300])
            if documented is not None:
                assert_keys(documented, r.json(), url)
