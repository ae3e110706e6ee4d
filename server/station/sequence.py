"""What a trigger is before the pipeline: the recipe, the view, the robot-mounted sequence.

Used only from the station's single trigger thread, so the views gathered so far need no lock.
A robot-mounted rig's part is measured over several triggers (one per view, in the recipe's view
order); every view but the last answers VIEW_DONE, the last one measures from all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.links import LinkRequest
from mvpose_core.reasons import Reason
from mvpose_core.station import StationConfig
from mvpose_core.transforms import from_robot
from server.pipeline import Pipeline, StationResult, ViewCapture
from server.recipes import ActiveRecipe, RecipeBook


@dataclass(frozen=True)
class Step:
    """What one trigger came to: a final verdict, an intermediate view, or a refusal."""

    recipe: ActiveRecipe
    final: bool
    views_done: int
    result: StationResult | None = None  # the final verdict of a measured part
    refused: tuple[int, str] | None = None  # (Reason, message): nothing could be measured


class ViewSequence:
    """Resolves recipe and view of each trigger and gathers a robot-mounted rig's views."""

    def __init__(self, station: StationConfig, pipeline: Pipeline, book: RecipeBook) -> None:
        self.station = station
        self.pipeline = pipeline
        self.book = book
        self.views: list[ViewCapture] = []

    def clear(self) -> None:
        self.views = []

    def run(self, req: LinkRequest, t0: float) -> Step:
        selected = self.book.selected
        recipe = self.book.by_number(req.recipe) if req.recipe else selected
        if recipe is None:
            fallback = selected or next(iter(self.book.recipes.values()))
            text = (f"recipe number {req.recipe} is not in the station file" if req.recipe else
                    "no recipe is selected (the PLC's SELECT_RECIPE or OPC UA PrepareRecipe "
                    "selects one)")
            return Step(fallback, True, 0, refused=(Reason.UNKNOWN_RECIPE, text))
        views = sorted({s.view for s in recipe.config.sightings})
        view = req.view_index or (views[0] if len(views) == 1 else 0)
        if view not in views:
            self.views = []
            return Step(recipe, True, 0, refused=(
                Reason.UNKNOWN_VIEW,
                f"view index {req.view_index} is not among the recipe's views {views}"))
        flange = None
        if req.robot_pose is not None and self.station.robot_mounted:
            flange = from_robot(req.robot_pose, recipe.config.robot_convention)
        vcap = self.pipeline.capture_view(view, req.trigger_id, recipe.config, flange, t0)
        if view == views[0]:
            self.views = []
        self.views = [v for v in self.views if v.view != view] + [vcap]
        if view != views[-1]:
            return Step(recipe, False, len(self.views))
        gathered, self.views = self.views, []
        result = self.pipeline.conclude(t0=t0, recipe=recipe, views=gathered)
        return Step(recipe, True, len(gathered), result=result)

