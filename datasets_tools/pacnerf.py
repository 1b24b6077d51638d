"""A PAC-NeRF-style multi-camera capture as a clflow scene (``clflow pacnerf``).

Two commands make such a capture ``clflow optimize``-ready::

    clflow reconstruct data/torus --frame 0 -o recon          # splats of the first frame
    clflow pacnerf data/torus recon -o scene --config configs/torus.py

``make_scene`` writes into the scene folder (atomically, all or nothing):

- ``scene.ply``: the reconstructed splats (a copy);
- ``camera.json``: the chosen camera as a NeRF ``transforms.json`` (its c2w and intrinsic,
  principal point kept; read back into clflow's OpenCV convention by the config loader);
- ``guidance.mp4``: that camera's images of every frame, composited over the background
  (white by default, as clflow renders scenes) where their alpha channel (or ``masks``)
  says, at the sequence's frame rate;
- ``object.png`` (without a PAC-NeRF config): frame 0 of that camera, the material query's image;
- ``config.yaml``: the scene config (docs/scene_config.md), checked by the config parser
  before anything is written.

PAC-NeRF's world is y-up in metres (gravity [0, -9.8, 0], ground plane y = 0), so the
scene has ``up: +y`` and scale 1. Its configs (Python files of ``cfg = dict(...)``, read
without running them, or the same keys as JSON) give the material, its initial guess, the
ground, gravity, the frame interval and which parameters to fit, in clflow's conventions
(docs/reconstruct.md, "Dynamic capture, first frame"): elasticity -> elastic (neo-Hookean),
von Mises with E -> plasticine, von Mises with mu and kappa -> non-Newtonian (eta =
plastic_viscosity), viscous fluid -> Newtonian (viscosity = mu / 2, bulk modulus = 7 kappa),
Drucker-Prager -> sand. Without a config the material is left to the material query
(``material: {type: query}``).
"""

from __future__ import annotations

import ast
import glob
import math
import os
from pathlib import Path
from typing import Any, Sequence

from clflow.errors import InputError
from clflow.fileio import read_json, read_text

OBJECT_OPACITY = 0.1  # Gaussians at least this opaque bound the default object box
BOX_MARGIN = 0.01  # fraction of the box's diagonal added on every side (float rounding, thin objects)
VELOCITY_ITERATIONS = 10  # iterations of the initial-velocity phase (PAC-NeRF's 'velocity' stage)
PACNERF_DENSITY = 1000.0  # kg/m^3: PAC-NeRF's density without 'rho' (10 ** its initial log10 rho of 3)
PACNERF_MATERIALS = {10: "elasticity", 11: "viscous_fluid", 12: "von_mises", 13: "drucker_prager"}  # MPMSimulator ids


def read_pacnerf_config(path: str | os.PathLike, _children: tuple[Path, ...] = ()) -> dict:
    """The ``cfg`` of a PAC-NeRF config: a ``.py`` file (``_base_`` files merged under it, as
    mmcv does; the file is parsed, never run: literals, arithmetic, ``dict(...)`` and
    ``MPMSimulator.NAME``, read as "NAME") or a ``.json`` object of the same keys."""
    path = Path(path)
    if not path.is_file():
        raise InputError(
            f"{path}: PAC-NeRF config not found" + (f" (the _base_ of {_children[-1]})" if _children else "")
        )
    if path.resolve() in _children:
        raise InputError(f"{_children[-1]}: _base_ {path} is a cycle of base files")
    if path.suffix.lower() == ".json":
        cfg = read_json(path, "PAC-NeRF config")
        if not isinstance(cfg, dict):
            raise InputError(f"{path}: expected a JSON object of PAC-NeRF's config keys")
        return cfg
    text = read_text(path, "PAC-NeRF config")
    try:
        tree = ast.parse(text, str(path))
    except SyntaxError as exc:
        raise InputError(f"{path}: line {exc.lineno}: not a Python config ({exc.msg})") from None
    values = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            if node.targets[0].id in ("cfg", "_base_"):
                values[node.targets[0].id] = _literal(node.value, path)
    if not isinstance(values.get("cfg"), dict):
        raise InputError(f"{path}: no 'cfg = dict(...)' assignment (a PAC-NeRF config defines one)")
    base = values.get("_base_")
    if base is None:
        return values["cfg"]
    if not isinstance(base, str):
        raise InputError(f"{path}: _base_ must be a file name, got {base!r}")
    return _merge(read_pacnerf_config(path.parent / base, (*_children, path.resolve())), values["cfg"])


def _merge(base: dict, child: dict) -> dict:
    """``child`` over ``base``, nested dicts merged key by key (mmcv's rule)."""
    out = dict(base)
    for key, value in child.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _literal(node: ast.AST, path: Path) -> Any:
    """The value of an expression made of literals, + - * / ** , dict(...) and Name.attr."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, (ast.List, ast.Tuple)):
        return [_literal(e, path) for e in node.elts]
    if isinstance(node, ast.Dict) and None not in node.keys:
        return {_literal(k, path): _literal(v, path) for k, v in zip(node.keys, node.values)}
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "dict" and not node.args:
        if any(k.arg is None for k in node.keywords):
            raise InputError(f"{path}: line {node.lineno}: dict(**...) is not supported")
        return {k.arg: _literal(k.value, path) for k in node.keywords}
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
        return node.attr  # MPMSimulator.elasticity -> "elasticity"
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        value = _literal(node.operand, path)
        if isinstance(value, (int, float)):
            return -value if isinstance(node.op, ast.USub) else value
    ops = {
        ast.Add: lambda a, b: a + b,
        ast.Sub: lambda a, b: a - b,
        ast.Mult: lambda a, b: a * b,
        ast.Div: lambda a, b: a / b,
        ast.Pow: lambda a, b: a**b,
    }
    if isinstance(node, ast.BinOp) and type(node.op) in ops:
        a, b = _literal(node.left, path), _literal(node.right, path)
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b)):
            try:
                return ops[type(node.op)](a, b)
            except (ZeroDivisionError, OverflowError) as exc:
                raise InputError(f"{path}: line {node.lineno}: {exc}") from None
    raise InputError(
        f"{path}: line {getattr(node, 'lineno', '?')}: cannot read {ast.unparse(node)!r} without running "
        f"the file (numbers, lists, dict(...) and MPMSimulator.NAME only)"
    )


def pacnerf_material(cfg: dict, where: str) -> tuple[dict, list[str]]:
    """(clflow ``material`` section, names of the parameters PAC-NeRF fits) of a PAC-NeRF
    ``cfg`` (its ``material``, E, nu, mu, kappa, yield_stress, plastic_viscosity,
    friction_angle, rho and ``physical_params``), in clflow's SI conventions."""
    from clflow.materials import validate_params

    name = cfg.get("material", "elasticity")  # PAC-NeRF's default
    name = PACNERF_MATERIALS.get(name, name) if isinstance(name, int) else name

    def need(*keys: str) -> list[float]:
        absent = [k for k in keys if not isinstance(cfg.get(k), (int, float)) or isinstance(cfg.get(k), bool)]
        if absent:
            raise InputError(f"{where}: material {name} needs the number(s) {', '.join(absent)}")
        return [float(cfg[k]) for k in keys]

    fit = {
        "global_E": "youngs_modulus",
        "global_nu": "poissons_ratio",
        "yield_stress": "yield_stress",
        "friction_angle": "friction_angle",
        "global_kappa": "bulk_modulus",
        "global_rho": "density",
    }
    model = None
    if name == "elasticity":
        kind, model = "elastic", "neo_hookean"
        params = dict(zip(("youngs_modulus", "poissons_ratio"), need("E", "nu")))
    elif name == "von_mises" and "mu" in cfg and "kappa" in cfg:
        kind = "non_newtonian"
        params = dict(
            zip(
                ("shear_modulus", "bulk_modulus", "yield_stress", "viscosity"),
                need("mu", "kappa", "yield_stress", "plastic_viscosity"),
            )
        )
        fit |= {"global_mu": "shear_modulus", "plastic_viscosity": "viscosity"}
    elif name == "von_mises":
        kind = "plasticine"
        params = dict(zip(("youngs_modulus", "poissons_ratio", "yield_stress"), need("E", "nu", "yield_stress")))
    elif name == "viscous_fluid":
        kind = "newtonian"
        mu, kappa = need("mu", "kappa")
        params = {"viscosity": mu / 2, "bulk_modulus": 7 * kappa}
        fit |= {"global_mu": "viscosity"}
    elif name == "drucker_prager":
        kind, model = "sand", "drucker_prager"
        params = dict(zip(("friction_angle", "youngs_modulus", "poissons_ratio"), need("friction_angle", "E", "nu")))
    else:
        raise InputError(
            f"{where}: unknown PAC-NeRF material {name!r} (elasticity, von_mises, viscous_fluid, drucker_prager)"
        )
    validate_params(kind, params, f"{where}: material {name}")
    density = need("rho")[0] if "rho" in cfg else PACNERF_DENSITY
    section = {"type": kind, **({"model": model} if model else {}), "parameters": params, "density": density}
    physical = cfg.get("physical_params") or {}
    unknown = [k for k in physical if k not in fit]
    if unknown:
        raise InputError(f"{where}: physical_params {', '.join(unknown)} have no clflow counterpart for {name}")
    return section, list(dict.fromkeys(fit[k] for k in physical))


def pacnerf_boundaries(cfg: dict, where: str) -> dict:
    """clflow ``boundaries`` of PAC-NeRF's ``BC`` (name -> [point, normal], sticky planes):
    a plane with normal +y is the ground, others are colliders; cylinders are refused."""
    out: dict = {}
    for name, bc in (cfg.get("BC") or {}).items():
        if not (isinstance(bc, list) and len(bc) == 2 and all(isinstance(v, list) and len(v) == 3 for v in bc)):
            raise InputError(f"{where}: BC {name!r} is not a plane [point, normal] (clflow has no cylinder colliders)")
        point, normal = ([float(x) for x in v] for v in bc)
        length = math.sqrt(sum(x * x for x in normal))
        if length == 0:
            raise InputError(f"{where}: BC {name!r} has a zero normal")
        if normal[0] == normal[2] == 0 and normal[1] > 0 and "ground" not in out:
            out["ground"] = {"height": point[1], "mode": "sticky"}
        else:
            out.setdefault("colliders", []).append({"point": point, "normal": normal, "mode": "sticky"})
    return out


def object_box(means, opacities) -> dict:
    """``object.select.box`` around the Gaussians at least :data:`OBJECT_OPACITY` opaque:
    means [N, 3] (m), opacities [N], grown by :data:`BOX_MARGIN` of its diagonal (+ 1 um, so
    rounding to um keeps every one inside)."""
    keep = opacities >= OBJECT_OPACITY
    if not bool(keep.any()):
        raise InputError(f"no Gaussian is at least {OBJECT_OPACITY} opaque to bound the object: give --box")
    low, high = means[keep].amin(0).double(), means[keep].amax(0).double()
    pad = BOX_MARGIN * float((high - low).norm()) + 1e-6
    return {"min": [round(v, 6) for v in (low - pad).tolist()], "max": [round(v, 6) for v in (high + pad).tolist()]}


def make_scene(
    data: str | os.PathLike,
    splats: str | os.PathLike,
    out: str | os.PathLike,
    *,
    camera: int = 0,
    config: str | os.PathLike | None = None,
    box: Sequence[float] | None = None,
    ground: float | None = None,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    masks: str | os.PathLike | None = None,
    fps: float | None = None,
    prompt: str = "",
    optimize: Sequence[str] = (),
    video: str = "guidance.mp4",
) -> dict:
    """Write the scene folder ``out`` (module docstring) from the capture ``data`` (folder with
    ``all_data.json``), the splats of its frame 0 (``splats``: a PLY or the folder of
    ``clflow reconstruct``'s output) and camera number ``camera``.

    Args:
        config: PAC-NeRF config (.py or .json): material, ground, gravity, frame interval,
            camera and frame counts, parameters to fit.
        box: object box (min xyz, max xyz, m); default: around the opaque Gaussians.
        ground: ground height (m, y up), over the config's.
        background: RGB in [0, 1] behind the masked object (white: what the optimiser renders over).
        fps: frame rate over the config's frame_dt and the index's times.
        prompt: text for the material query (without a config).
        optimize: parameter names to fit, over the config's physical_params.
        video: the guidance video's file name (suffix: a format of clflow.media.write_video).

    Returns a summary: config path, frames, fps and its source, camera, material, fit, box.
    """
    import shutil

    import numpy as np

    from clflow.fileio import atomic_dir, atomic_path, check_output_folder
    from clflow.media import write_image, write_video
    from clflow.recon.sequence import load_sequence
    from clflow.splat.cameras import save_transforms_json
    from clflow.splat.ply import load_ply

    written = ("scene.ply", "camera.json", glob.escape(video), "object.png", "config.yaml")
    check_output_folder(out, written, [data, splats, *([config] if config is not None else [])])  # before the work
    seq = load_sequence(data)
    seq.check_camera(camera)
    ply = _splat_file(Path(splats))
    pac = read_pacnerf_config(config) if config is not None else {}
    where = str(config)
    if "n_cameras" in pac and pac["n_cameras"] != len(seq.cameras):
        raise InputError(f"{where}: n_cameras = {pac['n_cameras']} but {seq.index} has {len(seq.cameras)} cameras")
    frames, fps, fps_from = _frames_and_rate(seq, pac, where, fps)

    gaussians = load_ply(ply)  # read even with a box: a bad PLY is refused before any work
    if box is not None:
        select = {"min": [float(v) for v in box[:3]], "max": [float(v) for v in box[3:]]}
    else:
        select = object_box(gaussians.means, gaussians.opacities)
    cam = seq.cameras[camera]
    images = _masked_frames(seq, camera, frames, masks, background)

    scene = _scene(pac, where, prompt, ground, optimize, fps, frames, select, video)
    made_from = f"{seq.index} (camera {camera}, frames 0-{frames - 1}) and {ply}"
    made_from += f", material from {config}" if pac else ", material left to the query"
    out = Path(out)
    with atomic_dir(out, written, inputs=[data, ply, *([config] if config is not None else [])]) as tmp:
        with atomic_path(tmp / "scene.ply") as part:
            shutil.copyfile(ply, part)
        save_transforms_json(tmp / "camera.json", [cam])
        write_video(tmp / video, np.stack(images), fps)
        if not pac:
            write_image(tmp / "object.png", images[0])
        _write_config(tmp, out / "config.yaml", scene, made_from)
    summary = dict(config=out / "config.yaml", frames=frames, fps=fps, fps_from=fps_from, camera=camera)
    return {
        **summary,
        "material": scene["material"]["type"],
        "optimize": scene["optimize"]["parameters"],
        "box": select,
    }


def _masked_frames(seq, camera: int, frames: int, masks, background: Sequence[float]) -> list:
    """Frames 0..frames-1 of camera ``camera`` [H, W, 3] uint8, the object over ``background``."""
    import torch

    from clflow.media import to_uint8
    from clflow.recon.views import load_view

    bg = torch.as_tensor(background, dtype=torch.float32)
    cam, images = seq.cameras[camera], seq.images[camera]
    return [to_uint8(load_view(cam, images[t], seq.index, masks, bg).image) for t in range(frames)]


def _write_config(folder: Path, final: Path, scene: dict, made_from: str) -> None:
    """``folder``/config.yaml (to become ``final``) with a header saying what it was made
    from; refused when clflow cannot read it."""
    import yaml

    from clflow.scene.config import parse_config

    header = f"# made by `clflow pacnerf` from {made_from}\n"
    if not scene["optimize"]["parameters"]:
        header += (
            "# optimize.parameters is empty: name what to fit once the query has chosen the material, e.g.\n"
            "#   clflow optimize config.yaml --set optimize.parameters=[youngs_modulus]\n"
        )
    text = header + yaml.safe_dump(scene, sort_keys=False, default_flow_style=None)
    parse_config(yaml.safe_load(text), str(final), folder)
    (folder / "config.yaml").write_text(text, encoding="utf-8")


def _splat_file(splats: Path) -> Path:
    """The PLY of ``splats``: the file itself, or point_cloud.ply in clflow reconstruct's folder."""
    ply = splats / "point_cloud.ply" if splats.is_dir() else splats
    if not ply.is_file():
        raise InputError(f"{splats}: no splats (a PLY file, or the folder clflow reconstruct wrote point_cloud.ply in)")
    return ply


def _frames_and_rate(seq, pac: dict, where: str, fps: float | None) -> tuple[int, float, str]:
    """Frames to use (>= 2), the frame rate (Hz) and where it came from: --fps, the config's
    frame_dt or the index's times, in that order."""
    frames = seq.frames
    if isinstance(pac.get("n_frames"), int):
        frames = min(frames, pac["n_frames"])
    if frames < 2:
        raise InputError(f"{seq.index}: {frames} frame(s); a guidance video needs at least 2")
    frame_dt = pac.get("frame_dt")
    if frame_dt is not None and (isinstance(frame_dt, bool) or not isinstance(frame_dt, (int, float)) or frame_dt <= 0):
        raise InputError(f"{where}: frame_dt must be a positive number of seconds, got {frame_dt!r}")
    candidates = (
        (fps, "--fps"),
        (frame_dt and 1 / frame_dt, f"{where} frame_dt"),
        (seq.fps, f"{seq.index.name} times"),
    )
    fps, fps_from = next(((v, s) for v, s in candidates if v), (None, None))
    if fps is None:
        raise InputError(f"{seq.index}: no frame rate: the index has no times; give --fps (or a config with frame_dt)")
    return frames, fps, fps_from


def _scene(pac: dict, where: str, prompt: str, ground, optimize, fps: float, frames: int, select: dict, video: str):
    """The scene config (a dict for config.yaml): material and boundaries from the PAC-NeRF
    config ``pac`` (or left to the query), the object box, the camera and the video."""
    if pac:
        material, fit = pacnerf_material(pac, where)
        boundaries = pacnerf_boundaries(pac, where)
    else:
        material, fit, boundaries = {"type": "query", "query": {"image": "object.png", "prompt": prompt}}, [], {}
    if ground is not None:
        boundaries["ground"] = {"height": float(ground), "mode": "sticky"}
    fit = list(optimize) or fit
    simulation = {"fps": fps, "frames": frames - 1}
    if "gravity" in pac:
        simulation["gravity"] = [float(g) for g in pac["gravity"]]
    scene = {
        "splats": "scene.ply",
        "scene": {"scale": 1.0, "up": "+y"},
        "object": {"select": {"box": select}},
        "material": material,
        **({"boundaries": boundaries} if boundaries else {}),
        "simulation": simulation,
        "camera": {"file": "camera.json", "index": 0},
        "video": video,
        "optimize": {"parameters": fit},
        "output": "results",
    }
    if isinstance(pac.get("hit_frame"), int) and pac["hit_frame"] >= 1:
        scene["optimize"]["estimate_velocity"] = {
            "frames": min(pac["hit_frame"], frames - 1),
            "iterations": VELOCITY_ITERATIONS,
        }
    return scene
