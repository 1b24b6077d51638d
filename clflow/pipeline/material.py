"""Stage 2 of the pipeline: a config whose ``material.type`` is ``query`` gets its material
type, density and initial parameters from the material query (clflow.query)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from clflow.errors import InputError
from clflow.fileio import atomic_path
from clflow.materials import get_material, validate_params
from clflow.scene.config import TIME_SCALE, VELOCITY, VELOCITY_COMPONENTS, SceneConfig, split_parameter

log = logging.getLogger(__name__)

QUERY_MARGIN = 0.1  # the object's screen box grows by this fraction of its size on each side
GUIDANCE_FRAME = "guidance_frame0.png"  # in the output folder: what the query looks at without an image


def resolve_material(cfg: SceneConfig) -> SceneConfig:
    """The config with concrete materials.

    For ``type: query`` the query (offline knowledge base or a foundation model), or the
    record of an earlier ``clflow query`` (``material.query.result``), decides the type,
    density and parameters; parameters and density written in the config override the
    query's. The record is saved as ``output/material_query.json`` (with several objects one
    per object that asks: ``output/material_query.NAME.json``). Other configs are returned
    unchanged."""
    if not any(o.material.type == "query" for o in cfg.objects):
        return cfg
    return cfg.with_objects(
        dataclasses.replace(o, material=_resolved(cfg, k)) if o.material.type == "query" else o
        for k, o in enumerate(cfg.objects)
    )


def _resolved(cfg: SceneConfig, k: int):
    """The MaterialConfig the query gives object ``k`` (of ``type: query``), its record saved
    in the output folder (``material_query.json``; with several objects one per object)."""
    from clflow.fileio import check_output_folder

    obj = cfg.objects[k]
    record = obj.own_file("material_query", ".json")
    mat, key = obj.material, obj.material_key
    # before the query is asked: it replaces only what clflow wrote (a record read back in place stays)
    rereads = mat.query_result is not None and mat.query_result.resolve() == (cfg.output / record).resolve()
    written = () if rereads else (record,)
    written += (GUIDANCE_FRAME,) if mat.query_image is None and mat.query_result is None else ()
    check_output_folder(cfg.output, written, [v for v in (cfg.video,) if v is not None])
    if mat.query_result is not None:
        from clflow.query.result import load_query_result

        result = load_query_result(mat.query_result)
    else:
        from clflow.query import ModelConfig
        from clflow.query.backends import query_material

        asked_by = f"{cfg.source}: {key}.query.backend: openai"  # the config has no --llm-url and --model
        model_config = ModelConfig.resolve(asked_by=asked_by) if mat.query_backend == "openai" else None
        image, box = (mat.query_image, None) if mat.query_image is not None else guidance_view_crop(cfg, obj)
        result = query_material(
            image, prompt=mat.query_prompt, box=box, backend=mat.query_backend, model_config=model_config
        )
    for warning in result.warnings:
        log.warning("material query (%s): %s", key, warning)
    cfg.output.mkdir(parents=True, exist_ok=True)
    result.save(cfg.output / record)
    where = f"{cfg.source}: {key}.parameters (material {result.material} from the query)"
    params = validate_params(result.material, {**result.parameters, **mat.parameters}, where)
    known = set(get_material(result.material).param_names) | {"density", VELOCITY, *VELOCITY_COMPONENTS}
    named = [  # this object's (its PARAM of OBJECT.PARAM)
        param
        for n in (*cfg.optimize.parameters, *cfg.ground_truth)
        if n != TIME_SCALE.name  # the scene's, no object's
        for j, param in [split_parameter(cfg.objects, n)]
        if j == k
    ]
    wrong = [n for n in named if n not in known]
    if wrong and obj.name not in cfg.optimize.materials:  # its hypotheses: checked against them (scene config)
        raise InputError(
            f"{cfg.source}: the query chose {result.material}, which has no parameter "
            f"{', '.join(map(repr, wrong))} (optimize.parameters / evaluation.ground_truth)"
        )
    density = mat.density if mat.density is not None else result.density
    log.info(
        "material query (%s): %s, density %g kg/m^3, %s",
        key,
        result.material,
        density,
        params,
    )
    # query_result: the record it came from (what optimize.prior: knowledge reads of the query's match)
    return dataclasses.replace(
        mat, type=result.material, parameters=params, density=density, query_result=cfg.output / record
    )


def guidance_view_crop(cfg: SceneConfig, obj) -> tuple[Path, tuple[float, float, float, float]]:
    """Where the query looks at ``obj`` (a SceneObject of ``cfg``) without an image of its
    own: the guidance video's first frame (written as ``output/guidance_frame0.png``) and
    the pixel box (x0, y0, x1, y1) of the object's Gaussian centres seen by the guidance
    camera, widened by QUERY_MARGIN of its size on each side and cut to the frame. So each of
    several objects is asked about its own part of one picture."""
    import cv2
    import torch

    from clflow.flow.simulated import project_means
    from clflow.flow.video import read_video
    from clflow.scene.load import guidance_camera, load_scene_objects

    where = f"{cfg.source}: {obj.material_key}.query"
    if cfg.video is None or cfg.generate is not None:
        raise InputError(
            f"{where}: without an image the query looks at the guidance video's first frame, and this "
            "config has no video yet (give query.image)"
        )
    frame = read_video(cfg.video, fps=cfg.simulation.fps if cfg.video.is_dir() else None).frames[0]
    camera = guidance_camera(cfg)
    if frame.shape[:2] != (camera.height, camera.width):
        raise InputError(
            f"{cfg.video}: frames are {frame.shape[1]}x{frame.shape[0]} px, the guidance camera "
            f"{camera.width}x{camera.height}: the object's place in the frame is unknown (give {where}.image)"
        )
    gaussians, labels = load_scene_objects(cfg, torch.float64)
    means = gaussians.means[labels == cfg.objects.index(obj)]
    depth = means @ camera.viewmat[2, :3] + camera.viewmat[2, 3]
    pixels = project_means(means[depth > 0], camera.viewmat, camera.K)
    inside = (pixels >= 0).all(1) & (pixels[:, 0] < camera.width) & (pixels[:, 1] < camera.height)
    if not bool(inside.any()):
        raise InputError(f"{where}: the guidance camera does not see {obj.name} (give query.image)")
    low, high = pixels[inside].min(0).values, pixels[inside].max(0).values
    pad = QUERY_MARGIN * (high - low) + 1.0
    x0, y0 = (low - pad).clamp(min=0).tolist()
    x1, y1 = (high + pad).tolist()
    box = (x0, y0, min(x1, camera.width), min(y1, camera.height))
    path = cfg.output / GUIDANCE_FRAME
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)):
            raise InputError(f"cannot write {path}")
    return path, box


__all__ = ["resolve_material"]
