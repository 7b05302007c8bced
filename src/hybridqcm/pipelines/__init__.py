"""Pipelines: the stages of make demo / noise / reproduce and their manifests."""
