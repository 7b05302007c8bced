"""Compatibility: the old home of the LightningModules, split by issue 8 (one concept a module).

Kept so that code and notebooks importing ``hybridqcm.models.modules`` keep working; new code
imports from where each name lives now:

    models/physics_losses.py   physics_residual, physics_residual_loss, balanced_residual_loss, least_squares_p12
    models/schedule.py         one_cycle_lr (and the time-budget progress of a run)
    models/base.py             QCMModule, CheckpointMismatch, build_network, stored_model_class
    models/estimators.py       ParameterEstimator, LabelledEstimator, GaussianEstimator, PhysicsResidualEstimator
    models/signal_models.py    DenoisingAutoencoder, CompletionUNet
    models/checkpoint.py       MODULES (the classes the safe loader may build)

Checkpoints store only the class name (``hybridqcm_class``), never this module's path, so files
written before the split load unchanged through models.checkpoint.load_checkpoint.
"""

from hybridqcm.models.base import CheckpointMismatch, QCMModule, build_network, stored_model_class
from hybridqcm.models.checkpoint import MODULES
from hybridqcm.models.estimators import (
    GaussianEstimator,
    LabelledEstimator,
    ParameterEstimator,
    PhysicsResidualEstimator,
)
from hybridqcm.models.physics_losses import (
    balanced_residual_loss,
    least_squares_p12,
    physics_residual,
    physics_residual_loss,
)
from hybridqcm.models.schedule import one_cycle_lr
from hybridqcm.models.signal_models import CompletionUNet, DenoisingAutoencoder

__all__ = [
    "LabelledEstimator",
    "GaussianEstimator",
    "PhysicsResidualEstimator",
    "DenoisingAutoencoder",
    "CompletionUNet",
    "QCMModule",
    "ParameterEstimator",
    "CheckpointMismatch",
    "build_network",
    "stored_model_class",
    "physics_residual",
    "physics_residual_loss",
    "balanced_residual_loss",
    "least_squares_p12",
    "one_cycle_lr",
    "MODULES",
]
