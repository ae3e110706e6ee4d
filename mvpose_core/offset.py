"""Robot frame offsets from the taught and the measured part pose (paper eq. 5–6).

The grasp frame G is rigid to the part: ``T_rf_from_g = T_rf_from_pf · T_pf_from_grasp``. At the
taught reference the part is at ``T_rf_from_pf0`` and the robot grasps at ``T_rf_from_g0``; now
it is at ``T_rf_from_pf``. Two equivalent offsets move the taught grasp onto the new one:

* base-frame offset (a user frame / "frame offset" on most controllers), left-multiplied::

      Δ = T_rf_from_pf · T_rf_from_pf0⁻¹,    T_rf_from_g = Δ · T_rf_from_g0

  Δ does not depend on the grasp point (it is the part's motion written in RF);
* tool-frame offset (a tool offset), right-multiplied::

      D = T_g0_from_g = T_rf_from_g0⁻¹ · T_rf_from_g,    T_rf_from_g = T_rf_from_g0 · D

Relation to the paper's eq. 6. The paper writes "A→B T" for our ``T_b_from_a`` and applies its
offset to ``T_gf_from_rf`` (eq. 5: ``T_gfi_from_rf = Δ_paper · T_gf0_from_rf``), so eq. 6,
``Δ_paper = T_pf_from_gf⁻¹ · T_cf1_from_pfi⁻¹ · T_cf1_from_pf0 · T_pf_from_gf``, is
``T_gfi_from_gf0 = D⁻¹``: the inverse of our tool-frame offset, and
``Δ = T_rf_from_g0 · Δ_paper⁻¹ · T_rf_from_g0⁻¹``. :func:`paper_eq6` computes it literally and the
tests check these identities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvpose_core.transforms import (
    Array,
    RobotConvention,
    compose,
    invert,
    rotation_angle_deg,
    to_robot,
)


def base_frame_offset(T_rf_from_pf: Array, T_rf_from_pf0: Array) -> Array:
    """Δ with ``T_rf_from_g = Δ · T_rf_from_g0`` for every frame g rigid to the part."""
    return compose(T_rf_from_pf, invert(T_rf_from_pf0))


def tool_frame_offset(T_rf_from_pf: Array, T_rf_from_pf0: Array, T_pf_from_grasp: Array) -> Array:
    """D = ``T_g0_from_g`` with ``T_rf_from_g = T_rf_from_g0 · D``."""
    T_rf_from_g0 = compose(T_rf_from_pf0, T_pf_from_grasp)
    T_rf_from_g = compose(T_rf_from_pf, T_pf_from_grasp)
    return compose(invert(T_rf_from_g0), T_rf_from_g)


def paper_eq6(T_cf1_from_pf0: Array, T_cf1_from_pfi: Array, T_pf_from_gf: Array) -> Array:
    """The paper's eq. 6 written literally in our names: ``T_gfi_from_gf0`` (= D⁻¹)."""
    return compose(invert(T_pf_from_gf), invert(T_cf1_from_pfi), T_cf1_from_pf0, T_pf_from_gf)


@dataclass(frozen=True)
class FrameOffset:
    """Both offsets, as matrices and in a robot convention, and how far the grasp moved."""

    T_rf_offset: Array  # Δ (base frame), 4x4
    T_tool_offset: Array  # D = T_g0_from_g (tool frame), 4x4
    convention: RobotConvention
    base: Array  # Δ in ``convention``
    tool: Array  # D in ``convention``
    grasp_displacement_mm: float  # |t_g − t_g0|: how far the grasp point moved
    rotation_deg: float  # rotation angle of the part (same for Δ and D)


def frame_offsets(
    T_rf_from_pf: Array,
    T_rf_from_pf0: Array,
    T_pf_from_grasp: Array,
    convention: RobotConvention | str = RobotConvention.FANUC,
) -> FrameOffset:
    """Base- and tool-frame offsets for a part measured at ``T_rf_from_pf``."""
    conv = RobotConvention(convention)
    delta = base_frame_offset(T_rf_from_pf, T_rf_from_pf0)
    D = tool_frame_offset(T_rf_from_pf, T_rf_from_pf0, T_pf_from_grasp)
    return FrameOffset(
        T_rf_offset=delta,
        T_tool_offset=D,
        convention=conv,
        base=to_robot(delta, conv),
        tool=to_robot(D, conv),
        grasp_displacement_mm=float(np.linalg.norm(D[:3, 3])),
        rotation_deg=rotation_angle_deg(delta[:3, :3]),
    )
