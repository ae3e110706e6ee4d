"""The OPC UA link itself: the server's life cycle, its status and the station's notices.

One ``VisionSystem`` object (``VisionSystemType`` of the OPC Foundation's Machine Vision NodeSet,
:mod:`.nodesets`) stands for the station. The link starts the server in the background (the
NodeSets' import takes seconds) and stops it, and wires the rooms of the folder together:

- :mod:`.endpoint`: the endpoint and its security; :mod:`.model`: the address space;
- :mod:`.machine`: ``VisionStateMachine`` and ``AutomaticModeStateMachine`` (Halt, Reset,
  StartSingleJob, StartContinuous, Stop, Abort), PrepareRecipe, mvpose's Measure and Verify,
  ``SystemState``;
- ``RecipeManagement``, ``ResultManagement``, ``ConfigurationManagement``: :mod:`.management`;
- :mod:`.results`: a ``ResultReadyEvent`` (our subtype ``MvposeResultReadyEventType``) for
  every recorded answer whichever link or client caused it, and the last result as variables
  (``ResultManagement/LastResult``), published here when the station's listener hears of it;
- :mod:`.conditions`: the station's alarms as condition events.

Security (:mod:`.endpoint`, :mod:`.access`, :mod:`.certificates`): Basic256Sha256 Sign /
SignAndEncrypt by default with a server certificate made at the first start in ``pki_dir``;
client certificates must be in ``<pki_dir>/trusted`` (refused ones land in
``<pki_dir>/rejected``); users log in with a name and password checked against the station
file's pbkdf2 hashes and get the read, operator (may call methods) or engineer role (also
ActivateConfiguration, writes); no session on a channel whose security the station file does
not list (None among them). In a station the server runs in a process of its own
(:mod:`drivers.links.process`): building and encoding each result event is pure Python that
would otherwise hold the station process's GIL beside the trigger path.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from pathlib import Path
from typing import Any

from asyncua import Server

from ..base import AlarmNotice, Link, StationHandler
from ..result import ResultEvent
from . import values as v
from .access import Roles, Users
from .certificates import make_certificate
from .conditions import AlarmConditions
from .endpoint import set_up
from .machine import VisionMachine
from .management import Management
from .model import Model, build
from .nodesets import MACHINE_VISION, complete_definitions, import_order
from .results import publish
from .settings import OpcUaLinkConfig

log = logging.getLogger(__name__)


class OpcUaLink(Link):
    """OPC UA server with the station's VisionSystem object."""

    name = "opcua"
    config: OpcUaLinkConfig

    def __init__(self, config: OpcUaLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.server: Server | None = None
        self.port_bound = 0
        self.load_s: dict[str, float] = {}
        self.results = 0  # ResultReadyEvents sent
        self.last_errors: list[str] = []
        self._listening = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Future[Any]] = set()
        self.model = Model()  # the nodes written, filled when the address space is built
        self.conditions = AlarmConditions()  # the station's alarms as condition events
        self._lock = asyncio.Lock()  # variable writes and events in order
        self._t0 = 0.0
        self._order: list[Path] = []
        self._pki: Path | None = None
        self._boot_task: asyncio.Future[Any] | None = None
        self.started = threading.Event()  # the endpoint listens (for threads and other loops)
        self.failed: str | None = None
        self._made: Server | None = None
        self._roles = Roles(config)
        self.machine = VisionMachine(config, handler, self.model, self._spawn, self._error,
                                     lambda: self.server is not None)
        self.management = Management(handler, self.machine.show_recipe, self._error,
                                     config.query_spacing_s)

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> None:
        """Check at once what can fail (the NodeSets against their pinned hashes, the server
        certificate), then build and open the server in the background: importing the Machine
        Vision NodeSet takes seconds (docs/opcua.md), more than a station gives its links
        to start. Until the endpoint listens, ready() is False and status() says starting."""
        self._loop = asyncio.get_running_loop()
        self._t0 = time.monotonic()
        self._order = import_order()
        if any(p != "None" for p in self.config.security):
            self._pki = await make_certificate(self.config)
        self._boot_task = self._spawn(self._boot())

    async def wait_ready(self, timeout_s: float) -> None:
        """Until the endpoint listens (on the station's loop); raises what the start raised."""
        if self._boot_task is not None:
            await asyncio.wait_for(asyncio.shield(self._boot_task), timeout_s)

    async def _boot(self) -> None:
        cfg = self.config
        try:
            t = time.monotonic()
            server = self._made = Server(user_manager=Users(cfg))
            await server.init()
            self.load_s["init"] = time.monotonic() - t
            await set_up(server, cfg, self._roles, self._pki, self._error)
            t = time.monotonic()
            for path in self._order:
                await server.import_xml(str(path), strict_mode=path.name == MACHINE_VISION)
            await complete_definitions(server)
            self.load_s["nodesets"] = time.monotonic() - t
            t = time.monotonic()
            await build(server, self.model, self.machine, self.management, self._roles,
                        self.conditions)
            self.load_s["model"] = time.monotonic() - t
            await server.start()
        except Exception as err:
            self.failed = f"the OPC UA server did not start: {type(err).__name__}: {err}"
            log.error("%s", self.failed, exc_info=True)
            raise
        self.server = server
        self.port_bound = server.bserver.port if server.bserver is not None else cfg.port
        self.machine.state = "Operational"
        await self.machine.show_recipe()
        await self.management.show_configuration()
        self._listening = True
        self.handler.add_listener(self._on_result)
        self.load_s["total"] = time.monotonic() - self._t0
        self.started.set()
        log.info("OPC UA link on opc.tcp://%s:%d/mvpose (%s); started in %s s", cfg.host,
                 self.port_bound, ", ".join(cfg.security),
                 {k: round(v, 2) for k, v in self.load_s.items()})

    async def stop(self) -> None:
        self._listening = False  # the station has no remove_listener: the callback goes quiet
        await self.machine.end_continuous()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        made, self._made, self.server = self._made, None, None
        if made is not None and made.bserver is not None:  # it listens (or did)
            await made.stop()

    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("the OPC UA link is not started")
        return self.port_bound

    def ready(self) -> bool:
        return self.server is not None

    def status(self) -> dict[str, Any]:
        if self.server is None:
            starting = self._boot_task is not None and not self._boot_task.done()
            return {"running": False, "starting": starting, "error": self.failed}
        m = self.machine
        return {
            "running": True, "port": self.port_bound, "security": list(self.config.security),
            "state": m.state, "automatic_mode": m.auto_state, "triggers": m.triggers,
            "continuous": m.continuous is not None,
            "results_published": self.results, "alarms_published": self.conditions.sent,
            "start_s": {k: round(v, 2) for k, v in self.load_s.items()},
            "last_errors": self.last_errors[-5:],
        }

    def alarm_changed(self, notice: AlarmNotice) -> None:
        if self.server is not None:
            self._spawn(self._publish_alarm(notice))

    async def _publish_alarm(self, notice: AlarmNotice) -> None:
        async with self._lock:
            if self.server is not None:
                await self.conditions.publish(self.server, notice)

    def recipe_changed(self) -> None:
        if self.server is not None:
            self._spawn(self.machine.show_recipe())
            # a calibration activated elsewhere (REST) comes with the same call
            self._spawn(self.management.show_configuration())

    # ------------------------------------------------------------------ results
    def _on_result(self, event: ResultEvent) -> None:
        """The station's listener (on the station loop): publish on our loop."""
        loop = self._loop
        if self._listening and loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(lambda: self._spawn(self._publish(event)))

    async def _publish(self, r: ResultEvent) -> None:
        if self.server is None or self.model.evgen is None:
            return
        own, standard = v.result_fields(r, self.management.versions)
        async with self._lock:
            await publish(self.server, self.model, own, standard)
            self.results += 1

    # ------------------------------------------------------------------ helpers
    def _spawn(self, coro: Any) -> asyncio.Future[Any]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)

        def done(t: asyncio.Future[Any]) -> None:
            self._tasks.discard(t)
            if not t.cancelled() and (err := t.exception()) is not None:
                log.error("OPC UA link task failed: %r", err, exc_info=err)
                self._error(f"{type(err).__name__}: {err}")

        task.add_done_callback(done)
        return task

    def _error(self, text: str) -> None:
        self.last_errors = [*self.last_errors[-19:], text]
