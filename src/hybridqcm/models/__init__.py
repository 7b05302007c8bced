"""Networks (plain nn.Modules) and LightningModules of the estimators, denoiser and completion U-Net."""

from hybridqcm.models.modules import (
    CheckpointMismatch,
    CompletionUNet,
    DenoisingAutoencoder,
    GaussianEstimator,
    LabelledEstimator,
    PhysicsResidualEstimator,
    QCMModule,
    least_squares_p12,
    physics_residual,
    physics_residual_loss,
)
from hybridqcm.models.networks import DenoisingCAE, ParameterCNN, UNet1d, count_parameters

__all__ = [
    "LabelledEstimator",
    "GaussianEstimator",
    "PhysicsResidualEstimator",
    "DenoisingAutoencoder",
    "CompletionUNet",
    "QCMModule",
    "CheckpointMismatch",
    "ParameterCNN",
    "DenoisingCAE",
    "UNet1d",
    "count_parameters",
    "physics_residual",
    "physics_residual_loss",
    "least_squares_p12",
]
