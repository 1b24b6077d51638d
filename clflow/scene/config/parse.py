"""A parsed config (dicts and lists) checked section by section into a SceneConfig: the
scene, simulation, guidance views and flow here, the objects, forces and boundaries in
``parse_objects``, the optimiser and the ground truth in ``parse_optimize``. The keys, their
defaults and ranges are declared once (``schema``); what cannot be declared is code here."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from clflow.errors import InputError
from clflow.scene.config import parse_objects, parse_optimize, schema
from clflow.scene.config.keys import LENGTH, MAX_PIXELS, SPEED  # noqa: F401  (LENGTH, SPEED: sysid's cases)
from clflow.scene.config.reader import Reader
from clflow.scene.config.settings import (
    CameraConfig,
    FlowSettings,
    GenerateSettings,
    GuidanceView,
    SceneConfig,
    SimulationSettings,
)


def _flow_mask(r: Reader, flow_in: dict) -> str:
    """ "alpha", "none", or the resolved path of a mask image (checked to exist)."""
    mask = flow_in.get("mask")
    if mask is None or mask in ("alpha", "none"):
        return mask or "alpha"
    if not isinstance(mask, str):
        raise r.fail("flow.mask", f"must be alpha, none or a mask image file, got {mask!r}")
    return str(r.file(flow_in, "mask", "flow"))


def _simulation(r: Reader, data: Any) -> SimulationSettings:
    """``simulation``: its domain and substep read first, then the keys as they declare."""
    p, keys = "simulation", schema.SIMULATION
    body = r.section(data, p, keys.known)
    lower = upper = None
    if body.get("domain") is not None:
        dom = r.section(body["domain"], f"{p}.domain", schema.DOMAIN.known)
        lower, upper = (r.read(dom, f"{p}.domain", schema.DOMAIN[k]) for k in ("min", "max"))
        if not all(lo < hi for lo, hi in zip(lower, upper)):
            raise r.fail(f"{p}.domain", f"min {list(lower)} must be below max {list(upper)} on every axis")
    dt = body.get("substep_dt", "auto")  # absent: auto; null: required (a number or auto)
    substep_dt = None if dt == "auto" else r.number(body, "substep_dt", p, low=keys["substep_dt"].low)
    return SimulationSettings(
        **r.fields(body, p, SimulationSettings, domain_lower=lower, domain_upper=upper, substep_dt=substep_dt)
    )


def _camera(r: Reader, data: Any, p: str = "camera") -> CameraConfig:
    keys = schema.CAMERA
    body = r.section(data, p, keys.known)
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
    position = look_at = None
    if explicit:  # both required; then the camera's own checks (the same point, up along the view)
        position, look_at = (r.vec3(body, k, p, limit=keys[k].high) for k in ("position", "look_at"))
        _check_look_at(r, position, look_at, r.read(body, p, keys["up"]), p)
    return CameraConfig(**r.fields(body, p, CameraConfig, image=image, position=position, look_at=look_at))


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
    keys = schema.GENERATE
    outer = r.section(data, "video", schema.VIDEO.known)
    body = r.section(outer.get("generate"), p, keys.known)
    if not body:
        raise r.fail(p, "is required: at least the model folder (video: {generate: {model: ...}})")
    model = body.get("model")
    if not isinstance(model, str) or not model:
        raise r.fail(f"{p}.model", f"is required: a local diffusers model folder, got {model!r}")
    # the texts, then the flags and the size, then the rest in field order
    texts = {k.name: r.read(body, p, k) for k in keys.keys if k.kind == "text"}
    texts["object"] = texts["object"] or keys["object"].default  # an empty name too
    flags = {k.name: r.read(body, p, k) for k in keys.keys if k.kind == "flag"}
    size = _video_size(r, body.get("size"), f"{p}.size")
    settings = GenerateSettings(
        **r.fields(body, p, GenerateSettings, model=(r.base / model).resolve(), size=size, **texts, **flags)
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


def parse_config(data: Any, source: str = "<config>", base: Path | None = None) -> SceneConfig:
    """Validate a parsed config (dict) and return a :class:`SceneConfig`."""
    r = Reader(source, base or Path.cwd())
    r.no_huge_integers(data)
    top = r.section(data, "", schema.TOP.known)
    if not top:
        raise r.fail("", "the config is empty")
    scene = r.section(top.get("scene"), "scene", schema.SCENE.known)
    objects = parse_objects.objects(r, top)
    material = objects[0].material
    flow = _flow(r, top.get("flow"))
    if len(objects) == 1:
        truth, true_density, true_velocity = parse_optimize.given_truth(r, top.get("evaluation"))
    simulation = _simulation(r, top.get("simulation"))
    output = top.get("output", schema.TOP["output"].default)  # null is no default here
    if not isinstance(output, str) or not output:
        raise r.fail("output", f"must be a folder path, got {output!r}")
    optimize = parse_optimize.optimize_settings(r, top.get("optimize"), objects, simulation.frames)
    if len(objects) == 1:
        truth = parse_optimize.ground_truth(r, truth, true_density, true_velocity, material, optimize)
    else:
        truth = parse_optimize.objects_truth(r, top.get("evaluation"), objects, optimize.materials)
    parse_optimize.check_optimize_fits(r, optimize, simulation, flow)
    forces = parse_objects.forces(r, r.items(top, "forces", ""))
    parse_optimize.check_time_scale(r, optimize, simulation, objects, forces)
    cameras, videos = _views(r, top)
    if len(cameras) > 1 and flow.mask not in ("alpha", "none"):
        raise r.fail("flow.mask", "a mask image fits one view: with several guidance views use alpha or none")
    return SceneConfig(
        source=Path(source),
        splats=r.read(top, "", schema.TOP["splats"]),
        scale=r.read(scene, "scene", schema.SCENE["scale"]),
        up=r.read(scene, "scene", schema.SCENE["up"]),
        objects=objects,
        forces=forces,
        colliders=parse_objects.colliders(r, top.get("boundaries")),
        simulation=simulation,
        camera=cameras[0],
        video=videos[0],  # a video or an image folder
        flow=flow,
        optimize=optimize,
        output=(r.base / output).resolve(),
        ground_truth=truth,
        more_views=tuple(GuidanceView(c, v) for c, v in zip(cameras[1:], videos[1:])),
        dataparser_transforms=r.read(scene, "scene", schema.SCENE["dataparser_transforms"]),
        generate=_generate(r, top.get("video"), simulation),
    )


def _flow(r: Reader, data: Any) -> FlowSettings:
    """``flow``: the optical-flow estimator, the loss, its mask, confidence and bias correction."""
    flow_in = r.section(data, "flow", schema.FLOW.known)
    return FlowSettings(**r.fields(flow_in, "flow", FlowSettings, mask=lambda: _flow_mask(r, flow_in)))
