"""The first start from the command line: `mvpose token`, and start-up errors as one line."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from apps import ROOT, STATION1, settings
from asgi import running

from server.app import create_app
from server.cli import main


def test_token_create_list_revoke_on_the_servers_store(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    data = tmp_path / "var"
    assert main(["token", "create", "first", "--role", "engineer", "--data-dir", str(data)]) == 0
    out, err = capsys.readouterr()
    engineer = out.strip()  # the secret alone on stdout
    assert engineer.startswith("mvp_") and len(engineer) > 40
    assert "'first' (engineer) created" in err and "shown only now" in err

    monkeypatch.setenv("MVPOSE_DATA_DIR", str(data))  # the same store, found as the server does
    assert main(["token", "create", "mes", "--role", "read"]) == 0
    reader = capsys.readouterr().out.strip()
    assert main(["token", "list"]) == 0
    listing = capsys.readouterr().out
    assert engineer not in listing and reader not in listing
    assert [line.split()[:2] for line in listing.splitlines()] == [
        ["name", "role"], ["first", "engineer"], ["mes", "read"]]

    assert main(["token", "revoke", "first"]) == 1  # the last engineer
    assert "last live engineer token" in capsys.readouterr().err
    assert main(["token", "create", "a b", "--role", "read"]) == 2
    assert "token name 'a b'" in capsys.readouterr().err
    assert main(["token", "revoke", "mes"]) == 0
    assert "'mes' (read) revoked at" in capsys.readouterr().err
    assert main(["token", "revoke", "mes"]) == 1
    assert "no live token named 'mes'" in capsys.readouterr().err


async def test_a_token_from_the_command_line_opens_the_api(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "var"
    assert main(["token", "create", "first", "--role", "engineer", "--data-dir", str(data),
                 "--station", str(STATION1)]) == 0
    secret = capsys.readouterr().out.strip()
    app = create_app(settings(tmp_path, bootstrap_token=None))  # the same data dir, no bootstrap
    async with running(app, secret) as (client, _):
        r = await client.post("/api/v1/tokens", json={"name": "mes", "role": "read"})
        assert r.status_code == 201, r.text
        assert r.json()["info"]["id"] == 2


def _mvpose(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "server.cli", *args], cwd=ROOT, text=True,
                          capture_output=True, timeout=120, env={**os.environ, **(env or {})})


def _one_line_error(result: subprocess.CompletedProcess[str], *words: str) -> None:
    assert result.returncode != 0, result
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_start_up_errors_are_one_line_and_a_failure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    data = ["--data-dir", str(tmp_path / "var")]
    station = ["--station", str(STATION1)]
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    # as a process (`python -m server.cli` runs the same dispatcher as the `mvpose` script)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        _one_line_error(_mvpose("api", *station, *data, "--port", port),
                        "mvpose api: error:", f"127.0.0.1:{port} is not free")
    _one_line_error(_mvpose("api", "--station", str(bad), *data), str(bad), "not valid YAML")

    def in_process(*argv: str) -> subprocess.CompletedProcess[str]:
        code = main(list(argv))
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(list(argv), code, out, err)

    monkeypatch.setenv("MVPOSE_BOOTSTRAP_TOKEN", "short")
    for command in ("api", "serve"):
        _one_line_error(in_process(command, *station, *data, "--port", "0"),
                        f"mvpose {command}: error:", "at least 16 characters, got 5")
    monkeypatch.delenv("MVPOSE_BOOTSTRAP_TOKEN")
    bad.write_text("name: x\nfoo: 1\n")
    _one_line_error(in_process("api", "--station", str(bad), *data), "foo: Extra inputs",
                    "views: Field required")
    _one_line_error(in_process("serve", "--station", str(tmp_path / "none.yaml"), *data),
                    "none.yaml: cannot read station file")
    _one_line_error(in_process("station", *station, *data, "--plc-port", "0",
                               "--sim-keep-poses", "-1"),
                    "mvpose station: error:", "--sim-keep-poses must be >= 0, got -1")
    monkeypatch.setenv("MVPOSE_SIM_KEEP_POSES", "many")
    _one_line_error(in_process("station", *station, *data, "--plc-port", "0"),
                    "environment variable MVPOSE_SIM_KEEP_POSES: expected an integer >= 0, "
                    "got 'many'")


def test_a_busy_link_port_or_a_bad_links_block_is_one_line_and_a_failure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The Modbus port already taken: `mvpose serve` and `mvpose station` end with one line
    naming host:port (as the REST port does), not a traceback; a typo inside links.modbus and an
    unknown backend stop start-up naming the file and the field (checked in this process: the
    station file is refused before anything starts)."""
    data = ["--data-dir", str(tmp_path / "var")]
    station = ["--station", str(STATION1)]
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        for command in ("serve", "station"):
            _one_line_error(_mvpose(command, *station, *data, "--port", "0", "--plc-port", port)
                            if command == "serve" else
                            _mvpose(command, *station, *data, env={"MVPOSE_PLC_PORT": port}),
                            f"mvpose {command}: error:", f"127.0.0.1:{port} is not free",
                            "modbus link", "--plc-port / set MVPOSE_PLC_PORT")
    text = STATION1.read_text()
    assert "\nlinks:" not in text  # station 1 runs the default links
    for links, words in (("links:\n  modbus:\n    prot: 5020\n",
                          ("links.modbus.prot", "Extra inputs are not permitted")),
                         ("links:\n  modbus:\n    port: 70000\n", ("links.modbus.port", "70000")),
                         ("links:\n  profibus: {}\n", ("links.profibus", "unknown link backend",
                                                       "modbus, opcua"))):
        bad = tmp_path / "links.yaml"
        bad.write_text(text.rstrip() + "\n" + links)
        code = main(["station", "--station", str(bad), *data])
        out, err = capsys.readouterr()
        _one_line_error(subprocess.CompletedProcess([], code, out, err), str(bad), *words)
