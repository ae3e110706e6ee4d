"""Station-file settings of the uncertainty model: detector noise pooling and calibration 1σ.

How the figures are used is in :mod:`mvpose_core.uncertainty` and docs/engine.md ("Uncertainty
model"). Every 1σ here is an RSS figure, as the calibration reports give it: ``mm`` is the RMS
length of the translation error, ``deg`` the RMS rotation angle; the error is taken isotropic
(each axis ``mm/√3``, ``deg/√3``).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mvpose_core.transforms import Array


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PoseSigma(_Model):
    """1σ of a transform (RSS over the axes): translation in mm, rotation in degrees."""

    mm: float = Field(0.0, ge=0, description="RMS length of the translation error, mm")
    deg: float = Field(0.0, ge=0, description="RMS rotation angle of the error, degrees")

    @property
    def is_zero(self) -> bool:
        return self.mm == 0.0 and self.deg == 0.0

    def covariance(self) -> Array:
        """6x6 over the right perturbation (ω [rad], v [mm]), isotropic per block."""
        r2 = np.radians(self.deg) ** 2 / 3.0
        t2 = self.mm**2 / 3.0
        return np.diag([r2, r2, r2, t2, t2, t2])


class UncertaintyConfig(_Model):
    """``uncertainty:`` in a station file (every field optional)."""

    detector_prior_dof: float = Field(
        0.0, ge=0,
        description="weight of the recipe's detector_noise_px in the detector σ, in degrees of "
        "freedom (0: from the residuals alone; large: the a-priori value alone)",
    )
    robot_repeatability: PoseSigma = Field(
        PoseSigma(), description="1σ of the flange pose at each view (robot-mounted rigs)"
    )
    rigs: dict[str, PoseSigma] = Field(
        default_factory=dict,
        description="1σ of each rig's mount pose: hand-eye T_gf_from_rig (robot) or "
        "T_rf_from_rig (fixed); a calibration file's report replaces it",
    )
    cameras: dict[str, PoseSigma] = Field(
        default_factory=dict, description="1σ of each camera's T_rig_from_cf (rig extrinsics)"
    )
