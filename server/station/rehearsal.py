"""A rehearsal on simulated cameras: move the simulated part, as the demo's PLC twin does.

Only a station whose cameras are simulated (``kind: sim``) has a scene to move; the part is put
at an offset from the active recipe's reference, in the recipe's robot convention (what the
station should then measure), and every camera of every view is rendered there at once. The
rendering runs on the caller's thread, between triggers: a trigger that arrives meanwhile sees
the old pose or the new one, camera by camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from mvpose_core.transforms import compose, from_robot
from server.errors import ConflictError, InvalidInputError
from server.station.core import Station


def move_part(station: Station, offset: Sequence[float]) -> dict[str, Any]:
    """Put the simulated part at ``offset`` from the active recipe's reference and render it."""
    scene = station.scene
    if scene is None:
        raise ConflictError("the station's cameras are not simulated (driver kind: sim): a "
                            "rehearsal moves only a simulated part")
    active = station.active
    if active is None:
        raise ConflictError("the station has no recipe selected")
    recipe = active.config
    if recipe.name != scene.recipe.name:
        raise ConflictError(f"the simulated part is recipe {scene.recipe.name!r}; the station "
                            f"measures {recipe.name!r}: select {scene.recipe.name!r} first")
    conv = recipe.robot_convention
    try:
        delta = from_robot(list(offset), conv)
    except (TypeError, ValueError) as err:
        raise InvalidInputError(f"offset: {err}") from None
    T_rf_from_pf = compose(delta, recipe.T_rf_from_pf0.matrix)
    try:
        scene.set_part_pose(T_rf_from_pf)
    except ValueError as err:  # the renderer refuses a pose it cannot draw
        raise InvalidInputError(f"offset {list(offset)}: {err}") from None
    return {"recipe": recipe.name, "recipe_version": active.version,
            "convention": conv.value, "offset": [float(v) for v in offset],
            "T_rf_from_pf": T_rf_from_pf.tolist()}
