"""Gaussian splatting: 3DGS files, cameras and the differentiable OpenCL rasteriser."""
