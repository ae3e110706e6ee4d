"""How the station process opens and runs its station (the station file says what the hardware
is): shared by the station's rooms (server.station.core and its collaborators)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from server.pipeline import PipelineOptions


@dataclass(frozen=True)
class StationOptions:
    """How the station opens its hardware (the station file says what the hardware is)."""

    pipeline: PipelineOptions = field(default_factory=PipelineOptions)
    sim_seed: int = 0  # the simulated scene's generator (kind: sim cameras)
    sim_render: Any = None  # drivers.cameras.RenderOptions for the simulated scene
    camera_ready_s: float = 10.0
    store_settle_s: float = 5.0  # the longest wait for the journal's zeros ahead before ready
    # Simulated cameras: render the part at the recipe's reference pose at start-up, so that a
    # served simulated station has something to measure (tests and the demo move it themselves).
    sim_part_at_reference: bool = False
    # Simulated cameras: keep the renderings of this many recent part poses, so a rehearsal
    # that moves the part back to one of them swaps frames instead of rendering (the station
    # benchmark cycles its part over a few poses within the tolerance, one per trigger).
    sim_keep_poses: int = 0
    # The watchdog's margin past the deadline: a trigger not recorded by then is answered with
    # a recorded TIMEOUT (the link's own backstop comes a second later).
    answer_margin_s: float = 1.0
    # Listeners (observers: the OPC UA link, whose process gets the result over its socket) hear
    # of a result this long after its append, when the answering link has answered: handing it
    # over holds the GIL.
    observer_delay_s: float = 0.005
