"""From a Gaussian-splat scene to a simulation and back: filling the selected object with
particles, and deforming its Gaussians by the simulated deformation gradients."""
