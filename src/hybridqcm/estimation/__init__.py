"""Parameter estimation: forward-mode sensitivities, batched Gauss-Newton / LM, hybrid pipeline."""

from hybridqcm.estimation._kernels import compiled_loops
from hybridqcm.estimation.front import (
    HybridEstimator,
    check_networks,
    equation_error_params,
)
from hybridqcm.estimation.problems import LeastSquaresProblem
from hybridqcm.estimation.refinement import GaussNewtonRefinement, GaussNewtonStage, RefinementSettings
from hybridqcm.estimation.restarts import Restarts
from hybridqcm.estimation.sensitivity import (
    EulerSensitivity,
    accelerations_and_jacobian,
    euler_accelerations,
    euler_sensitivities,
)
from hybridqcm.estimation.solver import (
    SOLVERS,
    STATUS_LABELS,
    GaussNewton,
    LevenbergMarquardt,
    NonlinearLeastSquares,
    SolverConfig,
    SolverResult,
    SolverStatus,
    build_solver,
)
from hybridqcm.estimation.weighting import NoiseWeighting

__all__ = [
    "compiled_loops",
    "EulerSensitivity",
    "accelerations_and_jacobian",
    "euler_accelerations",
    "euler_sensitivities",
    "SOLVERS",
    "STATUS_LABELS",
    "GaussNewton",
    "LeastSquaresProblem",
    "LevenbergMarquardt",
    "NonlinearLeastSquares",
    "SolverConfig",
    "SolverResult",
    "SolverStatus",
    "build_solver",
    "GaussNewtonRefinement",
    "GaussNewtonStage",
    "HybridEstimator",
    "equation_error_params",
    "check_networks",
    "RefinementSettings",
    "NoiseWeighting",
    "Restarts",
]
