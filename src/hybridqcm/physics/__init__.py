"""Physics of the passenger-based quarter-car model: parameters, prior, road, integrators."""

from hybridqcm.physics.integrators import METHODS, SemiExplicitEuler, Trajectory, simulate
from hybridqcm.physics.parameters import (
    CHANNELS,
    PARAM_MEANINGS,
    PARAM_NAMES,
    REFERENCE_VEHICLE,
    PhysicalConstants,
    euler_step_matrix,
    is_stable,
    matrices_to_params,
    occupant_mass,
    params_to_matrices,
    reference_params,
    road_gain,
    system_matrix,
)
from hybridqcm.physics.prior import PhysicalPrior, PriorDraw, ThesisPrior, build_prior
from hybridqcm.physics.road import ROAD_CLASSES, RoadProfile, road_class_index, road_class_phi0

__all__ = [
    "CHANNELS",
    "PARAM_NAMES",
    "PARAM_MEANINGS",
    "REFERENCE_VEHICLE",
    "PhysicalConstants",
    "euler_step_matrix",
    "is_stable",
    "matrices_to_params",
    "occupant_mass",
    "params_to_matrices",
    "reference_params",
    "road_gain",
    "system_matrix",
    "PhysicalPrior",
    "PriorDraw",
    "ThesisPrior",
    "build_prior",
    "ROAD_CLASSES",
    "RoadProfile",
    "road_class_index",
    "road_class_phi0",
    "METHODS",
    "SemiExplicitEuler",
    "Trajectory",
    "simulate",
]
