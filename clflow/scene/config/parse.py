"""A parsed config (dicts and lists) checked section by section into a SceneConfig."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from clflow.errors import InputError
from clflow.flow.optical_flow import (
    BIAS_CORRECTIONS,
    CONFIDENCES,
    DEFAULT_BIAS_CORRECTION,
    DEFAULT_CONFIDENCE,
    DEFAULT_PRESET,
    DIS_PRESETS,
)
from clflow.materials import DENSITY, get_material, validate_params
from clflow.mpm.constants import COLLIDER_MODES
from clflow.regions import Region
from clflow.scene.config.reader import Reader
from clflow.scene.config.settings import (
    DEFAULT_MAX_SUBSTEPS,
    FLOW_LOSSES,
    FLOW_METHODS,
    MATERIAL_MODELS,
    OPTIMIZERS,
    SINGLE_OBJECT,
    UP_AXES,
    VELOCITY,
    VELOCITY_COMPONENTS,
    BudgetSettings,
    CameraConfig,
    Collider,
    FillSettings,
    FlowSettings,
    ForceStage,
    GenerateSettings,
    GuidanceView,
    MaterialConfig,
    OptimizeSettings,
    SceneConfig,
    SceneObject,
    SearchSettings,
    Selection,
    SimulationSettings,
    main_grid_range,
    split_parameter,
    velocity_names,
)

# What a value can mean (docs/scene_config.md, "Ranges"): far beyond any scene's, where it
# means nothing and products of such values overflow (a domain of 1e308 m, a scale of 1e308).
LENGTH = 1e4  # m: a coordinate or size in the simulation frame (10 km)
SCENE_LENGTH = 1e9  # scene units: a coordinate or size in the splat file's frame
SCALE = (1e-6, 1e3)  # metres per scene unit
SPEED = 1e4  # m/s: a component of an initial velocity
ACCELERATION = 1e6  # m/s^2: a component of gravity or of a force stage's acceleration
FORCE = 1e9  # N: a component of a force stage's force
FPS = (1e-3, 1e6)  # frames per second
MAX_GRID = 100_000  # grid nodes along the domain's longest side (memory refuses far fewer)
MAX_PER_AXIS = 16  # fill particles per voxel and axis (16^3 = 4096 a voxel)
MAX_PIXELS = 16384  # an image's width or height: the most libx264 writes (a preview, a guidance video)
MAX_RATE = 100.0  # a learning rate, per iteration in the optimiser's units (decades for a modulus)


def _region(r: Reader, data: Any, path: str, allow_all: bool, limit: float) -> Region:
    """A box or sphere (``all`` too, with ``allow_all``) within +-``limit`` (its frame's length)."""
    if data == "all" and allow_all:
        return Region("all")
    shapes = ("box", "sphere") + (("all",) if allow_all else ())
    body = r.section(data, path, ("box", "sphere"))
    if len(body) != 1:
        raise r.fail(path, f"give exactly one of {', '.join(shapes)}")
    if "box" in body:
        box = r.section(body["box"], f"{path}.box", ("min", "max"))
        lower = r.vec3(box, "min", f"{path}.box", limit=limit)
        upper = r.vec3(box, "max", f"{path}.box", limit=limit)
        if not all(lo < hi for lo, hi in zip(lower, upper)):
            raise r.fail(f"{path}.box", f"min {list(lower)} must be below max {list(upper)} on every axis")
        return Region.box(lower, upper)
    sphere = r.section(body["sphere"], f"{path}.sphere", ("center", "radius"))
    return Region.sphere(
        r.vec3(sphere, "center", f"{path}.sphere", limit=limit),
        r.number(sphere, "radius", f"{path}.sphere", low=0.0, high=limit, strict_low=True),
    )


def _flow_mask(r: Reader, flow_in: dict) -> str:
    """ "alpha", "none", or the resolved path of a mask image (checked to exist)."""
    mask = flow_in.get("mask")
    if mask is None or mask in ("alpha", "none"):
        return mask or "alpha"
    if not isinstance(mask, str):
        raise r.fail("flow.mask", f"must be alpha, none or a mask image file, got {mask!r}")
    return str(r.file(flow_in, "mask", "flow"))


def _window(r: Reader, data: dict, path: str) -> tuple[float, float]:
    start = r.number(data, "start", path, 0.0, low=0.0)
    end = r.number(data, "end", path, math.inf) if data.get("end") is not None else math.inf
    if end <= start:
        raise r.fail(f"{path}.end", f"must be after start ({start:g} s), got {end:g}")
    return start, end


def _material(r: Reader, data: Any, p: str = "material") -> MaterialConfig:
    """``p``: the material of one object (``material``, or ``objects.NAME.material``)."""
    body = r.section(data, p, ("type", "parameters", "density", "model", "query"))
    kind = body.get("type")
    if not isinstance(kind, str):
        raise r.fail(f"{p}.type", "is required: a material name or 'query'")
    params_in = r.mapping(body.get("parameters"), f"{p}.parameters")  # names: the registry checks
    for name, value in params_in.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(
                f"{p}.parameters.{name}",
                f"must be a number, got {value!r} (YAML reads 2e4 as text: write 2.0e+4 or 20000.0)",
            )
    if kind == "query":
        if body.get("model") is not None:
            raise r.fail(f"{p}.model", "cannot be chosen before the query picks the material type")
        query = r.section(body.get("query"), f"{p}.query", ("image", "prompt", "backend", "result"))
        if query.get("image") is not None and query.get("result") is not None:
            raise r.fail(
                f"{p}.query",
                "give at most one of image (ask the query now) and result (a record `clflow query` wrote); "
                "with neither the query looks at the object in the guidance video's first frame",
            )
        density = (
            r.number(body, "density", p, low=0.0, strict_low=True) if body.get("density") is not None else None
        )  # None: the query's
        backend = r.choice(query, "backend", f"{p}.query", ("offline", "openai"), "offline")
        return MaterialConfig(
            "query",
            dict(params_in),
            density,
            query_image=r.file(query, "image", f"{p}.query", required=False),
            query_result=r.file(query, "result", f"{p}.query", required=False),
            query_prompt=str(query.get("prompt", "")),
            query_backend=backend,
        )
    if body.get("query") is not None:
        raise r.fail(f"{p}.query", f"is only read with type: query (the type is {kind!r})")
    try:
        material = get_material(kind)
        params = validate_params(material.name, params_in)
    except InputError as exc:
        raise r.fail(p, str(exc)) from None
    density = r.number(body, "density", p, material.default_density, low=0.0, strict_low=True)
    DENSITY.check(density, f"{r.source}: {p}.density")
    model = None
    if body.get("model") is not None:
        if material.name not in MATERIAL_MODELS:
            raise r.fail(f"{p}.model", f"{material.name} has no model option (only {', '.join(MATERIAL_MODELS)} have)")
        model = r.choice(body, "model", p, MATERIAL_MODELS[material.name])
    return MaterialConfig(material.name, params, density, model=model)


def _forces(r: Reader, items: list) -> tuple[ForceStage, ...]:
    stages = []
    for i, item in enumerate(items):
        path = f"forces[{i}]"
        body = r.section(item, path, ("region", "force", "acceleration", "start", "end"))
        kinds = [k for k in ("force", "acceleration") if k in body]
        if len(kinds) != 1:
            raise r.fail(path, "give exactly one of force (N) and acceleration (m/s^2)")
        start, end = _window(r, body, path)
        stages.append(
            ForceStage(
                _region(r, body.get("region", "all"), f"{path}.region", allow_all=True, limit=LENGTH),
                r.vec3(body, kinds[0], path, limit=FORCE if kinds[0] == "force" else ACCELERATION),
                kinds[0],
                start,
                end,
            )
        )
    return tuple(stages)


def _colliders(r: Reader, data: Any) -> tuple[Collider, ...]:
    body = r.section(data, "boundaries", ("ground", "colliders"))
    out = []
    if body.get("ground") is not None:
        ground = r.section(body["ground"], "boundaries.ground", ("height", "mode", "friction"))
        out.append(
            Collider(
                (0.0, r.number(ground, "height", "boundaries.ground", 0.0, low=-LENGTH, high=LENGTH), 0.0),
                (0.0, 1.0, 0.0),
                r.choice(ground, "mode", "boundaries.ground", COLLIDER_MODES, "slip"),
                r.number(ground, "friction", "boundaries.ground", 0.0, low=0.0),
            )
        )
    for i, item in enumerate(r.items(body, "colliders", "boundaries")):
        path = f"boundaries.colliders[{i}]"
        c = r.section(item, path, ("point", "normal", "mode", "friction", "start", "end"))
        normal = r.vec3(c, "normal", path, limit=1e6)
        if math.hypot(*normal) < 1e-6:  # a direction, made a unit vector: its length neither under- nor overflows
            raise r.fail(
                f"{path}.normal", f"must not be the zero vector (its length must be >= 1e-06), got {list(normal)}"
            )
        start, end = _window(r, c, path)
        out.append(
            Collider(
                r.vec3(c, "point", path, limit=LENGTH),
                normal,
                r.choice(c, "mode", path, COLLIDER_MODES, "slip"),
                r.number(c, "friction", path, 0.0, low=0.0),
                start,
                end,
            )
        )
    return tuple(out)


def _simulation(r: Reader, data: Any) -> SimulationSettings:
    p = "simulation"
    body = r.section(
        data, p, ("grid_resolution", "domain", "substep_dt", "flip", "fps", "frames", "gravity", "max_substeps")
    )
    lower = upper = None
    if body.get("domain") is not None:
        dom = r.section(body["domain"], f"{p}.domain", ("min", "max"))
        lower, upper = r.vec3(dom, "min", f"{p}.domain", limit=LENGTH), r.vec3(dom, "max", f"{p}.domain", limit=LENGTH)
        if not all(lo < hi for lo, hi in zip(lower, upper)):
            raise r.fail(f"{p}.domain", f"min {list(lower)} must be below max {list(upper)} on every axis")
    dt = body.get("substep_dt", "auto")
    substep_dt = None if dt == "auto" else r.number(body, "substep_dt", p, low=1e-9)
    return SimulationSettings(
        grid_resolution=r.integer(body, "grid_resolution", p, 32, low=11, high=MAX_GRID),  # walls: 4 cells a side
        domain_lower=lower,
        domain_upper=upper,
        substep_dt=substep_dt,
        flip=r.number(body, "flip", p, SimulationSettings.flip, low=0.0, high=1.0),
        fps=r.number(body, "fps", p, 24.0, low=FPS[0], high=FPS[1]),
        frames=r.integer(body, "frames", p, 24, low=1),
        gravity=r.vec3(body, "gravity", p, (0.0, -9.81, 0.0), limit=ACCELERATION),
        max_substeps=r.integer(body, "max_substeps", p, DEFAULT_MAX_SUBSTEPS, low=1),
    )


CAMERA_UP = (0.0, 1.0, 0.0)  # camera.up by default


def _camera(r: Reader, data: Any, p: str = "camera") -> CameraConfig:
    body = r.section(
        data, p, ("file", "colmap", "image", "index", "position", "look_at", "up", "fov_y_deg", "width", "height")
    )
    sources = [k for k in ("file", "colmap") if body.get(k) is not None]
    if not sources and body.get("position") is None:
        raise r.fail(
            p, "give a camera file (cameras.json / transforms.json), a COLMAP model (colmap) or position and look_at"
        )
    if len(sources) > 1:
        raise r.fail(p, "give file or colmap, not both")
    explicit = not sources
    ignored = [k for k in ("position", "look_at", "up", "fov_y_deg", "width", "height") if k in body]
    if not explicit and ignored:
        what = "file" if sources[0] == "file" else "model"
        raise r.fail(p, f"with a camera {what}, {', '.join(ignored)} come from the {what}: drop them")
    if explicit and "index" in body:
        raise r.fail(f"{p}.index", "picks an entry of a camera file or model: give file or colmap as well, or drop it")
    if "image" in body and "colmap" not in body:
        raise r.fail(f"{p}.image", "names an image of a COLMAP model: give colmap as well, or drop it")
    if "image" in body and "index" in body:
        raise r.fail(p, "give image or index, not both")
    image = body.get("image")
    if image is not None and (not isinstance(image, str) or not image):
        raise r.fail(f"{p}.image", f"must be an image name of the COLMAP model, got {image!r}")
    if explicit:  # the camera's own checks (the same point, up along the view), naming the config's keys
        _check_look_at(
            r,
            r.vec3(body, "position", p, limit=SCENE_LENGTH),
            r.vec3(body, "look_at", p, limit=SCENE_LENGTH),
            r.vec3(body, "up", p, CAMERA_UP, limit=SCENE_LENGTH),
            p,
        )
    return CameraConfig(
        cameras_file=r.file(body, "file", p, required=False),
        index=r.integer(body, "index", p, 0),
        colmap=r.file(body, "colmap", p, required=False, folder_ok=True),
        image=image,
        position=r.vec3(body, "position", p) if explicit else None,
        look_at=r.vec3(body, "look_at", p) if explicit else None,
        up=r.vec3(body, "up", p, CAMERA_UP, limit=SCENE_LENGTH),
        fov_y_deg=r.number(body, "fov_y_deg", p, 50.0, low=1.0, high=179.0),
        width=r.integer(body, "width", p, 512, low=8, high=MAX_PIXELS),
        height=r.integer(body, "height", p, 512, low=8, high=MAX_PIXELS),
    )


def _check_look_at(r: Reader, position, look_at, up, p: str) -> None:
    """The look-at camera's own checks of ``p``'s position, look_at and up, errors naming the keys."""
    from clflow.splat.cameras import look_at as camera

    try:
        camera(position, look_at, up, fov_x=1.0, width=8, height=8, keys=(f"{p}.position", f"{p}.look_at", f"{p}.up"))
    except InputError as exc:
        raise r.fail("", str(exc)) from None


def _views(r: Reader, top: dict) -> tuple[list[CameraConfig], list[Path | None]]:
    """The guidance views: ``camera`` and ``video`` each one entry or a list of one per view."""
    cameras, videos = top.get("camera"), top.get("video")
    if isinstance(videos, dict):  # video: {generate: ...}: one view, its video made later
        if isinstance(cameras, list) and len(cameras) != 1:
            raise r.fail(
                "video.generate",
                f"makes one guidance view's video; with {len(cameras)} cameras give a list of video files",
            )
        return [_camera(r, cameras[0] if isinstance(cameras, list) else cameras)], [None]
    for key, value in (("camera", cameras), ("video", videos)):
        if isinstance(value, list) and not value:
            raise r.fail(key, "is an empty list: give one entry per guidance view")
    if not isinstance(cameras, list):
        cameras = [cameras]
    if videos is not None and not isinstance(videos, list):
        videos = [videos]
    if videos is not None and len(videos) != len(cameras):
        raise r.fail("video", f"has {len(videos)} entries, camera {len(cameras)}: give one video per camera")
    if len(cameras) == 1:  # one view: the keys read as always (error messages without an index)
        return [_camera(r, cameras[0])], [
            r.file({"video": videos and videos[0]}, "video", "", required=False, folder_ok=True)
        ]
    return (
        [_camera(r, c, f"camera[{i}]") for i, c in enumerate(cameras)],
        [None] * len(cameras)
        if videos is None
        else [r.file({f"video[{i}]": v}, f"video[{i}]", "", folder_ok=True) for i, v in enumerate(videos)],
    )


def _generate(r: Reader, data: Any, simulation: SimulationSettings) -> GenerateSettings | None:
    """``video: {generate: {...}}``, its model folder and request checked as far as they can
    be before the scene is loaded (clflow.generate.check_request; the JSON files only)."""
    if not isinstance(data, dict):
        return None
    p = "video.generate"
    outer = r.section(data, "video", ("generate",))
    body = r.section(
        outer.get("generate"),
        p,
        (
            "model",
            "prompt",
            "prompt_template",
            "object",
            "negative_prompt",
            "image",
            "seed",
            "frames",
            "fps",
            "steps",
            "guidance_scale",
            "size",
            "fit",
            "cpu_offload",
            "vae_tiling",
            "vae_slicing",
        ),
    )
    if not body:
        raise r.fail(p, "is required: at least the model folder (video: {generate: {model: ...}})")
    model = body.get("model")
    if not isinstance(model, str) or not model:
        raise r.fail(f"{p}.model", f"is required: a local diffusers model folder, got {model!r}")
    texts = {}
    for key in ("prompt", "prompt_template", "object", "negative_prompt"):
        value = body.get(key)
        if value is not None and not isinstance(value, str):
            raise r.fail(f"{p}.{key}", f"must be text, got {value!r}")
        texts[key] = value
    flags = {}
    for key in ("cpu_offload", "vae_tiling", "vae_slicing"):
        flags[key] = body.get(key, False)
        if not isinstance(flags[key], bool):
            raise r.fail(f"{p}.{key}", f"must be true or false, got {flags[key]!r}")
    size = _video_size(r, body.get("size"), f"{p}.size")
    settings = GenerateSettings(
        model=(r.base / model).resolve(),
        prompt=texts["prompt"],
        prompt_template=texts["prompt_template"],
        object=texts["object"] or "object",
        negative_prompt=texts["negative_prompt"] or "",
        image=r.file(body, "image", p, required=False),
        seed=r.integer(body, "seed", p, 0),  # at most MAX_INTEGER (2^63 - 1), as every integer: torch's takes 64 bits
        frames=r.integer(body, "frames", p, low=2, high=10_000) if body.get("frames") is not None else None,
        fps=r.number(body, "fps", p, low=FPS[0], high=FPS[1]) if body.get("fps") is not None else None,
        steps=r.integer(body, "steps", p, low=1, high=10_000) if body.get("steps") is not None else None,
        guidance_scale=r.number(body, "guidance_scale", p, low=0.0, high=1e3)
        if body.get("guidance_scale") is not None
        else None,
        size=size,
        fit=r.choice(body, "fit", p, ("pad", "crop"), "pad"),
        **flags,
    )
    from clflow.scene.video_settings import check_settings

    check_settings(settings, simulation, fail=lambda key, message: r.fail(f"{p}.{key}" if key else p, message))
    return settings


def _video_size(r: Reader, value: Any, where: str) -> tuple[int, int] | None:
    """``video.generate.size``: WIDTHxHEIGHT or [width, height] in pixels (None: the model's)."""
    if value is None:
        return None
    if (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
    ):
        size = (value[0], value[1])
    elif isinstance(value, str) and len(value) <= 40:  # not thousands of digits, which int() refuses
        from clflow.generate import parse_size

        try:
            size = parse_size(value)
        except InputError as exc:
            raise r.fail(where, str(exc)) from None
    else:
        raise r.fail(where, f"must be WIDTHxHEIGHT or [width, height] in pixels, got {value!r}")
    if max(size) > MAX_PIXELS:
        raise r.fail(where, f"must be at most {MAX_PIXELS} pixels a side, got {size[0]}x{size[1]}")
    return size


def _optimize_settings(r: Reader, data: Any, objects: tuple[SceneObject, ...], frames: int) -> OptimizeSettings:
    """``optimize``; with several objects each parameter is named OBJECT.PARAM."""
    p = "optimize"
    body = r.section(
        data,
        p,
        (
            "parameters",
            "learning_rates",
            "iterations",
            "horizon",
            "final_rate",
            "search",
            "bounds",
            "method",
            "estimate_velocity",
            "material",
            "budget",
        ),
    )
    names = body.get("parameters", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise r.fail(f"{p}.parameters", f"must be a list of parameter names, got {names!r}")
    hypotheses = _hypotheses(r, body.get("material"), names)
    material = objects[0].material
    if len(objects) > 1:
        for name in names:
            _object_parameter(r, f"{p}.parameters", name, objects)
    elif material.type != "query" and not hypotheses:
        mat = get_material(material.type)
        for name in names:
            if name not in ("density", VELOCITY) and name not in mat.param_names:
                raise r.fail(
                    f"{p}.parameters",
                    f"{name!r} is not a parameter of {mat.name} "
                    f"(its parameters: {', '.join(mat.param_names)}, density, velocity)",
                )
    estimate = r.section(body.get("estimate_velocity"), f"{p}.estimate_velocity", ("frames", "iterations", "objects"))
    if "objects" in estimate and len(objects) == 1:
        raise r.fail(f"{p}.estimate_velocity.objects", "names objects of a config of several: drop it")
    estimate_frames = estimate_iterations = 0
    estimated: tuple[str, ...] = ()  # velocity, or OBJECT.velocity of each object the phase estimates
    if estimate:
        estimate_frames = r.integer(estimate, "frames", f"{p}.estimate_velocity", low=1)
        estimate_iterations = r.integer(estimate, "iterations", f"{p}.estimate_velocity", low=1)
        if estimate_frames > frames:
            raise r.fail(
                f"{p}.estimate_velocity.frames", f"must be <= simulation.frames ({frames}), got {estimate_frames}"
            )
        estimated = (VELOCITY,) if len(objects) == 1 else _estimated_objects(r, estimate.get("objects"), objects)
    rates_in = r.mapping(body.get("learning_rates"), f"{p}.learning_rates")
    for name in rates_in:
        if name not in names and name not in estimated:
            velocity = name.rpartition(".")[2] == VELOCITY
            raise r.fail(
                f"{p}.learning_rates.{name}",
                f"is not among optimize.parameters {names}"
                + (" (nor estimated: optimize.estimate_velocity)" if velocity else ""),
            )
    rates = {n: r.number(rates_in, n, f"{p}.learning_rates", low=0.0, high=MAX_RATE, strict_low=True) for n in rates_in}
    horizon = r.section(body.get("horizon"), f"{p}.horizon", ("start", "step"))
    # hypotheses are told apart by the search
    search = _search(r, body["search"]) if body.get("search") is not None else SearchSettings() if hypotheses else None
    bounds = _bounds(r, body.get("bounds"), names, objects, hypotheses)
    return OptimizeSettings(
        parameters=tuple(names),
        learning_rates=rates,
        iterations=r.integer(body, "iterations", p, 30, low=1),
        horizon_start=r.integer(horizon, "start", f"{p}.horizon", 0),
        horizon_step=r.integer(horizon, "step", f"{p}.horizon", 0),
        final_rate=r.number(body, "final_rate", p, 0.1, low=0.0, high=1.0),
        search=search,
        bounds=bounds,
        method=r.choice(body, "method", p, OPTIMIZERS, "adam"),
        estimate_velocity_frames=estimate_frames,
        estimate_velocity_iterations=estimate_iterations,
        estimate_velocity_objects=tuple(n.partition(".")[0] for n in estimated if len(objects) > 1),
        materials=hypotheses,
        budget=_budget(r, body["budget"]) if body.get("budget") is not None else None,
    )


def _budget(r: Reader, data: Any) -> BudgetSettings:
    """``optimize.budget``: seconds, and the finest main grid to consider."""
    p = "optimize.budget"
    found = r.section(data, p, ("seconds", "max_grid_resolution"))
    return BudgetSettings(
        seconds=r.number(found, "seconds", p, low=0.0, strict_low=True),
        max_grid_resolution=r.integer(found, "max_grid_resolution", p, 0, high=MAX_GRID),
    )


def _estimated_objects(r: Reader, data: Any, objects: tuple[SceneObject, ...]) -> tuple[str, ...]:
    """``optimize.estimate_velocity.objects`` of a config of several objects: the objects whose
    velocities the velocity phase estimates, as OBJECT.velocity (required: an object at rest
    has no velocity to estimate, and Adam's steps would move its weakly observed ones)."""
    where = "optimize.estimate_velocity.objects"
    names = [o.name for o in objects]
    if not isinstance(data, list) or not data or not all(isinstance(n, str) for n in data):
        raise r.fail(where, f"is required with several objects: a list of object names ({', '.join(names)})")
    for name in data:
        if name not in names:
            raise r.fail(where, f"{name!r}: there is no object {name!r} (the objects: {', '.join(names)})")
    if len(set(data)) < len(data):
        raise r.fail(where, f"names an object twice: {data!r}")
    return tuple(f"{n}.{VELOCITY}" for n in data)


def _search(r: Reader, data: Any) -> SearchSettings:
    """``optimize.search``: the global phase's samples, starts and grid."""
    p = "optimize.search"
    found = r.section(
        data,
        p,
        (
            "samples",
            "decades",
            "frames",
            "starts",
            "start_iterations",
            "refine",
            "object_samples",
            "grid_resolution",
        ),
    )
    search = SearchSettings(
        samples=r.integer(found, "samples", p, 32, low=1),
        decades=r.number(found, "decades", p, 3.0, low=0.0, strict_low=True),
        frames=r.integer(found, "frames", p, 0),
        starts=r.integer(found, "starts", p, 1, low=1),
        start_iterations=r.integer(found, "start_iterations", p, 3, low=1),
        refine=r.integer(found, "refine", p, 0),
        object_samples=r.integer(found, "object_samples", p, 12, low=0),
        grid_resolution=r.integer(found, "grid_resolution", p, 0),
    )
    if 0 < search.grid_resolution < 11:  # as simulation.grid_resolution: walls take 4 cells a side
        raise r.fail(f"{p}.grid_resolution", f"must be 0 (the simulation's) or >= 11, got {search.grid_resolution}")
    if search.starts > search.samples:
        raise r.fail(f"{p}.starts", f"must not exceed search.samples ({search.samples}), got {search.starts}")
    return search


def _bounds(
    r: Reader, data: Any, names: list[str], objects: tuple[SceneObject, ...], hypotheses: tuple[str, ...]
) -> dict[str, tuple[float, float]]:
    """``optimize.bounds``: [lower, upper] in SI per optimised parameter, within the
    parameter's valid range where the config names its material."""
    bounds = {}
    for name, box in r.mapping(data, "optimize.bounds").items():
        where = f"optimize.bounds.{name}"
        if name not in names:
            raise r.fail(where, f"is not among optimize.parameters {names}")
        if (
            not isinstance(box, list)
            or len(box) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in box)
        ):
            raise r.fail(where, f"must be [lower, upper] (SI), got {box!r}")
        if not box[0] < box[1]:
            raise r.fail(where, f"is empty or inverted: lower {box[0]:g} must be below upper {box[1]:g}")
        param = _registry_param(name, objects, hypotheses)
        if param is not None:
            (lo, hi), (low_in, high_in) = param.valid, (param.low_inclusive, param.high_inclusive)
            if box[0] < lo or (box[0] == lo and not low_in) or box[1] > hi or (box[1] == hi and not high_in):
                valid = f"{'[' if low_in else '('}{lo:g}, {hi:g}{']' if high_in else ')'}"
                raise r.fail(where, f"[{box[0]:g}, {box[1]:g}] must lie in {param.name}'s valid range {valid}")
        bounds[name] = (float(box[0]), float(box[1]))
    return bounds


def _registry_param(name: str, objects: tuple[SceneObject, ...], hypotheses: tuple[str, ...]):
    """The registry's Param that ``name`` of optimize.parameters stands for; None for a
    velocity and for a material the query picks."""
    k, param = split_parameter(objects, name)
    if param == "density":
        return DENSITY
    for material in hypotheses or (objects[k].material.type,):
        if material != "query" and param in get_material(material).param_names:
            return get_material(material).param(param)
    return None


def _hypotheses(r: Reader, data: Any, names: list[str]) -> tuple[str, ...]:
    """``optimize.material``: registry names (aliases resolved), each with at least one of
    ``optimize.parameters``; every parameter belongs to at least one of them."""
    p = "optimize.material"
    if data is None:
        return ()
    if not isinstance(data, list) or not data or not all(isinstance(n, str) for n in data):
        raise r.fail(p, f"must be a non-empty list of material names, got {data!r}")
    try:
        materials = [get_material(n) for n in data]
    except InputError as exc:
        raise r.fail(p, str(exc)) from None
    canonical = [m.name for m in materials]
    if len(set(canonical)) < len(canonical):
        raise r.fail(p, f"names a material twice: {data!r}")
    common = ("density", VELOCITY)
    for m in materials:
        if not any(n in common or n in m.param_names for n in names):
            raise r.fail(
                p,
                f"{m.name} has none of optimize.parameters {names} (its parameters: "
                f"{', '.join(m.param_names)}, density, velocity)",
            )
    for n in names:
        if n not in common and not any(n in m.param_names for m in materials):
            raise r.fail(
                "optimize.parameters", f"{n!r} is a parameter of none of the hypotheses {', '.join(canonical)}"
            )
    return tuple(canonical)


TOP_KEYS = (
    "splats",
    "scene",
    "object",
    "material",
    "objects",
    "forces",
    "boundaries",
    "simulation",
    "camera",
    "video",
    "flow",
    "optimize",
    "evaluation",
    "output",
)


def parse_config(data: Any, source: str = "<config>", base: Path | None = None) -> SceneConfig:
    """Validate a parsed config (dict) and return a :class:`SceneConfig`."""
    r = Reader(source, base or Path.cwd())
    r.no_huge_integers(data)
    top = r.section(data, "", TOP_KEYS)
    if not top:
        raise r.fail("", "the config is empty")
    scene = r.section(top.get("scene"), "scene", ("scale", "up", "dataparser_transforms"))
    objects = _objects(r, top)
    if len(objects) > 1:
        _refuse_identification(r, top)
    material = objects[0].material
    flow = _flow(r, top.get("flow"))
    if len(objects) == 1:
        truth, true_density, true_velocity = _given_truth(r, top.get("evaluation"))
    simulation = _simulation(r, top.get("simulation"))
    output = top.get("output", "results")
    if not isinstance(output, str) or not output:
        raise r.fail("output", f"must be a folder path, got {output!r}")
    optimize = _optimize_settings(r, top.get("optimize"), objects, simulation.frames)
    if len(objects) == 1:
        truth = _ground_truth(r, truth, true_density, true_velocity, material, optimize)
    else:
        truth = _objects_truth(r, top.get("evaluation"), objects)
    _check_optimize_fits(r, optimize, simulation, flow)
    cameras, videos = _views(r, top)
    if len(cameras) > 1 and flow.mask not in ("alpha", "none"):
        raise r.fail("flow.mask", "a mask image fits one view: with several guidance views use alpha or none")
    return SceneConfig(
        source=Path(source),
        splats=r.file(top, "splats", ""),
        scale=r.number(scene, "scale", "scene", 1.0, low=SCALE[0], high=SCALE[1]),
        up=r.choice(scene, "up", "scene", UP_AXES, "+y"),
        objects=objects,
        forces=_forces(r, r.items(top, "forces", "")),
        colliders=_colliders(r, top.get("boundaries")),
        simulation=simulation,
        camera=cameras[0],
        video=videos[0],  # a video or an image folder
        flow=flow,
        optimize=optimize,
        output=(r.base / output).resolve(),
        ground_truth=truth,
        more_views=tuple(GuidanceView(c, v) for c, v in zip(cameras[1:], videos[1:])),
        dataparser_transforms=r.file(scene, "dataparser_transforms", "scene", required=False),
        generate=_generate(r, top.get("video"), simulation),
    )


def _refuse_identification(r: Reader, top: dict) -> None:
    """A config of several objects identifies each object's material parameters
    (OBJECT.PARAM); material hypotheses name no object yet, so they are refused."""
    optimize = top.get("optimize") if isinstance(top.get("optimize"), dict) else {}
    if optimize.get("material"):
        raise r.fail(
            "optimize.material",
            "not built yet for several objects (optimize.parameters names each "
            "object's parameters, OBJECT.PARAM, of the material its config gives); drop it",
        )


def _object_parameter(r: Reader, where: str, name: str, objects: tuple[SceneObject, ...]) -> tuple[SceneObject, str]:
    """(object, parameter) of ``name`` (OBJECT.PARAM) of a config of several objects: the
    object is one of them and the parameter its material's, density or velocity."""
    names = ", ".join(o.name for o in objects)
    obj_name, dot, param = name.partition(".")
    example = f"{objects[0].name}.{next(iter(objects[0].material.parameters), 'density')}"
    if not dot or not param:
        raise r.fail(
            where, f"{name!r}: with several objects name each parameter's object, OBJECT.PARAM (e.g. {example})"
        )
    obj = next((o for o in objects if o.name == obj_name), None)
    if obj is None:
        raise r.fail(where, f"{name!r}: there is no object {obj_name!r} (the objects: {names})")
    if obj.material.type != "query" and param not in ("density", VELOCITY):
        mat = get_material(obj.material.type)
        if param not in mat.param_names:
            raise r.fail(
                where,
                f"{name!r}: {param!r} is not a parameter of {obj.name}'s material {mat.name} "
                f"(its parameters: {', '.join(mat.param_names)}, density, velocity)",
            )
    return obj, param


def _objects_truth(r: Reader, data: Any, objects: tuple[SceneObject, ...]) -> dict[str, float]:
    """``evaluation.ground_truth`` of a config of several objects: OBJECT.PARAM -> SI value,
    each checked against its object's material (density: kg/m^3; OBJECT.velocity: [3] m/s, as
    its components OBJECT.velocity_x, ...)."""
    p = "evaluation.ground_truth"
    evaluation = r.section(data, "evaluation", ("ground_truth",))
    given = dict(r.mapping(evaluation.get("ground_truth"), p))
    per_object: dict[str, dict] = {}
    for name, value in given.items():
        obj, param = _object_parameter(r, p, name, objects)
        if param == VELOCITY:
            value = r.vec3(given, name, p, limit=SPEED)
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(f"{p}.{name}", f"must be a number, got {value!r}")
        per_object.setdefault(obj.name, {})[param] = value
    truth = {}
    for k, obj in enumerate(objects):
        values = per_object.get(obj.name, {})
        truth.update(zip(velocity_names(objects, k)[1], values.pop(VELOCITY, ())))
        density = values.pop("density", None)
        try:
            if density is not None:
                DENSITY.check(density)
            if values and obj.material.type != "query":
                values = {k: v for k, v in validate_params(obj.material.type, values).items() if k in values}
        except InputError as exc:
            raise r.fail(p, f"{obj.name}: {exc}") from None
        truth.update({f"{obj.name}.{k}": float(v) for k, v in values.items()})
        if density is not None:
            truth[f"{obj.name}.density"] = float(density)
    return truth


def _selection(r: Reader, data: Any, p: str = "object.select") -> Selection:
    """``p`` (an object's ``select``): exactly one of a region (box, sphere), a mask file or a PLY of the part."""
    select = r.section(data, p, ("box", "sphere", "mask", "ply", "tolerance"))
    if not select:
        raise r.fail(p, "is required: a box, a sphere, a mask file or a PLY of the part")
    if "tolerance" in select and "ply" not in select:
        raise r.fail(f"{p}.tolerance", "applies to a ply selection only: drop it")
    if len(set(select) & {"box", "sphere", "mask", "ply"}) > 1:
        raise r.fail(p, "give exactly one of box, sphere, mask and ply")
    if "mask" in select:
        return Selection(None, r.file(select, "mask", p))
    if "ply" in select:
        tolerance = select.get("tolerance")
        return Selection(
            None,
            None,
            r.file(select, "ply", p),
            None
            if tolerance is None
            else r.number(select, "tolerance", p, low=0.0, high=SCENE_LENGTH, strict_low=True),
        )
    return Selection(_region(r, select, p, allow_all=False, limit=SCENE_LENGTH), None)


def _fill(r: Reader, data: Any, p: str = "object.fill") -> FillSettings:
    """``p`` (an object's ``fill``): particles inside the object besides the Gaussian centres."""
    fill_in = r.section(data, p, ("enabled", "spacing", "per_axis"))
    enabled = fill_in.get("enabled", True)
    if not isinstance(enabled, bool):
        raise r.fail(f"{p}.enabled", f"must be true or false, got {enabled!r}")
    return FillSettings(
        enabled=enabled,
        spacing=r.number(fill_in, "spacing", p, low=1e-6, high=LENGTH) if fill_in.get("spacing") is not None else None,
        per_axis=r.integer(fill_in, "per_axis", p, 1, low=1, high=MAX_PER_AXIS),
    )


OBJECT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")  # a name fits a --set key: objects.NAME.material...


def _objects(r: Reader, top: dict) -> tuple[SceneObject, ...]:
    """``objects`` (a list of entries with a name, or a mapping of names to entries), or the
    single-object form ``object`` + ``material``, read into the same SceneObject tuple."""
    if top.get("objects") is None:
        obj = r.section(top.get("object"), "object", ("select", "fill", "velocity"))
        return (
            SceneObject(
                SINGLE_OBJECT,
                _selection(r, obj.get("select")),
                _fill(r, obj.get("fill")),
                _material(r, top.get("material")),
                r.vec3(obj, "velocity", "object", (0.0, 0.0, 0.0), limit=SPEED),
            ),
        )
    single = [k for k in ("object", "material") if top.get(k) is not None]
    if single:
        raise r.fail(
            single[0],
            "give the scene's objects under objects (each with its own material), or one object "
            "as object and material, not both",
        )
    data = top["objects"]
    if isinstance(data, dict):  # a mapping of names to objects: the key names each
        entries = []
        for name, body in data.items():
            _check_name(r, name, f"objects.{name}")
            where = f"objects.{name}"
            body = r.section(body, where, ("select", "fill", "velocity", "material"))
            entries.append((name, body, where))
    elif isinstance(data, list):
        entries, first = [], {}
        for i, item in enumerate(data):
            body = r.section(item, f"objects[{i}]", ("name", "select", "fill", "velocity", "material"))
            name = body.get("name")
            if name is None:
                raise r.fail(
                    f"objects[{i}].name", "is required: a name for the object (its --set keys and outputs use it)"
                )
            _check_name(r, name, f"objects[{i}].name")
            if name in first:
                raise r.fail(
                    f"objects[{i}].name",
                    f"{name!r} names objects[{first[name]}] too: each object needs a name of its own",
                )
            first[name] = i
            entries.append((name, body, f"objects.{name}"))
    else:
        raise r.fail(
            "objects",
            f"must be a list of objects (each with a name) or a mapping of names to objects, got {type(data).__name__}",
        )
    if not entries:
        raise r.fail("objects", "is empty: give at least one object (its select and material)")
    return tuple(
        SceneObject(
            name,
            _selection(r, body.get("select"), f"{where}.select"),
            _fill(r, body.get("fill"), f"{where}.fill"),
            _material(r, body.get("material"), f"{where}.material"),
            r.vec3(body, "velocity", where, (0.0, 0.0, 0.0), limit=SPEED),
            key=where,
        )
        for name, body, where in entries
    )


def _check_name(r: Reader, name: Any, where: str) -> None:
    if not isinstance(name, str) or not OBJECT_NAME.fullmatch(name):
        raise r.fail(
            where,
            f"an object's name is letters, digits and _ (not starting with a digit), as --set keys "
            f"take it (objects.NAME.material...), got {name!r}",
        )


def _flow(r: Reader, data: Any) -> FlowSettings:
    """``flow``: the optical-flow estimator, the loss, its mask, confidence and bias correction."""
    flow_in = r.section(data, "flow", ("method", "preset", "loss", "mask", "confidence", "bias_correction"))
    return FlowSettings(
        method=r.choice(flow_in, "method", "flow", FLOW_METHODS, "dis"),
        preset=r.choice(flow_in, "preset", "flow", DIS_PRESETS, DEFAULT_PRESET),
        loss=r.choice(flow_in, "loss", "flow", FLOW_LOSSES, "l2"),
        mask=_flow_mask(r, flow_in),
        confidence=r.choice(flow_in, "confidence", "flow", CONFIDENCES, DEFAULT_CONFIDENCE),
        bias_correction=r.choice(flow_in, "bias_correction", "flow", BIAS_CORRECTIONS, DEFAULT_BIAS_CORRECTION),
    )


def _given_truth(r: Reader, data: Any) -> tuple[dict, float | None, tuple]:
    """``evaluation.ground_truth`` as given: the material's values (numbers, checked against
    the material later), the density (kg/m^3, checked) and the velocity (m/s; () if absent)."""
    evaluation = r.section(data, "evaluation", ("ground_truth",))
    truth = dict(r.mapping(evaluation.get("ground_truth"), "evaluation.ground_truth"))
    true_velocity = r.vec3(truth, VELOCITY, "evaluation.ground_truth", (), limit=SPEED)  # () when not given
    truth.pop(VELOCITY, None)
    for name, value in truth.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(f"evaluation.ground_truth.{name}", f"must be a number, got {value!r}")
    true_density = truth.pop("density", None)
    if true_density is not None:
        try:
            DENSITY.check(true_density)
        except InputError as exc:
            raise r.fail("evaluation.ground_truth", str(exc)) from None
    return truth, true_density, true_velocity


def _ground_truth(
    r: Reader,
    truth: dict,
    true_density: float | None,
    true_velocity: tuple,
    material: MaterialConfig,
    optimize: OptimizeSettings,
) -> dict[str, float]:
    """The ground truth's material values validated for the material (with hypotheses: the
    first that has all its names), its density and velocity components, SI."""
    if truth and (optimize.materials or material.type != "query"):
        candidates = optimize.materials or (material.type,)
        fitting = [m for m in candidates if set(truth) <= set(get_material(m).param_names)] or candidates[:1]
        try:
            truth = {k: v for k, v in validate_params(fitting[0], truth).items() if k in truth}
        except InputError as exc:
            raise r.fail("evaluation.ground_truth", str(exc)) from None
    if true_density is not None:
        truth["density"] = float(true_density)
    truth.update(zip(VELOCITY_COMPONENTS, true_velocity))
    return dict(truth)


def _check_optimize_fits(r: Reader, optimize: OptimizeSettings, simulation: SimulationSettings, flow: FlowSettings):
    """The optimiser's settings that depend on other sections: several starts need
    Levenberg-Marquardt, the search's grid is the coarser one, LM needs the l2 loss."""
    if optimize.search is not None and optimize.search.starts > 1 and optimize.method != "levenberg_marquardt":
        raise r.fail(
            "optimize.search.starts",
            "several starts are polished by levenberg_marquardt: set "
            "optimize.method: levenberg_marquardt, or starts: 1",
        )
    if optimize.search is not None and optimize.search.grid_resolution > simulation.grid_resolution:
        raise r.fail(
            "optimize.search.grid_resolution",
            f"must not exceed simulation.grid_resolution ({simulation.grid_resolution}): the search's "
            f"grid is the coarse one, got {optimize.search.grid_resolution}",
        )
    budget = optimize.budget
    if budget is not None and 0 < budget.max_grid_resolution < main_grid_range(optimize, simulation)[0]:
        raise r.fail(
            "optimize.budget.max_grid_resolution",
            f"must be 0 or at least the search's grid ({main_grid_range(optimize, simulation)[0]}), the coarsest "
            f"the budget chooses from, got {budget.max_grid_resolution}",
        )
    if optimize.method == "levenberg_marquardt" and flow.loss != "l2":
        raise r.fail(
            "optimize.method", f"levenberg_marquardt minimises a sum of squares: it needs flow.loss l2, not {flow.loss}"
        )
