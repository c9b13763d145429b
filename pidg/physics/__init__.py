"""Physics of PIDG: the Cauchy momentum residual (CMR) on the time-evolving material field.

``PhysicsConfig`` holds its settings (``--physics.*``). The field itself is ``pidg.models.material_field``
(``--material.*``); ``cmr_loss`` is the block-sampled L_CMR the trainer adds every step; ``momentum_residual``
works on any ``FieldJet`` (``pidg.models.jet``); ``velocity_mismatch`` is the optional particle-velocity
consistency term (``--physics.lambda_kinematic``), against ``particle_velocity`` or ``particle_step_velocity``.
"""
from pidg.physics.cmr import (
    STAT_NAMES,
    CMRResult,
    JetField,
    cmr_loss,
    convective_acceleration,
    material_acceleration,
    momentum_residual,
    sample_rows,
    stress_divergence,
)
from pidg.physics.config import KinematicTarget, KinematicTimes, PhysicsConfig, PhysicsKind
from pidg.physics.consistency import particle_step_velocity, particle_velocity, velocity_mismatch

__all__ = [
    "STAT_NAMES", "CMRResult", "JetField", "KinematicTarget", "KinematicTimes", "PhysicsConfig", "PhysicsKind", "cmr_loss",
    "convective_acceleration", "material_acceleration", "momentum_residual", "particle_step_velocity",
    "particle_velocity", "sample_rows", "stress_divergence", "velocity_mismatch",
]
