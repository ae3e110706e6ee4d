"""A link whose PLC side is the shared handshake: what the station asks of every such backend
(its line state and a recipe selected elsewhere) answered once from its runner."""

from __future__ import annotations

from typing import Any

from ..base import Link, StationHandler
from .runner import HandshakeRunner


class HandshakeLink(Link):
    """Base of the cyclic links (EtherNet/IP, S7, PROFINET): ``runner`` is set while it runs."""

    def __init__(self, config: Any, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.runner: HandshakeRunner | None = None

    def line_state(self) -> str | None:
        return None if self.runner is None else self.runner.machine.state.name

    def recipe_changed(self) -> None:
        if self.runner is not None:
            self.runner.recipe_selected(self.handler.selected_recipe(),
                                        self.handler.convention().code)
