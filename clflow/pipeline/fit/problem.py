"""What an optimisation fits: the config, its parameterisation and variables, the scene
prepared on each grid it runs on, and the guidance views."""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
import warnings

import torch

from clflow.errors import InputError
from clflow.flow.scene_flow import render_scene_flows
from clflow.mpm import StabilityWarning
from clflow.pipeline.fit.guidance import View
from clflow.pipeline.fit.state import OptimizerState
from clflow.pipeline.forward import Prepared, prepare, scene_values
from clflow.pipeline.simulation import ObjectValues, build_simulator, object_masks, run
from clflow.scene.config import (
    TIME_SCALE,
    VELOCITY,
    SceneConfig,
    is_velocity_component,
    split_parameter,
    velocity_names,
)
from clflow.splat.device_scene import DeviceScene

log = logging.getLogger(__name__)


def parameterizations(cfg: SceneConfig):
    """Parameter name -> its parameterisation, for each of optimize.parameters but a
    velocity: a material's (with several objects OBJECT.PARAM, of that object's material)
    and the scene's time_scale."""
    from clflow.mpm.parameterization import Parameterization, parameterization

    names = cfg.optimize.parameters
    if not names:
        raise InputError(f"{cfg.source}: optimize.parameters is empty: name the parameters to optimise")
    out = {}
    for name in names:
        if name == TIME_SCALE.name:
            out[name] = Parameterization(TIME_SCALE)
            continue
        k, param = split_parameter(cfg.objects, name)
        if param != VELOCITY:
            out[name] = parameterization(cfg.objects[k].material.type, param)
    return out


class Problem:
    """What an optimisation of ``cfg`` (a concrete material, its guidance video made) fits.

    ``params``: material parameter name -> parameterisation (z <-> SI); ``main_variables``
    the z names the main phase optimises, ``velocity_variables`` the velocity phase's,
    ``variables`` every z name; ``total_iterations`` of the run, the velocity phase's and
    every search start's included; ``frames`` simulated per run; ``model_grid`` and
    ``search_grid`` the main and the global phase's grid nodes (the scene prepared on each,
    and on the grid check's, by :meth:`prepared_on`); ``views`` the guidance views, set
    once the pre-flight checks passed (their flow is the expensive part). The one change
    in a run is the main grid a time budget chooses (:meth:`move_to_grid`)."""

    def __init__(self, cfg: SceneConfig):
        self.cfg = cfg
        self.params = parameterizations(cfg)
        opt = cfg.optimize
        # each object's velocity components where optimize.parameters names its velocity; the
        # velocity phase's: those of estimate_velocity_objects
        velocities = [velocity_names(cfg.objects, k) for k in range(len(cfg.objects))]
        optimised = tuple(c for name, components in velocities if name in opt.parameters for c in components)
        self.velocity_variables = tuple(
            c
            for o, (_, components) in zip(cfg.objects, velocities)
            if opt.estimate_velocity_iterations and o.name in opt.estimate_velocity_objects
            for c in components
        )
        estimated = tuple(c for c in self.velocity_variables if c not in optimised)
        self.main_variables = tuple(self.params) + optimised
        self.variables = self.main_variables + estimated
        # every start but the kept one spends search.start_iterations iterations of its own
        extra_start_iterations = (opt.search.starts - 1) * opt.search.start_iterations if opt.search else 0
        self.total_iterations = opt.estimate_velocity_iterations + opt.iterations + extra_start_iterations
        self.frames = cfg.simulation.frames
        # optimize.search.grid_resolution: the global phase's coarser grid over the same domain
        self.model_grid = cfg.simulation.grid_resolution
        self.search_grid = (opt.search.grid_resolution if opt.search else 0) or self.model_grid
        self._prepared = {self.model_grid: prepare(cfg)}
        self._device_scenes: dict[int, DeviceScene] = {}  # by grid, as _prepared
        self.prepared_on(self.search_grid)
        self.views: list[View] = []

    @property
    def prepared(self) -> Prepared:
        """The scene prepared on the main grid."""
        return self._prepared[self.model_grid]

    def move_to_grid(self, grid: int) -> None:
        """The main phase runs on a grid of ``grid`` nodes (the budget's choice): its config
        and prepared scene become that grid's; the scenes of other grids but the search's
        are dropped."""
        self.model_grid = grid
        self.cfg = self.prepared_on(grid).cfg
        self._prepared = {g: p for g, p in self._prepared.items() if g in (self.search_grid, self.model_grid)}
        self._device_scenes = {g: s for g, s in self._device_scenes.items() if g in self._prepared}

    def prepared_on(self, grid: int) -> Prepared:
        """The scene prepared on a grid of ``grid`` nodes over the same domain (the model's,
        the search's, the grid check's), made on first use."""
        if grid not in self._prepared:
            simulation = dataclasses.replace(self.cfg.simulation, grid_resolution=grid)
            self._prepared[grid] = prepare(dataclasses.replace(self.cfg, simulation=simulation))
        return self._prepared[grid]

    def __getstate__(self) -> dict:
        """A copy for another process (a Ray task) leaves the device scenes behind: device
        memory is this process's; the copy makes its own on first use."""
        return {**self.__dict__, "_device_scenes": {}}

    def scene_on_device(self, grid: int) -> DeviceScene:
        """The Gaussians of the scene prepared on the grid of ``grid`` nodes on the device, to
        render a run's simulated flow from (made on first use)."""
        if grid not in self._device_scenes:
            prepared = self.prepared_on(grid)
            self._device_scenes[grid] = DeviceScene(prepared.static, prepared.obj_rest)
        return self._device_scenes[grid]

    def values(self, z: dict[str, float]) -> dict[str, float]:
        """The value of every variable in z: material parameters in SI, velocity components in m/s."""
        out = {n: float(p.decode(torch.tensor(z[n], dtype=torch.float64))) for n, p in self.params.items()}
        out.update((n, v) for n, v in z.items() if is_velocity_component(n))
        return out

    def velocities(self, z: dict[str, float]) -> tuple[tuple[float, float, float], ...]:
        """Each object's initial velocity (m/s, simulation frame) at z: its components in z
        where they are optimised, else its config's."""
        out = []
        for k, obj in enumerate(self.cfg.objects):
            names = velocity_names(self.cfg.objects, k)[1]
            out.append(tuple(z[n] for n in names) if names[0] in z else obj.velocity)
        return tuple(out)

    def object_values(self, values: dict[str, float], velocities) -> tuple[ObjectValues, ...]:
        """Each object's ObjectValues with the optimised ``values`` (SI, by z name) and initial
        ``velocities`` (one [3] tuple or tensor per object, m/s)."""
        overrides = {n: values[n] for n in self.params if n != TIME_SCALE.name}
        return tuple(
            dataclasses.replace(v, velocity=velocity)
            for v, velocity in zip(scene_values(self.cfg, overrides), velocities)
        )

    def velocity_input(self, zt: dict[str, torch.Tensor], prepared: Prepared) -> torch.Tensor | None:
        """The initial velocity :func:`run` takes from the z tensors ``zt``: None where no
        object's velocity is optimised; [3] where every object's velocity is the same
        components (the one object's); else per particle [M, 3], each object's particles its
        own (a masked sum, as scene_run_values: an object's components reach only its
        particles)."""
        names = [velocity_names(self.cfg.objects, k)[1] for k in range(len(self.cfg.objects))]
        if not any(n[0] in zt for n in names):
            return None
        if len(set(names)) == 1:
            return torch.stack([zt[n] for n in names[0]])
        per_object = torch.stack(
            [
                torch.stack([zt[c].double() for c in n])
                if n[0] in zt
                else torch.tensor(obj.velocity, dtype=torch.float64)
                for n, obj in zip(names, self.cfg.objects)
            ]
        )  # [K, 3]
        masks = object_masks(prepared.setup, len(names))  # [K, M]
        return (per_object[:, None, :] * masks[:, :, None]).sum(0)

    def initial_state(self) -> OptimizerState:
        """The state a run starts from: z at the config's values (an optimised velocity at
        its config's), no moments."""
        objects = scene_values(self.cfg)
        values = {}
        for n in self.params:  # the one object's PARAM, or OBJECT.PARAM: that object's
            if n == TIME_SCALE.name:
                values[n] = TIME_SCALE.default  # the video plays at the speed it was filmed
                continue
            k, param = split_parameter(self.cfg.objects, n)
            values[n] = objects[k].density if param == "density" else objects[k].params[param]
        z = {n: float(p.encode(values[n])) for n, p in self.params.items()}
        for k, obj in enumerate(self.cfg.objects):  # an optimised velocity starts at its config's
            components = velocity_names(self.cfg.objects, k)[1]
            if components[0] in self.variables:
                z.update(zip(components, obj.velocity))
        return OptimizerState(0, z, {n: 0.0 for n in z}, {n: 0.0 for n in z})

    def time_scale(self, z: dict[str, float]) -> float:
        """Simulated seconds per second of the guidance video at z: its time_scale where
        optimised, else 1."""
        if TIME_SCALE.name not in self.params:
            return 1.0
        return float(self.params[TIME_SCALE.name].decode(torch.tensor(z[TIME_SCALE.name], dtype=torch.float64)))

    def simulator_on(self, grid: int, z: dict[str, float]):
        """A forward simulator of z on a grid of ``grid`` nodes (its substeps those of z's
        stability limits at the start)."""
        return build_simulator(
            self.cfg,
            self.prepared_on(grid).setup,
            self.object_values(self.values(z), self.velocities(z)),
            time_scale=self.time_scale(z),
        )

    def plan_on(self, grid: int, z: dict[str, float] | None = None):
        """The RunPlan of z (default: the initial parameters) on a grid of ``grid`` nodes:
        substeps, the seconds of a substep and of a frame's flow rendered (timed there);
        SubstepLimitError beyond ``simulation.max_substeps``."""
        from clflow.pipeline.preflight import plan_run

        z = self.initial_state().z if z is None else z  # plan_run builds the simulator: it checks the forces
        objects = self.object_values(self.values(z), self.velocities(z))
        prepared = self.prepared_on(grid)
        plan = plan_run(
            prepared.cfg,
            prepared.setup,
            objects,
            max_substeps=self.cfg.simulation.max_substeps,
            optimizing=True,
            time_scale=self.time_scale(z),
        )
        return dataclasses.replace(plan, render_seconds_per_frame=self.render_seconds(prepared))

    def start_substeps(self, grid: int, z: dict[str, float]) -> int:
        """Substeps per frame the run of z takes on a grid of ``grid`` nodes over every frame,
        the CFL retries its motion makes included (forward only, no flow rendered)."""
        sim = self.simulator_on(grid, z)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", StabilityWarning)  # the optimiser's runs retry the same way
            return run(sim, self.frames, {}).substeps

    def rest_substeps(self, grid: int, z: dict[str, float]) -> int:
        """Substeps per frame the stability limits of z ask at its start on a grid of ``grid``
        nodes (no run: the substeps a search sample of z begins with)."""
        return self.simulator_on(grid, z).substeps

    def render_seconds(self, prepared: Prepared) -> float:
        """Seconds one frame step's flow takes in every view, rendered and its gradient back
        (timed once in the guidance view on ``prepared``'s scene at rest: what an iteration
        adds to the simulation's time)."""
        p = prepared
        scene = DeviceScene(p.static, p.obj_rest)
        x = p.setup.particles.positions.to(p.obj_rest.means.dtype).expand(2, -1, 3).clone().requires_grad_()
        F = torch.eye(3, dtype=x.dtype).expand(2, x.shape[1], 3, 3)
        seconds = []
        for _ in range(2):  # the first builds the rasteriser's kernels
            started = time.perf_counter()
            render_scene_flows(scene, x, F, p.camera)[0].sum().backward()
            seconds.append(time.perf_counter() - started)
        return seconds[-1] * (1 + len(self.cfg.more_views))

    def preflight(self):
        """Force stages and the substeps at the initial parameters: the predicted time is
        logged, a run beyond ``simulation.max_substeps`` refused (SubstepLimitError)."""
        from clflow.pipeline.preflight import describe

        plan = self.plan_on(self.model_grid)
        log.info("%s", describe(plan, "optimize", gradient=True))
        return plan

    def typical_box(self, name: str) -> tuple[float, float]:
        """(lower, upper) in z of material parameter ``name``'s typical range."""
        p = self.params[name]
        lo, hi = (float(p.encode(v)) for v in p.param.typical) if p.param.scale != "linear" else p.param.typical
        return lo, hi

    def search_box(self, z0: dict[str, float]) -> dict[str, tuple[float, float]]:
        """(lower, upper) in z of each parameter's search box: ``optimize.bounds`` when
        given; else a log parameter's start times 10^(+-decades) within its typical range,
        and a bounded or linear one's typical range; each widened to hold the start."""
        opt = self.cfg.optimize
        box = {}
        for name, p in self.params.items():
            if name in opt.bounds:
                lo, hi = (float(p.encode(v)) for v in opt.bounds[name])
                if not lo <= z0[name] <= hi:
                    raise InputError(
                        f"{self.cfg.source}: the start of {name} lies outside optimize.bounds.{name} "
                        f"{list(opt.bounds[name])}"
                    )
            else:
                lo, hi = self.typical_box(name)
                if p.param.scale == "log":
                    lo, hi = max(lo, z0[name] - opt.search.decades), min(hi, z0[name] + opt.search.decades)
                lo, hi = min(lo, z0[name]), max(hi, z0[name])
            box[name] = (lo, hi)
        return box

    @functools.cached_property
    def _local_box(self) -> dict[str, tuple[float, float]]:
        return self.search_box(self.initial_state().z) if self.cfg.optimize.search is not None else {}

    def local_box(self) -> dict[str, tuple[float, float]]:
        """(lower, upper) in z that the local phase stays in: the search's box (none without a search)."""
        return self._local_box

    def box_of(self, name: str, z: dict[str, float]) -> tuple[float, float]:
        """(lower, upper) in z where the search looked for variable ``name``, widened to hold
        z: the local phase's box, else a material parameter's typical range; a velocity
        component's is unbounded."""
        if name not in self.params:
            return -math.inf, math.inf
        lo, hi = self.local_box().get(name) or self.typical_box(name)
        return min(lo, z[name]), max(hi, z[name])

    @property
    def corrects_bias(self) -> bool:
        return self.cfg.flow.bias_correction == "simulated"
