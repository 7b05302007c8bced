"""The hybrid estimator, under its historical module name: networks in front, Gauss-Newton behind.

    (â3, â2) --CAE?--> (a3, a2) --U-Net?--> completed (a2, a1) from (a3, p_u u)
             --CNN--> (p1, p2) initial values --> GN stage(s) on the (completed) residual

The two halves live in their own modules: :mod:`hybridqcm.estimation.front` (the networks as a
LightningModule, :class:`HybridEstimator`, and the checkpoint checks) and
:mod:`hybridqcm.estimation.refinement` (the :class:`GaussNewtonRefinement` callback). This module
re-exports both for code written against it; the package imports from the two modules directly::

    trainer.predict(HybridEstimator(cnn_ckpt=...), loader, callbacks=[GaussNewtonRefinement(stages)])
"""

from __future__ import annotations

from .front import (
    BASE_EXCITATION,
    CHANNELS,
    KIND_CLASSES,
    CheckpointKindError,
    HybridEstimator,
    check_networks,
    checkpoint_class,
    equation_error_params,
    load_network,
)
from .refinement import GaussNewtonRefinement, GaussNewtonStage
from .refinement_result import RefinementResult

__all__ = [
    "BASE_EXCITATION",
    "CHANNELS",
    "KIND_CLASSES",
    "CheckpointKindError",
    "GaussNewtonRefinement",
    "GaussNewtonStage",
    "HybridEstimator",
    "RefinementResult",
    "check_networks",
    "checkpoint_class",
    "equation_error_params",
    "load_network",
]
