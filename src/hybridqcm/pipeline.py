"""Deprecated: moved to hybridqcm.apps.pipeline (the runner) and hybridqcm.apps.stages (stages, manifest)."""

from hybridqcm.apps.pipeline import main, run_pipeline  # noqa: F401
from hybridqcm.apps.stages import PIPELINES, Stage, demo_stages, load_manifest, reproduce_stages  # noqa: F401
