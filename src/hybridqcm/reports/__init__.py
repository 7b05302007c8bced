"""Reports: tables, metrics files, plots and TensorBoard summaries of runs (above estimation, below apps)."""
