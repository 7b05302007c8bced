"""Networks (plain nn.Modules) and LightningModules of the estimators, denoiser and completion U-Net."""

from hybridqcm.models.base import QCMModule
from hybridqcm.models.estimators import LabelledEstimator, PhysicsResidualEstimator
from hybridqcm.models.gaussian_estimator import GaussianEstimator
from hybridqcm.models.networks import DenoisingCAE, ParameterCNN, SpectralCNN, UNet1d, count_parameters
from hybridqcm.models.physics_losses import least_squares_p12, physics_residual, physics_residual_loss
from hybridqcm.models.signal_models import CompletionUNet, DenoisingAutoencoder

__all__ = [
    "LabelledEstimator",
    "GaussianEstimator",
    "PhysicsResidualEstimator",
    "DenoisingAutoencoder",
    "CompletionUNet",
    "QCMModule",
    "ParameterCNN",
    "SpectralCNN",
    "DenoisingCAE",
    "UNet1d",
    "count_parameters",
    "physics_residual",
    "physics_residual_loss",
    "least_squares_p12",
]
