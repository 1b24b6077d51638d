"""``clflow optimize``: material parameters from a guidance video's optical flow.

Each iteration: simulate (differentiable MPM) -> render the simulated flow from the guidance
camera -> masked flow loss against the video's flow -> adjoint -> one step on the
parameters' unconstrained variables z (log10 for moduli, bounded maps for ratios: see
clflow.mpm.parameterization): Adam with a cosine-decaying rate, or Levenberg-Marquardt with a
trust region (``optimize.method``). The loss may cover only the first
frames at first (``optimize.horizon``): a short horizon keeps the loss monotone far from the
optimum, where a long one has local minima (docs/pipeline.md). With
``optimize.estimate_velocity`` a velocity phase comes first: only the initial velocity (of
the one object, or of the objects it names) is optimised, over the first frames, with the material at its initial guess; the
main phase starts from that estimate. The steps are written out here in float64 so that the
optimiser's whole state (Adam's moments, the damping) goes into ``checkpoint.json`` after every
iteration; ``resume`` continues from it and
gives the same result as an uninterrupted run. A failed iteration (NaN, a simulation that blows
up, breaks the CFL limit, clamps particles at the grid's edge or needs more substeps than
``simulation.max_substeps``) is never accepted: it rolls back to the last good parameters,
halves the step and tries again (``rollbacks`` in metrics.json), or stops with the reason.
Before the first iteration the pre-flight checks (clflow.pipeline.preflight) print the
substeps and the predicted time, and refuse a run beyond the substep limit or a guidance
video that does not fit the scene (``force_video``: warn and record it instead).

Results in ``output/``: params.json, metrics.json, history.json, loss.png, comparison.mp4
(comparison_view1.mp4, ... for more guidance views), observed_flow.npz (the video's flow and
its confidence, computed once).

The package's modules, one part each; ``Optimization`` (driver) holds one object of each
part, and every part gets what it needs when it is made:

- problem: Problem, what is fitted (config, parameterisation, variables, prepared scenes
  per grid, guidance views, the boxes the phases stay in)
- objective: Objective, the loss, its gradient, the residuals' Jacobian and the flow
  estimator's calibration
- steps: Steps, Levenberg-Marquardt, Adam and the own-loss line search; their schedules
- iteration: Iterations, one iteration from a state to the next (rollbacks, convergence)
- search: SearchDesign, Search (the global phase) and StartPolish (a start's polish); the
  polishes mapped serially, or as Ray tasks (starts_on_ray)
- diagnostics: Diagnostics, identifiability, profiles and the grid check
- budget: the main grid a time budget affords (optimize.budget), predicted from timed runs
- results: Results, params.json, metrics.json and the comparison videos
- state: OptimizerState, Evaluation and the config digests; checkpoint: Checkpoint
- guidance: the guidance views, their videos' flow (cached) and the loss masks
- driver: Optimization, the parts put together and the loop over phases and iterations
"""

from clflow.pipeline.fit.driver import Optimization
from clflow.pipeline.fit.guidance import resampled_guidance
from clflow.pipeline.fit.results import parameter_unit
from clflow.pipeline.fit.search import starts_on_ray
from clflow.pipeline.fit.state import Evaluation, OptimizerState

__all__ = ["Evaluation", "Optimization", "OptimizerState", "parameter_unit", "resampled_guidance", "starts_on_ray"]
