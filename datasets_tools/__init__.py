"""Generators of the demo and of benchmark scenes (installed as clflow_datasets)."""
