"""MLS-MPM forward simulation on OpenCL devices (kernels in kernels_cl/mpm/).

Public API: :class:`Simulator`, :class:`MaterialSpec`, :class:`Grid`, the boundary
conditions and drivers of :mod:`clflow.mpm.boundaries` (force stages act on a
:class:`clflow.regions.Region`, re-exported here); :mod:`clflow.mpm.substep` holds the
four substep kernels for the adjoint.
"""

from clflow.mpm.boundaries import (
    Box,
    Force,
    HalfSpace,
    RotatingCylinder,
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
from clflow.regions import Region

__all__ = [
    "Box",
    "Force",
    "Grid",
    "HalfSpace",
    "MaterialSpec",
    "Particles",
    "Region",
    "RotatingCylinder",
    "SimulationError",
    "SimulationSpec",
    "Simulator",
    "StabilityWarning",
    "State",
    "SubstepKernels",
    "SubstepTape",
    "Trajectory",
    "layer_release_times",
]
