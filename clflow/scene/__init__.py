"""From a Gaussian-splat scene to a simulation and back: the scene config (``config``), the
splats in the simulation frame with the object's selection and the guidance camera
(``load``), filling the selected object with particles (``filling``), and deforming its
Gaussians by the simulated deformation gradients (``deform``)."""
