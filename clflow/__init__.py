"""clflow: OpenCL-portable MLS-MPM and Gaussian splatting with a PyTorch front end.

Importing :mod:`clflow` is cheap; submodules (``clflow.runtime``, ...) import torch and
pyopencl when they are used.
"""

__version__ = "0.1.0"
