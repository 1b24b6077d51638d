"""The objects of a parsed config (``object`` + ``material``, or ``objects``), its force
stages and boundaries, checked into SceneObject, ForceStage and Collider values."""

from __future__ import annotations

import math
import re
from typing import Any

from clflow.errors import InputError
from clflow.materials import DENSITY, get_material, validate_params
from clflow.regions import Region
from clflow.scene.config import schema
from clflow.scene.config.reader import Reader
from clflow.scene.config.schema import Section
from clflow.scene.config.settings import (
    MATERIAL_MODELS,
    SINGLE_OBJECT,
    Collider,
    FillSettings,
    ForceStage,
    MaterialConfig,
    SceneObject,
    Selection,
)


def _region(r: Reader, data: Any, path: str, allow_all: bool, box: Section, sphere: Section) -> Region:
    """A box or sphere (``all`` too, with ``allow_all``), their keys as ``box`` and ``sphere`` declare."""
    if data == "all" and allow_all:
        return Region("all")
    shapes = schema.REGION.known + (("all",) if allow_all else ())
    body = r.section(data, path, schema.REGION.known)  # an object's select takes a mask and a ply besides
    if len(body) != 1:
        raise r.fail(path, f"give exactly one of {', '.join(shapes)}")
    if "box" in body:
        corners = r.section(body["box"], f"{path}.box", box.known)
        lower, upper = (r.read(corners, f"{path}.box", box[k]) for k in ("min", "max"))
        if not all(lo < hi for lo, hi in zip(lower, upper)):
            raise r.fail(f"{path}.box", f"min {list(lower)} must be below max {list(upper)} on every axis")
        return Region.box(lower, upper)
    ball = r.section(body["sphere"], f"{path}.sphere", sphere.known)
    return Region.sphere(*(r.read(ball, f"{path}.sphere", key) for key in sphere.keys))


def _window(r: Reader, data: dict, path: str) -> tuple[float, float]:
    """[start, end) s of a force stage or collider: start >= 0, end after it (default never)."""
    start, end = (r.read(data, path, schema.COLLIDER[k]) for k in ("start", "end"))
    if end <= start:
        raise r.fail(f"{path}.end", f"must be after start ({start:g} s), got {end:g}")
    return start, end


def material(r: Reader, data: Any, p: str = "material") -> MaterialConfig:
    """``p``: the material of one object (``material``, or ``objects.NAME.material``)."""
    body = r.section(data, p, schema.MATERIAL.known)
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
    positive = {"low": 0.0, "strict_low": True}  # then the registry's range (DENSITY), its own message
    if kind == "query":
        if body.get("model") is not None:
            raise r.fail(f"{p}.model", "cannot be chosen before the query picks the material type")
        query = r.section(body.get("query"), f"{p}.query", schema.QUERY.known)
        if query.get("image") is not None and query.get("result") is not None:
            raise r.fail(
                f"{p}.query",
                "give at most one of image (ask the query now) and result (a record `clflow query` wrote); "
                "with neither the query looks at the object in the guidance video's first frame",
            )
        density = (
            r.number(body, "density", p, **positive) if body.get("density") is not None else None
        )  # None: the query's
        backend = r.read(query, f"{p}.query", schema.QUERY["backend"])
        return MaterialConfig(
            "query",
            dict(params_in),
            density,
            query_image=r.read(query, f"{p}.query", schema.QUERY["image"]),
            query_result=r.read(query, f"{p}.query", schema.QUERY["result"]),
            query_prompt=str(query.get("prompt", "")),
            query_backend=backend,
        )
    if body.get("query") is not None:
        raise r.fail(f"{p}.query", f"is only read with type: query (the type is {kind!r})")
    try:
        registered = get_material(kind)
        params = validate_params(registered.name, params_in)
    except InputError as exc:
        raise r.fail(p, str(exc)) from None
    density = r.number(body, "density", p, registered.default_density, **positive)
    DENSITY.check(density, f"{r.source}: {p}.density")
    model = None
    if body.get("model") is not None:
        if registered.name not in MATERIAL_MODELS:
            raise r.fail(
                f"{p}.model", f"{registered.name} has no model option (only {', '.join(MATERIAL_MODELS)} have)"
            )
        model = r.choice(body, "model", p, MATERIAL_MODELS[registered.name])
    return MaterialConfig(registered.name, params, density, model=model)


def forces(r: Reader, items: list) -> tuple[ForceStage, ...]:
    """``forces``: the force stages, each a force (N) or an acceleration (m/s^2) on a region."""
    stages = []
    for i, item in enumerate(items):
        path = f"forces[{i}]"
        body = r.section(item, path, schema.FORCE_STAGE.known)
        kinds = [k for k in ("force", "acceleration") if k in body]
        if len(kinds) != 1:
            raise r.fail(path, "give exactly one of force (N) and acceleration (m/s^2)")
        start, end = _window(r, body, path)
        region_key = schema.FORCE_STAGE["region"]
        stages.append(
            ForceStage(
                _region(
                    r,
                    body.get(region_key.name, region_key.default),
                    f"{path}.region",
                    allow_all=True,
                    box=schema.REGION_BOX,
                    sphere=schema.REGION_SPHERE,
                ),
                r.read(body, path, schema.FORCE_STAGE[kinds[0]]),
                kinds[0],
                start,
                end,
            )
        )
    return tuple(stages)


def colliders(r: Reader, data: Any) -> tuple[Collider, ...]:
    """``boundaries``: the ground and the colliders, each a half-space."""
    body = r.section(data, "boundaries", schema.BOUNDARIES.known)
    out = []
    if body.get("ground") is not None:
        p, ground = "boundaries.ground", schema.GROUND
        found = r.section(body["ground"], p, ground.known)
        height, mode, friction = (r.read(found, p, key) for key in ground.keys)
        out.append(Collider((0.0, height, 0.0), (0.0, 1.0, 0.0), mode, friction))
    for i, item in enumerate(r.items(body, "colliders", "boundaries")):
        path = f"boundaries.colliders[{i}]"
        c = r.section(item, path, schema.COLLIDER.known)
        normal = r.read(c, path, schema.COLLIDER["normal"])
        if math.hypot(*normal) < 1e-6:  # a direction, made a unit vector: its length neither under- nor overflows
            raise r.fail(
                f"{path}.normal", f"must not be the zero vector (its length must be >= 1e-06), got {list(normal)}"
            )
        start, end = _window(r, c, path)
        out.append(Collider(**r.fields(c, path, Collider, normal=normal, start=start, end=end)))
    return tuple(out)


def _selection(r: Reader, data: Any, p: str = "object.select") -> Selection:
    """``p`` (an object's ``select``): exactly one of a region (box, sphere), a mask file or a PLY of the part."""
    select = r.section(data, p, schema.SELECT.known)
    if not select:
        raise r.fail(p, "is required: a box, a sphere, a mask file or a PLY of the part")
    if "tolerance" in select and "ply" not in select:
        raise r.fail(f"{p}.tolerance", "applies to a ply selection only: drop it")
    if len(set(select) & {"box", "sphere", "mask", "ply"}) > 1:
        raise r.fail(p, "give exactly one of box, sphere, mask and ply")
    if "mask" in select:
        return Selection(None, r.read(select, p, schema.SELECT["mask"]))
    if "ply" in select:
        return Selection(
            None, None, r.read(select, p, schema.SELECT["ply"]), r.read(select, p, schema.SELECT["tolerance"])
        )
    region = _region(r, select, p, allow_all=False, box=schema.SELECT_BOX, sphere=schema.SELECT_SPHERE)
    return Selection(region, None)


def _fill(r: Reader, data: Any, p: str = "object.fill") -> FillSettings:
    """``p`` (an object's ``fill``): particles inside the object besides the Gaussian centres."""
    return FillSettings(**r.fields(r.section(data, p, schema.FILL.known), p, FillSettings))


OBJECT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")  # a name fits a --set key: objects.NAME.material...


def objects(r: Reader, top: dict) -> tuple[SceneObject, ...]:
    """``objects`` (a list of entries with a name, or a mapping of names to entries), or the
    single-object form ``object`` + ``material``, read into the same SceneObject tuple."""
    velocity = schema.OBJECT["velocity"]
    if top.get("objects") is None:
        obj = r.section(top.get("object"), "object", schema.OBJECT.known)
        return (
            SceneObject(
                SINGLE_OBJECT,
                _selection(r, obj.get("select")),
                _fill(r, obj.get("fill")),
                material(r, top.get("material")),
                r.read(obj, "object", velocity),
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
            body = r.section(body, where, schema.OBJECT_ENTRY.known)
            entries.append((name, body, where))
    elif isinstance(data, list):
        entries, first = [], {}
        for i, item in enumerate(data):
            body = r.section(item, f"objects[{i}]", schema.OBJECT_ITEM.known)
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
            material(r, body.get("material"), f"{where}.material"),
            r.read(body, where, velocity),
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
