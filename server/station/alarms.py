"""The station's alarm watch: a thread that looks at its sources once a period and keeps the
store's alarms (server/store/alarms.py) in step with them.

Sources (docs/alarms.md has the table): each link (generically, from drivers.links.base.Link:
not ready, or a line state of PREOPERATIONAL or ERROR), each camera (down, reconnected), the
durable writer (database down, chain conflict) and the journal (an append refused), the drift
watch (server/drift.py), the active calibration's age (the station file's
``calibration_max_age_days``) and NOKs in a row (the recipe's ``nok_streak_warning``).

A condition must hold ``on_delay_s`` before its alarm is raised (ISA-18.2's on-delay: a link
restarting does not alarm), and the alarm is raised with the time the condition was first seen.
A write the database refuses is tried again next period: an alarm of a database outage is
written, raised and cleared, once the database is back. The ``alarm-watch`` thread never
touches the trigger thread: it reads the rooms' status, and hears of results as a listener.
While the line triggers, each round starts when a result has been heard (the listener is
called a few milliseconds after the answer went out), so its Python (the store's reads, the
drift watch parsing the new records) falls into the gap before the next trigger instead of
sharing the GIL with a running one; the drift watch reads the new records every round, a few
at a time, not hundreds in one go.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from drivers.links.base import AlarmNotice
from server.store.alarms import AlarmFilter, AlarmRepository, Priority

if TYPE_CHECKING:
    from drivers.links.result import ResultEvent
    from server.drift import DriftService
    from server.station.core import Station

log = logging.getLogger(__name__)

#: the codes this watch raises and clears (the supervisor owns STATION_DOWN)
CODES = frozenset({"LINK_DOWN", "LINK_NO_PLC", "LINK_ERROR", "CAMERA_DOWN", "CAMERA_RECONNECTED",
                   "STORE_DOWN", "STORE_CONFLICT", "STORE_FAILED", "DRIFT_WARNING",
                   "DRIFT_ALARM", "CALIBRATION_AGE", "NOK_STREAK"})


@dataclass(frozen=True)
class Condition:
    """An alarm's condition as a source sees it now."""

    source: str
    code: str
    priority: Priority
    text: str
    args: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> tuple[str, str]:
        return self.source, self.code


@dataclass(frozen=True)
class AlarmWatchOptions:
    period_s: float = 1.0
    on_delay_s: float = 3.0  # a condition must hold this long before it alarms
    # the drift watch reads the new records this often (~0.05 ms of Python each, their
    # residuals only: every round, so that a round stays short enough for the gap between two
    # triggers; its Python holds the GIL the trigger thread needs)
    drift_every_s: float = 1.0
    calibration_every_s: float = 300.0
    # records the drift watch reads at its first report, drift_every_s after the start (a
    # one-off ~0.05 ms each of the station process's CPU; the recipe's residual response, ~20 ms,
    # is built in start(), before ready)
    drift_window: int = 500
    # a link that has not been ready yet is not down while it starts (the OPC UA link loads the
    # Machine Vision NodeSet in the background for seconds)
    link_start_grace_s: float = 120.0


class AlarmWatch:
    """Keeps one station's alarms in the store in step with its sources."""

    def __init__(self, station: Station, repo: AlarmRepository,
                 options: AlarmWatchOptions | None = None) -> None:
        self.station = station
        self.repo = repo
        self.options = options or AlarmWatchOptions()
        self._stop = threading.Event()
        self._heard_one = threading.Event()  # a result since the round's period ended
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()  # the result listener's figures
        self._streak: int | None = None  # NOKs in a row, None until read from the store
        self._first_seen: dict[tuple[str, str], tuple[float, datetime]] = {}
        self._raised: set[tuple[str, str]] = set()
        self._loaded = False
        self._told = 0  # the newest transition the links heard of
        self._events: list[Condition] = []  # one-shot alarms (raised, then cleared) to write
        self._reconnects: dict[str, int] = {}
        self._store_failed = 0
        self._slow: dict[str, tuple[float, list[Condition]]] = {}  # drift, calibration
        self._drift: DriftService | None = None
        self._started = time.monotonic()
        self._was_ready: set[str] = set()  # links that have been ready since the start
        self.last_error: str | None = None

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        active = self.station.active
        if active is not None and self.station.services is not None:
            # the active recipe's drift response now, before ready: built on the round after its
            # first record, its ~20 ms of Python held the GIL the next trigger needed
            try:
                self._drift_service().prepare(active.config.name)
            except Exception as err:  # the drift check's rounds build it then
                log.warning("station %s: alarm watch: the drift response for recipe %s: %s",
                            self.repo.station, active.config.name, err)
        self.station.add_listener(self._heard)
        self._thread = threading.Thread(target=self._run, name="alarm-watch", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._heard_one.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def status(self) -> dict[str, Any]:
        return {"raised": len(self._raised), "last_error": self.last_error}

    def _heard(self, event: ResultEvent) -> None:
        """A result (the station loop's thread): count NOKs in a row."""
        with self._lock:
            if self._streak is not None:
                self._streak = 0 if event.ok else self._streak + 1
        self._heard_one.set()

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        while not self._stop.wait(self.options.period_s):
            # the next answer, or another period when the line is not triggering
            self._heard_one.clear()
            self._heard_one.wait(self.options.period_s)
            if self._stop.is_set():
                return
            try:
                self.check()
            except Exception as err:  # the database is down: try again next period
                self.last_error = f"{type(err).__name__}: {str(err).splitlines()[0][:200]}"
                log.warning("station %s: alarm watch: %s", self.repo.station, self.last_error)

    def check(self) -> None:
        """One round: look at every source, raise and clear what changed."""
        if not self._loaded:  # alarms left active by the last run are this run's to clear
            active = self.repo.find(AlarmFilter(active=True), limit=1000)
            self._raised |= {(a.source, a.code) for a in active if a.code in CODES}
            self._told = self.repo.last_transition()
            self._loaded = True
        now, at = time.monotonic(), datetime.now(UTC)
        conditions = {c.key: c for c in self.conditions()}
        for key in list(self._first_seen):
            if key not in conditions:
                del self._first_seen[key]
        for key, cond in conditions.items():
            since = self._first_seen.setdefault(key, (now, at))
            if key in self._raised or now - since[0] < self.options.on_delay_s:
                continue
            _, new = self.repo.raise_(cond.source, cond.code, cond.priority, cond.text,
                                      cond.args, at=since[1])
            self._raised.add(key)
            if new:
                log.warning("station %s: alarm %s %s: %s", self.repo.station, cond.source,
                            cond.code, cond.text)
        for key in sorted(self._raised - conditions.keys()):
            self.repo.clear(*key, at=at)
            self._raised.discard(key)
        while self._events:  # an event alarm: raised and cleared, standing until acknowledged
            ev = self._events[0]
            self.repo.raise_(ev.source, ev.code, ev.priority, ev.text, ev.args, at=at)
            self.repo.clear(ev.source, ev.code, at=at)
            self._events.pop(0)
        self._tell_links()
        self.last_error = None

    def _tell_links(self) -> None:
        """Every transition since the last round, this process's and others' (an operator's
        acknowledgement through the API), to the links (OPC UA condition events)."""
        for event_id, kind, by, at, alarm in self.repo.transitions_after(self._told):
            # the alarm's state just after this transition, from its timestamps
            active = alarm.cleared_at is None or alarm.cleared_at > at or kind == "raised"
            acked = kind == "acknowledged" or (
                kind == "cleared" and alarm.acked_at is not None and alarm.acked_at <= at)
            self.station.host.alarm_changed(AlarmNotice(
                kind, event_id, alarm.id, alarm.source, alarm.code, alarm.priority,
                alarm.text, active and kind != "cleared", acked,
                by if kind == "acknowledged" else alarm.acked_by if acked else None, at))
            self._told = event_id

    def conditions(self) -> list[Condition]:
        """What every source says now."""
        out = [*self._links(), *self._cameras(), *self._store(), *self._nok_streak()]
        for name, every, read in (("drift", self.options.drift_every_s, self._drift_now),
                                  ("calibration", self.options.calibration_every_s,
                                   self._calibration_now)):
            # the first look a period after the start, not at once
            last = self._slow.setdefault(name, (self._started, []))
            if time.monotonic() - last[0] >= every:
                try:
                    last = (time.monotonic(), read())
                except Exception as err:
                    log.warning("station %s: alarm watch: the %s check failed: %s",
                                self.repo.station, name, err)
                    last = (time.monotonic(), last[1])
                self._slow[name] = last
            out.extend(last[1])
        return out

    # ------------------------------------------------------------------ the sources
    def _links(self) -> list[Condition]:
        out = []
        for link in list(self.station.links):
            src, args = f"link:{link.name}", {"link": link.name}
            ready = link.ready()
            if ready:
                self._was_ready.add(link.name)
            elif link.name not in self._was_ready and (
                    time.monotonic() - self._started < self.options.link_start_grace_s):
                continue  # still starting
            if not ready:
                out.append(Condition(src, "LINK_DOWN", "high",
                                     f"link {link.name} is down", args))
                continue
            state = link.line_state()
            if state == "PREOPERATIONAL":
                out.append(Condition(src, "LINK_NO_PLC", "high",
                                     f"link {link.name}: no PLC heartbeat", args))
            elif state == "ERROR":
                out.append(Condition(src, "LINK_ERROR", "medium",
                                     f"link {link.name} is in ERROR and needs a reset", args))
        return out

    def _cameras(self) -> list[Condition]:
        capture = self.station.measuring.capture
        if capture is None:
            return []
        out = []
        for cid, (up, why, reconnects) in capture.health().items():
            args = {"camera": cid}
            if not up:
                why = why or "starting"
                out.append(Condition(f"camera:{cid}", "CAMERA_DOWN", "high",
                                     f"camera {cid} is down: {why}"[:400],
                                     {**args, "reason": why[:200]}))
            seen = self._reconnects.setdefault(cid, reconnects)
            if reconnects > seen:
                self._reconnects[cid] = reconnects
                self._events.append(Condition(
                    f"camera:{cid}", "CAMERA_RECONNECTED", "low",
                    f"camera {cid} reconnected ({reconnects} reconnects since start)",
                    {**args, "reconnects": reconnects}))
        return out

    def _store(self) -> list[Condition]:
        out = []
        sink = self.station.sink
        st = sink.status() if sink is not None else None
        if st is not None and st.get("conflict"):
            out.append(Condition("store", "STORE_CONFLICT", "high",
                                 "the database holds another chain: the writer stopped",
                                 {"error": st.get("last_error")}))
        elif st is not None and not st.get("up", True):
            out.append(Condition("store", "STORE_DOWN", "high",
                                 f"the database does not take records ({st.get('pending')} "
                                 f"waiting in the journal): {st.get('last_error')}"[:400],
                                 {"pending": st.get("pending"), "error": st.get("last_error")}))
        recorder = self.station.recorder
        failed = recorder.snapshot()[1].get("store_failed", 0)
        if failed > self._store_failed:
            self._store_failed = failed
            self._events.append(Condition(
                "store", "STORE_FAILED", "high",
                f"a record could not be stored (the PLC got STORE_FAILED): "
                f"{recorder.store_error}"[:400], {"error": recorder.store_error}))
        return out

    def _nok_streak(self) -> list[Condition]:
        active = self.station.active
        with self._lock:
            streak = self._streak
        if streak is None:
            streak = self.station.services.store.shifts.nok_streak() if (
                self.station.services is not None) else 0
            with self._lock:
                self._streak = streak
        if active is None or streak < active.config.nok_streak_warning:
            return []
        return [Condition("station", "NOK_STREAK", "medium",
                          f"{streak} NOK result{'' if streak == 1 else 's'} in a row (recipe "
                          f"{active.config.name})",
                          {"count": streak, "recipe": active.config.name})]

    def _drift_now(self) -> list[Condition]:
        if self.station.services is None:
            return []
        out = []
        for cam in self._drift_service().cameras():
            if cam.status in ("warning", "alarm"):
                alarm = cam.status == "alarm"
                code = "DRIFT_ALARM" if alarm else "DRIFT_WARNING"
                prio: Priority = "high" if alarm else "medium"
                out.append(Condition(f"drift:{cam.camera_id}", code, prio, cam.message[:400],
                                     {"camera": cam.camera_id, "view": cam.view,
                                      "shift_px": cam.shift_px}))
        return out

    def _drift_service(self) -> DriftService:
        if self._drift is None:
            from server.drift import DriftService

            services = self.station.services
            assert services is not None
            self._drift = DriftService(services.store, services.station,
                                       window=self.options.drift_window)
        return self._drift

    def _calibration_now(self) -> list[Condition]:
        limit = self.station.file_station.calibration_max_age_days
        services = self.station.services
        if limit is None or services is None:
            return []
        from server.errors import NotFoundError

        try:
            info, content = services.store.versions.content(
                "calibration", self.station.file_station.name)
        except NotFoundError:
            return []
        created = datetime.fromisoformat(str(content.get("created")))
        if created.tzinfo is None:
            created = created.replace(tzinfo=UTC)
        age_days = (datetime.now(UTC) - created).total_seconds() / 86400
        if age_days <= limit:
            return []
        return [Condition("calibration", "CALIBRATION_AGE", "medium",
                          f"the calibration (version {info.version}, {created:%Y-%m-%d}) is "
                          f"{age_days:.0f} days old; the limit is {limit:g} days",
                          {"version": info.version, "age_days": round(age_days, 1),
                           "limit_days": limit, "created": created.isoformat()})]


class ProcessAlarms:
    """STATION_DOWN, raised and cleared by ``mvpose serve``'s supervisor when the station
    process ends and when it is ready again (server.supervisor's ``Child.on_change``). The
    writes run on a thread of their own, in order; the engine is made at the first write (the
    station process has migrated the schema by then)."""

    def __init__(self, url: str, station: str, topic: str | None) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.url = url
        self.station = station
        self.topic = topic
        self._repo: AlarmRepository | None = None
        self._exec = ThreadPoolExecutor(1, thread_name_prefix="station-alarms")

    def __call__(self, up: bool, exit_code: int | None) -> None:
        at = datetime.now(UTC)
        self._exec.submit(self._write, up, exit_code, at)

    def _write(self, up: bool, exit_code: int | None, at: datetime) -> None:
        try:
            if self._repo is None:
                from server.store.db import create_store_engine

                self._repo = AlarmRepository(create_store_engine(self.url), self.station,
                                             self.topic)
            if up:
                self._repo.clear("station", "STATION_DOWN", at=at)
            else:
                self._repo.raise_("station", "STATION_DOWN", "high",
                                  f"the station process ended (exit code {exit_code}); it is "
                                  f"being restarted", {"exit_code": exit_code}, at=at)
        except Exception as err:
            log.warning("station %s: the STATION_DOWN alarm could not be written: %s",
                        self.station, err)

    def close(self, timeout_s: float = 5.0) -> None:
        self._exec.shutdown(wait=True, cancel_futures=False)
        if self._repo is not None:
            self._repo.engine.dispose()
