"""The one trigger interface every link speaks (python-can style): request, outcome, handler, ABC.

A link is how a controller reaches the station: Modbus/TCP for the PLC, OPC UA for cells and MES.
Each backend lives in a folder of its own (``drivers/links/<backend>/``) and is the only code that
knows its wire format (registers, word order, scaling; nodes and events), its settings model and
its twin. What crosses this seam is in the station's terms, and it is the only request/outcome
pair there is:

- a :class:`LinkRequest`: trigger id, view index, the robot's actual flange pose at full precision
  in the recipe's robot convention (``mvpose_core.transforms.to_robot`` form), part id, recipe;
- a :class:`LinkOutcome`: one result code from the one reason table (``mvpose_core.reasons``),
  the durable result id (the record's ``seq``: never reused, the same number in the record, the
  REST API and every link), the offset at full precision in the recipe's robot convention, 1σ;
  a recorded answer's outcome is derived from its :class:`~drivers.links.result.ResultEvent`;
- a :class:`~drivers.links.result.ResultEvent`: a recorded answer, as the station's listeners
  hear of it and its result queries (OPC UA GetResultById ...) return it.

The station implements :class:`StationHandler`; every answer it gives has a record with the same
code. A link that cannot get an answer (its own backstop timeout, a handler that raised) asks the
station to record that failure (:meth:`StationHandler.record_failure`) before it answers, so the
controller and the store never disagree.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, ClassVar, Protocol, TypeVar, runtime_checkable

from mvpose_core.transforms import RobotConvention

from .result import ResultEvent

S = TypeVar("S")
D = TypeVar("D")


@dataclass(frozen=True)
class LinkRequest:
    """One accepted trigger, in the station's terms."""

    link: str  # the backend's name ("modbus", "opcua", "rest")
    trigger_id: int  # chosen by the controller, echoed in the record
    view_index: int  # 0 = fixed station, all cameras; 1..n = a view of a robot-mounted rig
    robot_pose: tuple[float, ...] | None  # actual flange pose, recipe convention, full precision
    part_id: str  # VIN or data-matrix code
    recipe: int  # recipe number selected at the link (0: the station's selected recipe)


@dataclass(frozen=True)
class LinkOutcome:
    """The station's answer to one trigger."""

    result_code: int  # mvpose_core.reasons.Reason: 0 = OK
    result_id: int  # the record's seq; 0 for an intermediate view (no record)
    offset: tuple[float, ...] | None = None  # recipe convention, full precision; None unless OK
    sigma_trans_mm: float = 0.0
    sigma_rot_deg: float = 0.0
    processing_ms: float = 0.0
    views_done: int = 1
    final: bool = True  # False: an intermediate view of a robot-mounted rig is done

    @classmethod
    def from_event(cls, event: ResultEvent, processing_ms: float) -> LinkOutcome:
        """The answer to the trigger whose record ``event`` is; ``processing_ms``: the time
        to the answer as the station measured it."""
        return cls(result_code=event.reason_code, result_id=event.result_id,
                   offset=event.robot_offset, sigma_trans_mm=event.sigma_mm or 0.0,
                   sigma_rot_deg=event.sigma_deg or 0.0, processing_ms=processing_ms,
                   views_done=max(1, event.views or 1), final=event.final)


@dataclass(frozen=True)
class VerifyOutcome:
    """The station's answer to a calibration verify: the taught reference part measured again
    and its 6-DoF difference to the taught pose judged against the recipe's limits."""

    result_code: int  # 0: measured and judged (``passed`` is the verdict); else why not
    result_id: int  # the verify record's seq (0: nothing was recorded)
    passed: bool = False
    difference: tuple[float, ...] | None = None  # implied offset, recipe convention
    displacement_mm: float = 0.0  # at the grasp point
    rotation_deg: float = 0.0
    limit_mm: float = 0.0
    limit_deg: float = 0.0
    message: str = ""


@dataclass(frozen=True)
class AlarmNotice:
    """One transition of a station alarm (raised, acknowledged, cleared), as the station's store
    keeps it (docs/alarms.md); a link that shows alarms (OPC UA conditions) gets each one
    through :meth:`Link.alarm_changed`."""

    event: str  # raised | acknowledged | cleared
    event_id: int  # the transition's id: increasing, never reused
    alarm_id: int
    source: str  # e.g. link:modbus, camera:left1, store
    code: str  # e.g. LINK_DOWN
    priority: str  # high | medium | low
    text: str
    active: bool
    acknowledged: bool
    acked_by: str | None
    at: datetime  # when the transition happened (UTC)

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "at": self.at.isoformat()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AlarmNotice:
        return cls(**{**data, "at": datetime.fromisoformat(data["at"])})


@dataclass(frozen=True)
class HandEyeOutcome:
    """The station's answer to a step of a robot-driven hand-eye session (begin, add pose,
    calculate): the code (``mvpose_core.calibration.session.HandEyeCode``, 0 = done), how many
    poses the session holds, the pose the step was about (1-based; 0: none), and after a
    calculate the stored calibration version waiting for activation with its figures."""

    code: int
    poses: int = 0
    pose: int = 0
    version: int = 0  # the stored calibration version (0: none yet)
    sigma_mm: float = 0.0  # 1σ of the hand-eye translation (RSS) and rotation
    sigma_deg: float = 0.0
    holdout_rms_px: float = 0.0  # the held-out poses' reprojection RMS
    holdout_mm: float = 0.0  # largest held-out flange pose error (mm, deg)
    holdout_deg: float = 0.0
    message: str = ""


@dataclass(frozen=True)
class ResultQuery:
    """Which stored records a link asks for: every filter optional (None), oldest first from
    ``start`` (0-based), at most ``limit``."""

    part_id: str | None = None
    recipe: str | None = None  # recipe name
    trigger_id: int | None = None
    ok: bool | None = None
    reason_code: int | None = None
    start: int = 0
    limit: int = 100


@dataclass(frozen=True)
class RecipeInfo:
    """One recipe of the station as it is now."""

    number: int  # what a controller selects it by
    name: str
    version: int  # the active stored version
    sha256: str
    selected: bool


@dataclass(frozen=True)
class CalibrationInfo:
    """One stored version of the station's calibration (the one named after the station)."""

    version: int
    calibration_id: str  # the calibration file's own id
    sha256: str  # the calibration file's content hash
    created_at: datetime
    created_by: str
    comment: str
    active: bool  # the store's active version (the station measures with it from the next trigger)
    in_use: bool  # the version the station measures with now


class StationHandler(Protocol):
    """What the station gives every link. Calls come on the link's event loop."""

    def measure(self, request: LinkRequest) -> Awaitable[LinkOutcome]:
        """Measure one trigger; the station answers within its deadline + 1 s, whatever the store
        or the pipeline do (a recorded TIMEOUT at worst). A handler may start the work in the
        call itself and return a future."""
        ...

    def record_failure(self, request: LinkRequest, code: int, message: str,
                       processing_ms: float) -> Awaitable[int]:
        """Record an answer the link gives on its own (its backstop timeout, a failed handler):
        returns the result id, 0 if not even that could be recorded."""
        ...

    async def select_recipe(self, number: int) -> int:
        """0 when recipe ``number`` is now selected, else a Reason code."""
        ...

    async def teach_reference(self, by: str) -> int:
        """0 when the next final OK result will become the reference (zero offset)."""
        ...

    async def reset(self) -> None:
        """Drop a half-done multi-view sequence."""
        ...

    async def verify(self, link: str, by: str) -> VerifyOutcome:
        """Measure the taught reference part now (a trigger recorded as the verify record) and
        judge its difference to the taught pose."""
        ...

    async def handeye_begin(self, link: str, by: str, holdout: int | None = None
                            ) -> HandEyeOutcome:
        """Begin a robot-driven hand-eye session (any earlier one is dropped); ``holdout``
        poses are kept out of the solve to check it (None: the default, 3)."""
        ...

    async def handeye_add_pose(self, link: str, by: str, robot_pose: tuple[float, ...] | None
                               ) -> HandEyeOutcome:
        """Capture the board from every camera of the rig at the robot's actual flange pose
        (recipe convention, as a trigger's) and keep it in the session."""
        ...

    async def handeye_calculate(self, link: str, by: str) -> HandEyeOutcome:
        """Solve the session and store the result as a calibration version waiting for an
        engineer's activation."""
        ...

    def convention(self) -> RobotConvention:
        """The selected recipe's robot convention (how poses cross the link)."""
        ...

    def selected_recipe(self) -> int:
        """The selected recipe's number (0: none)."""
        ...

    async def unselect_recipe(self) -> int:
        """0 when no recipe is selected any more (a trigger naming no recipe is then refused
        with UNKNOWN_RECIPE until one is selected), else a Reason code."""
        ...

    async def recipes(self) -> list[RecipeInfo]:
        """Every recipe of the station, by number."""
        ...

    async def get_result(self, result_id: int) -> ResultEvent | None:
        """The stored record with seq ``result_id``, None if there is none. Queries run off the
        station's loop and trigger thread (they never delay a trigger)."""
        ...

    async def find_results(self, query: ResultQuery) -> tuple[list[ResultEvent], int]:
        """The page of stored records ``query`` asks for, and how many match in all."""
        ...

    async def calibrations(self) -> list[CalibrationInfo]:
        """Every stored version of the station's calibration, oldest first."""
        ...

    async def activate_calibration(self, version: int, by: str) -> tuple[int, str]:
        """Activate stored calibration ``version`` (checked as an upload is), measured with
        from the next trigger: (0, "") or (a Reason code, what is wrong)."""
        ...

    def add_listener(self, listen: Callable[[ResultEvent], None]) -> None:
        """Call ``listen(event)`` after every recorded answer, whichever link or client caused
        it, a few milliseconds after the answer (on the station's own thread: hand it over to
        your own loop)."""
        ...


@runtime_checkable
class AnswersEarly(Protocol):
    """A StationHandler that can also tell a trigger's outcome on the thread that recorded it,
    before its awaitable ends on the link's loop (a link in a process of its own sends it on
    from there: drivers/links/process/)."""

    def measure_early(self, request: LinkRequest, answered: Callable[[LinkOutcome], None]
                      ) -> Awaitable[LinkOutcome]:
        """:meth:`StationHandler.measure`, and ``answered(outcome)`` called once with the same
        outcome as soon as it is recorded, on the recording thread (it must not block)."""
        ...

    def measure_posted(self, request: LinkRequest, answered: Callable[[LinkOutcome], None]
                       ) -> concurrent.futures.Future[LinkOutcome]:
        """:meth:`measure_early` called from any thread (a link's reader of its process's
        trigger requests): the trigger starts without waiting for the station's loop; the
        future ends with the same outcome, or the error, on the thread that decided it."""
        ...


def relay(src: asyncio.Future[S], dst: asyncio.Future[D],
          convert: Callable[[S], D | None]) -> None:
    """When ``src`` ends, end ``dst`` the same way (its result through ``convert``; a result
    converted to None leaves ``dst`` to someone else), unless ``dst`` has ended already."""

    def done(f: asyncio.Future[S]) -> None:
        if dst.done():
            return
        if f.cancelled():
            dst.cancel()
        elif (err := f.exception()) is not None:
            dst.set_exception(err)
        elif (value := convert(f.result())) is not None:
            dst.set_result(value)

    src.add_done_callback(done)


class Link(ABC):
    """One link backend, started and stopped on the event loop it serves on (the station's, or
    its child process's own: ``drivers.links.OWN_PROCESS``)."""

    name: ClassVar[str]

    def __init__(self, config: Any, handler: StationHandler) -> None:
        self.config = config
        self.handler = handler

    @abstractmethod
    async def start(self) -> None:
        """Open the link (listen, register); raises when it cannot."""

    @abstractmethod
    async def stop(self) -> None:
        """Close every connection; running measurements are cancelled."""

    @abstractmethod
    def status(self) -> dict[str, Any]:
        """What the station's status page shows of this link (JSON-able)."""

    @abstractmethod
    def ready(self) -> bool:
        """The link is up (listening, connected or registered as the backend needs)."""

    def line_state(self) -> str | None:
        """The handshake state this link shows the line's PLC (the station status's ``state``
        and ``plc`` entries come from the first link that has one); None: it has none."""
        return None

    def recipe_changed(self) -> None:  # noqa: B027 - optional hook
        """The selected recipe (or its robot convention) changed outside this link."""

    def alarm_changed(self, notice: AlarmNotice) -> None:  # noqa: B027 - optional hook
        """A station alarm was raised, acknowledged or cleared (on the link's loop)."""
