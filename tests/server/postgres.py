"""A throwaway PostgreSQL 15 cluster for the store tests, started from the binaries on the machine.

initdb and pg_ctl refuse to run as root, so under root the cluster belongs to an unprivileged
system user (``mvpose-pg``, created with useradd when missing) and the binaries run through
``runuser``. PostgreSQL cannot listen on port 0: a free port is found by binding a socket to port
0 first (and the start is retried on a new port if another process took it meanwhile). The
socket directory lives in the cluster's temp dir; fsync is off because the data is thrown away.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

PG_BIN = Path(os.environ.get("MVPOSE_PG_BIN", "/usr/lib/postgresql/15/bin"))
PG_USER = "mvpose-pg"


@dataclass(frozen=True)
class PostgresCluster:
    port: int
    datadir: Path

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{database}"

    def create_database(self) -> str:
        """A fresh, empty database; returns its SQLAlchemy URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres",
                             autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _as_owner(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", PG_USER, "--", *cmd] if os.geteuid() == 0 else cmd


def _ensure_user() -> None:
    if os.geteuid() != 0:
        return
    try:
        pwd.getpwnam(PG_USER)
    except KeyError:
        subprocess.run(["useradd", "--system", "--no-create-home", "--shell", "/usr/sbin/nologin",
                        PG_USER], check=True, capture_output=True)


def start_cluster() -> tuple[PostgresCluster, Path]:
    if not (PG_BIN / "initdb").exists():
        pytest.skip(f"PostgreSQL binaries not found in {PG_BIN}")
    _ensure_user()
    root = Path(tempfile.mkdtemp(prefix="mvpose-pg-"))
    datadir, sockdir = root / "data", root / "sock"
    sockdir.mkdir()
    if os.geteuid() == 0:
        pw = pwd.getpwnam(PG_USER)
        for p in (root, sockdir):
            os.chown(p, pw.pw_uid, pw.pw_gid)
    subprocess.run(_as_owner([str(PG_BIN / "initdb"), "-D", str(datadir), "-U", "postgres",
                              "--auth=trust", "-E", "UTF8", "--no-sync", "--no-instructions"]),
                   check=True, capture_output=True)
    last_err = ""
    for _ in range(3):
        port = _free_port()
        opts = (f"-p {port} -k {sockdir} -c listen_addresses=127.0.0.1 -c fsync=off "
                "-c synchronous_commit=off -c full_page_writes=off -c shared_buffers=16MB")
        proc = subprocess.run(_as_owner([str(PG_BIN / "pg_ctl"), "-D", str(datadir), "-o", opts,
                                         "-l", str(root / "log"), "-w", "-t", "60", "start"]),
                              capture_output=True, text=True)
        if proc.returncode == 0:
            return PostgresCluster(port=port, datadir=datadir), root
        last_err = proc.stderr + (root / "log").read_text(errors="replace")[-2000:]
    shutil.rmtree(root, ignore_errors=True)
    raise RuntimeError(f"PostgreSQL did not start: {last_err}")


def stop_cluster(cluster: PostgresCluster, root: Path) -> None:
    subprocess.run(_as_owner([str(PG_BIN / "pg_ctl"), "-D", str(cluster.datadir), "-m", "immediate",
                              "-w", "stop"]), capture_output=True)
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    cluster, root = start_cluster()
    try:
        yield cluster
    finally:
        stop_cluster(cluster, root)
