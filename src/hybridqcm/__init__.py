"""hybridqcm: hybrid neural-network + Gauss-Newton parameter estimation for a passenger-based quarter-car model."""

__version__ = "0.1.0"
