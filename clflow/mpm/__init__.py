"""MLS-MPM forward simulation on OpenCL devices (kernels in kernels_cl/mpm/).

Public API: :class:`Simulator`, :class:`MaterialSpec`, :class:`Grid`, the boundary
conditions and drivers of :mod:`clflow.mpm.boundaries`; :mod:`clflow.mpm.substep` holds the
four substep kernels for the adjoint.
"""

from clflow.mpm.boundaries import (
    Box,
    BoxRegion,
    Force,
    HalfSpace,
    RotatingCylinder,
    SphereRegion,
    layer_release_times,
)
from clflow.mpm.simulator import (
    MaterialSpec,
    SimulationError,
    SimulationSpec,
    Simulator,
    StabilityWarning,
    Trajectory,
)
from clflow.mpm.substep import Grid, Particles, State, SubstepKernels, SubstepTape

__all__ = [
    "Box",
    "BoxRegion",
    "Force",
    "Grid",
    "HalfSpace",
    "MaterialSpec",
    "Particles",
    "RotatingCylinder",
    "SimulationError",
    "SimulationSpec",
    "Simulator",
    "SphereRegion",
    "StabilityWarning",
    "State",
    "SubstepKernels",
    "SubstepTape",
    "Trajectory",
    "layer_release_times",
]
