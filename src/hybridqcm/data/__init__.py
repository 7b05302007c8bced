"""Datasets: HDF5 I/O (SPEC §5), sample generation and Lightning datamodules."""
