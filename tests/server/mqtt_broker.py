"""Mosquitto from Debian's package on a free loopback port, and an independent subscriber.

The broker keeps its state in the test's temp dir (``persistence true``, written after every
change): a plant's broker must, or a consumer with a persistent session misses what arrives while
the broker restarts. It comes back on the same port (the stations' files name it).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from system_packages import ensure_commands


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(what: str, check: Callable[[], Any], timeout: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        got = check()
        if got:
            return got
        assert time.monotonic() < deadline, f"{what} within {timeout:g} s"
        time.sleep(0.02)


class Mosquitto:
    def __init__(self, tmp: Path, users: dict[str, str] | None = None) -> None:
        """``users``: a password file with these users, and no anonymous clients."""
        found = ensure_commands({"mosquitto": "mosquitto", "mosquitto_passwd": "mosquitto"})
        self.exe = found["mosquitto"]
        self.dir = tmp / "mosquitto"
        self.dir.mkdir()
        self.port = _free_port()
        auth = "allow_anonymous true\n"
        if users:
            passwd = self.dir / "passwd"
            for user, password in users.items():
                subprocess.run([found["mosquitto_passwd"], "-b"]
                               + ([] if passwd.exists() else ["-c"])
                               + [str(passwd), user, password], check=True,
                               capture_output=True)
            auth = f"allow_anonymous false\npassword_file {passwd}\n"
        self.conf = self.dir / "mosquitto.conf"
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\n{auth}persistence true\n"
            f"persistence_location {self.dir}/\nautosave_on_changes true\nautosave_interval 1\n"
            f"log_dest file {self.dir}/broker.log\n"
            "log_type error\nlog_type warning\nlog_type notice\n"
            # as root it would switch to its own user, who cannot enter pytest's 0700 temp dirs
            + ("user root\n" if os.geteuid() == 0 else ""))
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen([self.exe, "-c", str(self.conf)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_until(f"mosquitto listening on 127.0.0.1:{self.port}", self._listening, 15)

    def _listening(self) -> bool:
        assert self.proc is not None
        if self.proc.poll() is not None:
            log = (self.dir / "broker.log")
            raise AssertionError(f"mosquitto exited with {self.proc.returncode}: "
                                 f"{log.read_text()[-2000:] if log.exists() else ''}")
        try:
            socket.create_connection(("127.0.0.1", self.port), timeout=0.5).close()
            return True
        except OSError:
            return False

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=10)
        self.proc = None


class Subscriber:
    """A consumer with a persistent session (QoS 1): every message, duplicates included."""

    def __init__(self, port: int, topics: list[str], client_id: str = "test-consumer",
                 username: str | None = None, password: str | None = None) -> None:
        self.topics = topics
        self.messages: list[tuple[str, dict[str, Any], bool]] = []  # topic, payload, retained
        self.lock = threading.Lock()
        self.subscribed = threading.Event()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=client_id,
                                  protocol=paho.MQTTv311, clean_session=False)
        self.client.reconnect_delay_set(min_delay=1, max_delay=1)
        if username is not None:
            self.client.username_pw_set(username, password)
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        self.client.on_subscribe = lambda *_: self.subscribed.set()
        self.client.connect("127.0.0.1", port, keepalive=10)
        self.client.loop_start()
        assert self.subscribed.wait(10), "the test subscriber was not subscribed within 10 s"

    def _on_connect(self, client: paho.Client, *_: Any) -> None:
        client.subscribe([(t, 1) for t in self.topics])

    def _on_message(self, _c: paho.Client, _u: Any, msg: paho.MQTTMessage) -> None:
        with self.lock:
            self.messages.append((msg.topic, json.loads(msg.payload), bool(msg.retain)))

    def on(self, suffix: str) -> list[dict[str, Any]]:
        with self.lock:
            return [p for t, p, _ in self.messages if t.endswith(suffix)]

    def results(self) -> dict[tuple[str, int], dict[str, Any]]:
        """Deduplicated by (station, result id); asserts duplicates are byte-for-byte equal."""
        out: dict[tuple[str, int], dict[str, Any]] = {}
        for p in self.on("/mvpose/result"):
            key = (p["station"], p["result_id"])
            assert out.setdefault(key, p) == p, f"two different messages for {key}"
        return out

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
