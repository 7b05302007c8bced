"""Deprecated: moved to hybridqcm.testing (test fixtures are not estimation code); this alias goes once no test uses it."""
from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints, write_dataset  # noqa: F401
