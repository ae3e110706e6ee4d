"""Results streamed to the plant through MQTT: the outbox's publisher in the station process.

Only a station file with a ``plant:`` block that names an ``mqtt`` broker starts it
(server/station/process.py). Then:

- the durable writer is opened with the outbox hook (:meth:`MqttPublisher.sink`): every record
  the database takes gets its result message in the same transaction (server/store/outbox.py);
- the ``mqtt-publisher`` thread reads the unpublished rows in order, publishes them with QoS 1
  and marks them published when the broker's PUBACK arrives (paho's network thread reports it);
  a broker that is down only delays them, a station that stops or dies publishes them after its
  restart: at least once, consumers deduplicate by ``id`` (docs/integration.md);
- the station state (online, recipe and version, calibration) is a retained message; the
  broker's last will replaces it with ``online: false`` when the station dies.

Nothing here runs on the trigger path: the outbox rows are written by the writer's database
thread, which wakes the publisher (an event) once they are committed.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any

from sqlalchemy import Engine

from mvpose_core.plantconfig import MqttConfig, PlantConfig
from mvpose_core.station import StationConfig
from server.state import Services
from server.station.core import WriterSink
from server.store.outbox import Outbox, result_rows

if TYPE_CHECKING:
    import paho.mqtt.client as paho

    from server.station.core import Station

log = logging.getLogger(__name__)

_INFLIGHT = 200  # outbox rows handed to the client and not yet acknowledged
_STALE_S = 30.0  # a row unacknowledged this long on a live connection is published again
_PRUNE_EVERY_S = 600.0


def topic_prefix(plant: PlantConfig, station: str) -> str:
    """``<enterprise>/<site>/<area>/<line>/<station>/mvpose``: the station's ISA-95 topic root."""
    return plant.topic_prefix(station)


class MqttPublisher:
    """Publishes one station's outbox and its retained state to the plant's broker."""

    def __init__(self, station: str, plant: PlantConfig, mqtt: MqttConfig,
                 software_version: str = "") -> None:
        self.station = station
        self.plant = plant
        self.config = mqtt
        self.software_version = software_version
        prefix = topic_prefix(plant, station)
        self.result_topic = f"{prefix}/result"
        self.state_topic = f"{prefix}/state"
        self.alarm_topic = f"{prefix}/alarms"  # written by server.store.alarms (server/state.py)
        self._outbox: Outbox | None = None
        self._station: Station | None = None
        self._client: paho.Client | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._lock = threading.Lock()  # what paho's network thread shares with the publisher
        self._connected = False
        self._connected_at = 0.0
        self._inflight: dict[int, tuple[int, float]] = {}  # mid -> (outbox id, published at)
        self._acked: list[int] = []  # outbox ids acknowledged, not yet marked in the database
        self._early: dict[int, float] = {}  # mids acknowledged before publish() returned
        self._cursor = 0  # the highest outbox id handed to the client
        self._state_sent: tuple[Any, ...] | None = None
        self.published = 0  # acknowledged by the broker since start
        self.last_error: str | None = None

    @classmethod
    def for_station(cls, station: StationConfig, software_version: str = "") \
            -> MqttPublisher | None:
        """The publisher the station file asks for, or None (no ``plant.mqtt`` block)."""
        if station.plant is None or station.plant.mqtt is None:
            return None
        return cls(station.name, station.plant, station.plant.mqtt, software_version)

    def sink(self, services: Services) -> WriterSink:
        """The station's writer with this publisher's outbox rows in each record's transaction
        (the journal's replay at start-up too)."""
        return WriterSink(services, outbox=result_rows(self.result_topic))

    # ------------------------------------------------------------------ life cycle
    def start(self, station: Station) -> None:
        """Connect (in the background: a broker that is down is retried) and start publishing."""
        sink = station.sink
        if not isinstance(sink, WriterSink) or sink.outbox is None:
            raise RuntimeError(f"station {self.station!r}: the MQTT publisher needs the station "
                               f"started with its sink (MqttPublisher.sink)")
        self._station = station
        self.connect(sink.writer.engine)
        sink.writer.add_commit_listener(lambda _seq: self._wake.set())  # its rows are in

    def connect(self, engine: Engine) -> None:
        """Publish the outbox in ``engine``'s database (``start`` does this for a station)."""
        import paho.mqtt.client as paho

        self._outbox = Outbox(engine, self.station)
        cfg = self.config
        client = paho.Client(paho.CallbackAPIVersion.VERSION2,
                             client_id=f"mvpose/{self.result_topic.rsplit('/', 2)[0]}",
                             protocol=paho.MQTTv311, clean_session=True)
        if cfg.username is not None:
            password = os.environ.get(cfg.password_env) if cfg.password_env else None
            if cfg.password_env and password is None:
                raise RuntimeError(f"station {self.station!r}: plant.mqtt.password_env names "
                                   f"{cfg.password_env!r}, which is not set")
            client.username_pw_set(cfg.username, password)
        client.will_set(self.state_topic, self._state_payload(online=False, why="connection lost"),
                        qos=1, retain=True)
        client.max_inflight_messages_set(_INFLIGHT)
        client.reconnect_delay_set(min_delay=1, max_delay=2)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish
        self._client = client
        client.connect_async(cfg.host, cfg.port, keepalive=cfg.keepalive_s)
        client.loop_start()
        self._thread = threading.Thread(target=self._run, name="mqtt-publisher", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Publish ``online: false`` (retained), hand over what is acknowledged, disconnect.
        Rows not acknowledged by then stay in the outbox for the next start."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s + 5)
            self._thread = None
        client = self._client
        if client is None:
            return
        if self._connected:
            try:
                info = client.publish(self.state_topic,
                                      self._state_payload(online=False, why="stopped"),
                                      qos=1, retain=True)
                info.wait_for_publish(timeout_s)
            except (RuntimeError, ValueError) as err:
                log.warning("station %s: the offline state was not published: %s",
                            self.station, err)
        self._mark_acked()
        client.disconnect()
        client.loop_stop()
        self._client = None

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {"connected": self._connected, "broker": f"{self.config.host}:"
                    f"{self.config.port}", "inflight": len(self._inflight),
                    "published": self.published, "last_error": self.last_error}

    # ------------------------------------------------------------------ paho's network thread
    def _on_connect(self, client: paho.Client, _userdata: Any, _flags: Any, reason: Any,
                    _props: Any) -> None:
        if reason.is_failure:
            self.last_error = f"the broker refused the connection: {reason}"
            log.warning("station %s: MQTT broker %s:%d: %s", self.station, self.config.host,
                        self.config.port, reason)
            return
        with self._lock:
            self._connected = True
            self._connected_at = time.monotonic()
            self._state_sent = None  # a new session: the state is published again
        log.info("station %s: connected to the MQTT broker %s:%d", self.station,
                 self.config.host, self.config.port)
        self._wake.set()

    def _on_disconnect(self, _client: paho.Client, _userdata: Any, _flags: Any, reason: Any,
                       _props: Any) -> None:
        with self._lock:
            was, self._connected = self._connected, False
        if was and not self._stop.is_set():  # a refused connect has said why already
            self.last_error = f"disconnected from the broker: {reason}"
            log.warning("station %s: MQTT broker %s:%d lost (%s); reconnecting", self.station,
                        self.config.host, self.config.port, reason)

    def _on_publish(self, _client: paho.Client, _userdata: Any, mid: int, _reason: Any,
                    _props: Any) -> None:
        with self._lock:
            found = self._inflight.pop(mid, None)
            if found is not None:
                self._acked.append(found[0])
                self.published += 1
            else:
                self._early[mid] = time.monotonic()  # or the state message's
        if found is not None:
            self._wake.set()

    # ------------------------------------------------------------------ the publisher thread
    def _run(self) -> None:
        last_prune = 0.0
        while not self._stop.is_set():
            self._wake.wait(self.config.poll_s)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self._mark_acked()
                if self._connected:
                    self._publish_state()
                    self._publish_pending()
                if time.monotonic() - last_prune > _PRUNE_EVERY_S:
                    assert self._outbox is not None
                    gone = self._outbox.prune(timedelta(hours=self.config.keep_published_h))
                    last_prune = time.monotonic()
                    if gone:
                        log.info("station %s: %d published outbox rows deleted", self.station,
                                 gone)
            except Exception as err:  # the database is down: the rows wait, so do we
                self.last_error = f"{type(err).__name__}: {str(err).splitlines()[0][:200]}"
                log.warning("station %s: MQTT publisher: %s", self.station, self.last_error)
                self._stop.wait(1.0)

    def _mark_acked(self) -> None:
        with self._lock:
            acked, self._acked = self._acked, []
        if not acked or self._outbox is None:
            return
        try:
            self._outbox.mark_published(acked)
        except Exception:
            with self._lock:  # published again after a restart at worst; retried next round
                self._acked[:0] = acked
            raise

    def _publish_pending(self) -> None:
        assert self._outbox is not None and self._client is not None
        now = time.monotonic()
        with self._lock:
            room = _INFLIGHT - len(self._inflight)
            oldest = min((at for _, at in self._inflight.values()), default=now)
            if (now - oldest > _STALE_S and now - self._connected_at > _STALE_S):
                # never acknowledged on a live connection: hand the rows over again
                log.warning("station %s: %d MQTT messages unacknowledged for %.0f s; "
                            "publishing them again", self.station, len(self._inflight),
                            now - oldest)
                self._inflight.clear()
                self._early.clear()
                self._cursor = 0
                room = _INFLIGHT
            cursor = self._cursor
        if room <= 0:
            return
        for row in self._outbox.pending(after_id=cursor, limit=room):
            # Not under self._lock: paho's network thread holds its own lock while it calls
            # _on_publish, which takes self._lock.
            info = self._client.publish(row.topic, row.payload, qos=1)
            with self._lock:
                self._cursor = row.id
                early = self._early.pop(info.mid, None)
                if early is not None and time.monotonic() - early < 5.0:
                    # the PUBACK came before publish() returned (an older entry is the state
                    # message's, its mid long reused)
                    self._acked.append(row.id)
                    self.published += 1
                else:
                    self._inflight[info.mid] = (row.id, time.monotonic())

    def _publish_state(self) -> None:
        assert self._client is not None
        key = self._state_key()
        if key == self._state_sent:
            return
        self._client.publish(self.state_topic, self._state_payload(online=True), qos=1,
                             retain=True)
        self._state_sent = key

    def _state_key(self) -> tuple[Any, ...]:
        st = self._station
        active = st.active if st is not None else None
        prov = st.provenance if st is not None else None
        return (None if active is None else (active.config.name, active.version, active.number),
                prov.calibration if prov is not None else None)

    def _state_payload(self, online: bool, why: str | None = None) -> str:
        recipe, calibration = self._state_key()
        return json.dumps({
            "schema": "mvpose.state/1",
            "station": self.station,
            "online": online,
            "reason": why,
            "at": datetime.now(UTC).isoformat(),
            "recipe": None if recipe is None else {
                "name": recipe[0], "version": recipe[1], "number": recipe[2]},
            "calibration": None if calibration is None else {
                "id": calibration[0], "sha256": calibration[1]},
            "software_version": self.software_version,
        }, separators=(",", ":"))
