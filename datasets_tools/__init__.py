"""Generators of clflow's demo scene and synthetic benchmark scenes (installed as
``clflow_datasets``): shapes, materials with ground-truth parameters, forces, cameras and
rendered guidance videos, so that tests and benchmarks share one path."""
