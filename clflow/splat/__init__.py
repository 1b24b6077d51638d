"""Gaussian splats: 3DGS files, the Gaussians container, cameras and rendering."""
