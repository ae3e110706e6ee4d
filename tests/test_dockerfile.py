"""The Dockerfile's install steps, executed in a fresh virtual environment (no Docker engine here).

The test reads the Dockerfile, rebuilds its build context from the COPY lines that precede the
install, and runs every ``pip install`` RUN command literally with the fresh environment's
``python``. The fresh environment sees the shared ``.venv`` site-packages through a ``.pth`` file,
playing the part of a base layer that already holds the third-party wheels: pip still resolves
every requirement of the project (a missing or conflicting one fails), but downloads nothing.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"


def _instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs with line continuations joined and comments dropped."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        line = pending + line
        pending = ""
        word, _, rest = line.partition(" ")
        out.append((word.upper(), rest.strip()))
    return out


def _env(instructions: list[tuple[str, str]]) -> dict[str, str]:
    env: dict[str, str] = {}
    for word, rest in instructions:
        if word == "ENV":
            for item in shlex.split(rest):
                key, _, value = item.partition("=")
                env[key] = value
    return env


def _stages(instructions: list[tuple[str, str]]) -> dict[str, list[tuple[str, str]]]:
    """Each build stage's instructions by stage name (``FROM image AS name``); the final stage
    is also under ``""``."""
    stages: dict[str, list[tuple[str, str]]] = {}
    current: list[tuple[str, str]] = []
    for word, rest in instructions:
        if word == "FROM":
            current = []
            parts = rest.split()
            stages[parts[2] if len(parts) == 3 and parts[1].upper() == "AS" else rest] = current
            stages[""] = current
        current.append((word, rest))
    return stages


def _npm_commands(instructions: list[tuple[str, str]]) -> list[list[str]]:
    cmds = []
    for word, rest in instructions:
        if word == "RUN":
            for part in rest.split("&&"):
                argv = shlex.split(part)
                if argv and argv[0] == "npm":
                    cmds.append(argv)
    return cmds


def _pip_commands(instructions: list[tuple[str, str]],
                  also: tuple[str, ...] = ()) -> list[list[str]]:
    """The RUN lines' ``pip install`` commands (and those naming a module in ``also``)."""
    cmds = []
    for word, rest in instructions:
        if word != "RUN":
            continue
        for part in rest.split("&&"):
            argv = shlex.split(part)
            if ("pip" in argv and "install" in argv) or any(m in argv for m in also):
                cmds.append(argv)
    return cmds


def test_dockerfile_is_slim_non_root_with_healthcheck() -> None:
    ins = _stages(_instructions(DOCKERFILE.read_text()))[""]  # the image that runs
    words = [w for w, _ in ins]
    base = next(rest for w, rest in ins if w == "FROM")
    assert base.endswith("-slim"), f"base image {base!r} is not a slim image"
    users = [rest for w, rest in ins if w == "USER"]
    assert users and users[-1] not in ("root", "0"), f"container runs as {users!r}"
    assert "HEALTHCHECK" in words
    assert words.index("USER") < words.index("ENTRYPOINT")
    health = next(rest for w, rest in ins if w == "HEALTHCHECK")
    assert "/api/v1/health/live" in health
    assert _pip_commands(ins), "the Dockerfile installs nothing with pip"


def _web_stage(ins: list[tuple[str, str]], tmp_path: Path,
               name: str = "web") -> tuple[str, Path]:
    """Run a node stage (the operator page's, the OPC UA NodeSets'): its COPY lines, then its
    ``npm ci`` literally (--prefer-offline: from the npm cache `make venv` filled). Returns
    (WORKDIR, its copy)."""
    npm = _npm_commands(ins)
    assert npm and all(argv[:2] == ["npm", "ci"] for argv in npm), \
        f"the web stage must install exactly the lock file's versions (npm ci), got {npm}"
    workdir = next(rest for w, rest in ins if w == "WORKDIR")
    ctx = tmp_path / name
    ctx.mkdir()
    for word, rest in ins:
        if word == "COPY":
            *sources, dest = shlex.split(rest)
            assert dest in ("./", "."), rest
            for src in sources:
                shutil.copy2(ROOT / src, ctx / Path(src).name)
    for argv in npm:
        done = subprocess.run([shutil.which("npm") or "npm", *argv[1:]], cwd=ctx,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{shlex.join(argv)} failed:\n{done.stdout}\n{done.stderr}"
    return workdir, ctx


def test_dockerfile_install_commands_in_fresh_venv(tmp_path: Path) -> None:
    stages = _stages(_instructions(DOCKERFILE.read_text()))
    node = {name: _web_stage(stages[name], tmp_path, name) for name in ("web", "nodesets")}
    ins = stages[""]
    # Build context: the COPY lines before the first pip install, relative to WORKDIR.
    ctx = tmp_path / "workdir"
    ctx.mkdir()
    for word, rest in ins:
        if word == "RUN" and "pip" in rest:
            break
        if word == "COPY":
            *sources, dest = shlex.split(rest)
            stage = next((s.removeprefix("--from=") for s in sources if s.startswith("--from=")),
                         None)
            sources = [s for s in sources if not s.startswith("--")]
            for src in sources:
                target = ctx / (Path(src).name if dest in ("./", ".") else dest.removeprefix("./"))
                origin = ROOT / src
                if stage is not None:
                    assert stage in node, rest
                    stage_dir, stage_ctx = node[stage]
                    origin = stage_ctx / Path(src).relative_to(stage_dir)
                if origin.is_dir():
                    # a developer's own server/web/node_modules and compiled catalogues are
                    # not in the image's context (.dockerignore)
                    shutil.copytree(origin, target, ignore=shutil.ignore_patterns(
                        "__pycache__", "*.pyc",
                        *(("node_modules", "*.mo") if stage is None else ())))
                else:
                    shutil.copy2(origin, target)

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            check=True, capture_output=True, text=True,
        ).stdout.strip()
    )
    (site / "_base_layer.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    env = {k: v for k, v in os.environ.items() if not k.startswith("VIRTUAL_ENV")}
    env.update(_env(ins))
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    # the install commands, and the compilation of the page's message catalogues between them
    for argv in _pip_commands(ins, also=("babel.messages.frontend",)):
        if argv[0] in ("python", "python3"):
            argv = [str(py), *argv[1:]]
        done = subprocess.run(argv, cwd=ctx, env=env, capture_output=True, text=True, timeout=240)
        assert done.returncode == 0, f"{shlex.join(argv)} failed:\n{done.stdout}\n{done.stderr}"

    # The installed copy, not the source tree, is what the entry point runs.
    where = subprocess.run(
        [str(py), "-c", "import server, mvpose_core; print(server.__file__)"],
        cwd=tmp_path, env=env, capture_output=True, text=True, check=True,
    ).stdout
    assert str(site) in where, where
    # Every non-Python file the packages ship (migrations, templates, ini) made it into the wheel.
    missing = []
    for pkg in ("mvpose_core", "drivers", "server"):
        for f in (ROOT / pkg).rglob("*"):
            shipped = f.suffix in (".py", ".ini", ".mako", ".yaml") and "__pycache__" not in f.parts
            if shipped and not (site / f.relative_to(ROOT)).exists():
                missing.append(str(f.relative_to(ROOT)))
    web = ROOT / "server" / "web"
    missing += [str(f.relative_to(ROOT)) for f in (web / "static").iterdir()
                if not (site / f.relative_to(ROOT)).exists()]
    # the message catalogues, compiled in the image (never committed)
    for po in (web / "locale").glob("*/LC_MESSAGES/messages.po"):
        for f in (po, po.with_suffix(".mo")):
            if not (site / f.relative_to(ROOT)).is_file():
                missing.append(str(f.relative_to(ROOT)))
    assert not missing, f"files not installed by the Dockerfile's pip install: {missing}"
    # The operator page's libraries: the npm packages' files it serves, in the installed package
    from server.web.assets import VENDOR

    for name, rel in VENDOR.items():
        assert (site / "server" / "web" / "node_modules" / rel).is_file(), (
            f"/static/vendor/{name}: {rel} is not in the image (pyproject package-data?)")
    # The OPC UA link's NodeSet2 files, as pinned (the installed link verifies them itself)
    checked = subprocess.run(
        [str(py), "-c", "from drivers.links.opcua import import_order; print(import_order())"],
        env=env, capture_output=True, text=True, cwd=tmp_path)
    assert checked.returncode == 0 and str(site) in checked.stdout, checked.stdout + checked.stderr
    check = subprocess.run(
        [str(py), "-m", "pip", "check"], env=env, capture_output=True, text=True, cwd=tmp_path
    )
    assert check.returncode == 0, check.stdout + check.stderr
    entry = json.loads(next(rest for w, rest in ins if w == "ENTRYPOINT"))
    helped = subprocess.run(
        [str(venv / "bin" / entry[0]), *entry[1:], "--help"],
        env=env, capture_output=True, text=True, cwd=tmp_path, timeout=60,
    )
    assert helped.returncode == 0, helped.stdout + helped.stderr
    assert "--station" in helped.stdout


def test_compose_files_run_the_image_on_an_example_station_with_known_settings() -> None:
    import yaml

    from server.commands.options import LINK_OPTIONS
    from server.settings import Settings

    known = {f"MVPOSE_{name.upper()}" for name in Settings.model_fields}
    known |= {"MVPOSE_HOST", "MVPOSE_PORT"} | {env for env, *_ in LINK_OPTIONS.values()}
    files = sorted((ROOT / "deploy").glob("compose.*.yaml"))
    plant = [ROOT / "deploy" / "compose.plant.yaml"]  # three stations, PostgreSQL, a broker
    single = [f for f in files if not f.name.endswith(".split.yaml") and f not in plant]
    assert {f.name for f in single} == {f"compose.{p.stem}.yaml"
                                       for p in (ROOT / "deploy" / "stations").glob("*.yaml")}
    for f in files:
        doc = yaml.safe_load(f.read_text())
        if f in single:  # one container: `mvpose serve` supervises both processes
            services = {"mvpose": doc["services"]["mvpose"]}
            assert doc["services"]["postgres"]["profiles"] == ["postgres"]
        elif f in plant:  # one `mvpose serve` per station, one database and broker for all
            services = {k: v for k, v in doc["services"].items() if k.startswith("station")}
            assert len(services) == 3 and {"postgres", "mosquitto"} <= set(doc["services"])
            for svc in services.values():
                assert svc["environment"]["MVPOSE_DATABASE_URL"].startswith("postgresql")
        else:  # two containers: each process on its own
            services = {k: doc["services"][k] for k in ("station", "api")}
            assert services["station"]["entrypoint"] == ["mvpose", "station"]
            assert services["api"]["entrypoint"] == ["mvpose", "api"]
        for svc in services.values():
            assert svc["network_mode"] == "host"
            unknown = set(svc["environment"]) - known
            assert not unknown, f"{f.name}: environment variables nothing reads: {unknown}"
            mounts = [v.split(":") for v in svc["volumes"]]
            station = next(src for src, dst, *_ in mounts if dst == "/etc/mvpose/station.yaml")
            assert (ROOT / "deploy" / station).is_file(), f"{f.name}: no station file {station}"
            assert any(dst == "/var/lib/mvpose" for _, dst, *_ in mounts)
