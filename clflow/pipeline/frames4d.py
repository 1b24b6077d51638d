"""Stage 5 of the pipeline: the simulated scene as per-frame Gaussians (4D), written once by
``clflow simulate CONFIG`` and rendered from any viewpoint over time by ``clflow render4d``.

``gaussians.npz`` (simulation frame: metres, +y up) holds the object's n Gaussians per frame
and the static ones once::

    object_means [T+1, n, 3] m, object_covariances [T+1, n, 3, 3] m^2,
    object_sh_rotations [T+1, n, 3, 3]    rotation of each Gaussian since its SH were fitted
    static_means [S, 3], static_covariances [S, 3, 3], static_sh_rotations [S, 3, 3]
    opacities [n + S], sh [n + S, K, 3] (or colors [n + S, C]), object first
    time [T+1] s, fps, camera_viewmat [4, 4], camera_K [3, 3], camera_size [2] (guidance camera)
    scale, up_rotation [3, 3]           x_sim = scale * up_rotation @ x_file
    object [n] int32                    each object Gaussian's object: an index into object_names
    object_names [K] str                the config's objects (``object`` for the single-object form)

(files of clflow before scenes of several objects lack the last two: one object).

``frame_000.ply ...`` are standard 3DGS PLY files in the splat file's own frame and units,
so they overlay the input scene in any 3DGS viewer: the whole scene per frame, or (object
only) the object per frame and ``static.ply`` once; or the same as ``.compressed.ply``
(SuperSplat / PlayCanvas). Each Gaussian of a PLY keeps its object (an index into the npz's
object_names, 0 for the one object of a single-object config), -1 for a static one: a plain
PLY as one more float property, ``object``; a compressed one as runs of vertices named in a
header comment (:mod:`clflow.splat.compressed_ply`). A PLY cannot say that a
Gaussian's SH turned with it, so the object's SH coefficients are written rotated into each frame
(:func:`clflow.splat.sh.rotate_sh`): a viewer shows the view-dependent colours clflow's
renders show.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from clflow.errors import InputError
from clflow.fileio import atomic_path, load_arrays
from clflow.scene.load import to_file_frame, up_rotation
from clflow.splat.gaussians import Gaussians

NPZ_NAME = "gaussians.npz"
#: render4d's entries in its folder: a sequence's PNG folder and video
RENDER_4D_ENTRIES = ("guidance*", "orbit*", "view_*")
STATIC_NAME = "static"  # static.ply: the static Gaussians, once, next to object-only frames


@dataclass
class Frames4D:
    """Per-frame Gaussians of a simulated scene (see the module docstring for the arrays)."""

    arrays: dict[str, np.ndarray]

    @property
    def frame_count(self) -> int:
        return int(self.arrays["object_means"].shape[0])

    @property
    def fps(self) -> float:
        return float(self.arrays["fps"])

    def scene_at(self, t: int, dtype: torch.dtype = torch.float32) -> Gaussians:
        """The whole scene at frame t (object Gaussians first)."""
        a = self.arrays
        get = lambda name, *index: None if name not in a else torch.from_numpy(a[name][index]).to(dtype)  # noqa: E731
        return Gaussians.from_covariances(
            torch.cat([get("object_means", t), get("static_means")]),
            torch.cat([get("object_covariances", t), get("static_covariances")]),
            get("opacities"),
            sh=get("sh"),
            colors=get("colors"),
            sh_rotations=torch.cat([get("object_sh_rotations", t), get("static_sh_rotations")]),
        )

    def guidance_camera(self):
        from clflow.splat.cameras import Camera

        width, height = (int(v) for v in self.arrays["camera_size"])
        return Camera(
            torch.from_numpy(self.arrays["camera_viewmat"]).double(),
            torch.from_numpy(self.arrays["camera_K"]).double(),
            width,
            height,
            "guidance",
        )

    def object_center(self) -> np.ndarray:
        """Centre (m) of the object's Gaussians at rest: the orbit's target."""
        means = self.arrays["object_means"][0]
        return 0.5 * (means.min(0) + means.max(0))


def export_size(prepared, frames: int, preview: bool) -> tuple[int, int]:
    """Upper bounds of (bytes written, bytes held in memory) by simulating ``frames`` frames of
    a :class:`clflow.pipeline.forward.Prepared` scene and exporting them (PLY, npz, preview)."""
    from clflow.limits import TRAJECTORY_REALS

    n, s = prepared.obj_rest.means.shape[0], prepared.static.means.shape[0]
    g = prepared.obj_rest
    colours = g.sh[0].numel() if g.sh is not None else g.colors.shape[1]
    particles = prepared.setup.particles.positions.shape[0]
    cam = prepared.camera
    ply = 15 + colours  # floats per PLY Gaussian, its object's included
    per_frame = 4 * (21 * n + (n + s) * ply) + (6 * cam.width * cam.height if preview else 0)
    held = 4 * (TRAJECTORY_REALS * particles + 21 * n + (n + s) * (22 + colours))  # trajectory, frames, stacks
    return (frames + 1) * per_frame, (frames + 1) * held


def export_gaussians(result, folder: Path, object_only: bool = False, compressed: bool = False) -> None:
    """Write ``folder/gaussians.npz`` and ``folder/frame_000.ply ...`` of a
    :class:`clflow.pipeline.forward.SimulationResult`, each file atomically. With
    ``object_only`` the PLY frames hold the object alone and ``folder/static.ply`` the
    static Gaussians, once; ``compressed``: the PLYs in the compressed layout
    (``frame_000.compressed.ply``, :mod:`clflow.splat.compressed_ply`)."""
    from clflow.splat.compressed_ply import save_compressed_ply
    from clflow.splat.ply import save_ply

    save, suffix = (save_compressed_ply, ".compressed.ply") if compressed else (save_ply, ".ply")

    prepared = result.prepared
    cfg, static = prepared.cfg, prepared.static
    folder.mkdir(parents=True, exist_ok=True)
    frames = [result.scene_at(t) for t in range(result.x.shape[0])]
    n = prepared.obj_rest.means.shape[0]
    f32 = lambda t: t.detach().float().numpy()  # noqa: E731
    first, cam = frames[0], prepared.camera
    arrays = {
        "object_means": np.stack([f32(f.means[:n]) for f in frames]),
        "object_covariances": np.stack([f32(f.covariances[:n]) for f in frames]),
        "object_sh_rotations": np.stack([f32(f.sh_rotations[:n]) for f in frames]),
        "static_means": f32(static.means),
        "static_covariances": f32(static.covariances),
        "static_sh_rotations": f32(first.sh_rotations[n:]),
        "opacities": f32(first.opacities),
        "time": np.arange(len(frames)) / cfg.simulation.fps,
        "fps": np.float64(cfg.simulation.fps),
        "camera_viewmat": cam.viewmat.double().numpy(),
        "camera_K": cam.K.double().numpy(),
        "camera_size": np.array([cam.width, cam.height]),
        "scale": np.float64(cfg.scale),
        "up_rotation": up_rotation(cfg.up).numpy(),
    }
    arrays["sh" if first.sh is not None else "colors"] = f32(first.sh if first.sh is not None else first.colors)
    objects = prepared.gaussian_objects
    arrays["object"] = objects.numpy().astype(np.int32)
    arrays["object_names"] = np.array(cfg.object_names)
    labels = torch.cat([objects, torch.full((static.means.shape[0],), -1, dtype=torch.long)])  # each PLY Gaussian's
    with atomic_path(folder / NPZ_NAME) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    if object_only:
        save(folder / f"{STATIC_NAME}{suffix}", file_gaussians(static, cfg.scale, cfg.up, 0, labels[n:]))
    for t, g in enumerate(frames):
        part, shown = (g.select(torch.arange(n)), labels[:n]) if object_only else (g, labels)
        save(folder / f"frame_{t:03d}{suffix}", file_gaussians(part, cfg.scale, cfg.up, turned=n, objects=shown))


def file_gaussians(g: Gaussians, scale: float, up: str, turned: int, objects: torch.Tensor | None = None) -> Gaussians:
    """Simulation-frame Gaussians as undeformed Gaussians in the splat file's frame and units
    (x_file = R_up^T x_sim / scale), each covariance diagonalised into scales and a rotation.
    The SH of the first ``turned`` (the object's) are rotated by their turn since rest,
    R_up^T sh_rotations, so that a renderer without ``sh_rotations`` shows what clflow
    renders; the others' rotation is the frame change alone. ``objects`` [N]: each one's
    object (-1 static), kept as the float feature ``object`` (a PLY property)."""
    from clflow.splat.geometry import rotmat_to_quat
    from clflow.splat.sh import rotate_sh

    R_up = up_rotation(up)
    means, covs = to_file_frame(g.means.double(), g.covariances.double(), R_up, scale)
    variances, axes = torch.linalg.eigh(covs)
    axes = axes * torch.sign(torch.det(axes))[:, None, None]  # proper rotations
    sh = None if g.sh is None else g.sh.double()
    if sh is not None and turned:
        turns = R_up.T if g.sh_rotations is None else R_up.T @ g.sh_rotations[:turned].double()
        sh = torch.cat([rotate_sh(sh[:turned], turns.expand(turned, 3, 3)), sh[turned:]])
    return Gaussians.from_activated(
        means,
        rotmat_to_quat(axes),
        variances.clamp(min=1e-20).sqrt(),
        g.opacities.double().clamp(1e-6, 1 - 1e-6),
        sh=sh,
        colors=None if g.colors is None else g.colors.double(),
        features=None if objects is None else objects.double()[:, None],
        feature_names=() if objects is None else ("object",),
    )


def load_frames(folder: str | Path) -> Frames4D:
    """Read ``folder/gaussians.npz`` written by :func:`export_gaussians`."""
    path = Path(folder) / NPZ_NAME
    if not path.is_file():
        raise InputError(f"{path} not found: run `clflow simulate CONFIG -o {folder}` first")
    arrays = load_arrays(path, "gaussians file of clflow simulate")
    required = (
        "object_means",
        "object_covariances",
        "object_sh_rotations",
        "static_means",
        "opacities",
        "camera_viewmat",
        "camera_K",
        "camera_size",
        "fps",
    )
    missing = [k for k in required if k not in arrays]
    if missing:
        raise InputError(f"{path}: missing arrays {', '.join(missing)} (not written by clflow simulate?)")
    n = arrays["object_means"].shape[1] if arrays["object_means"].ndim == 3 else -1
    if "object" in arrays and (arrays["object"].shape != (n,) or arrays["object"].dtype.kind not in "iu"):
        got = f"{arrays['object'].dtype} {arrays['object'].shape}"
        raise InputError(f"{path}: object must be {n} integers (each object Gaussian's object), got {got}")
    for name, a in arrays.items():
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            where = f" (first in frame {int(np.argwhere(~np.isfinite(a))[0, 0])})" if name.startswith("object_") else ""
            raise InputError(f"{path}: {name} holds NaN or infinite values{where}")
    return Frames4D(arrays)


def orbit_cameras(frames: Frames4D, count: int, turns: float = 1.0, phase: float = 0.0) -> list:
    """``count`` cameras circling the object (about +y) at the guidance camera's distance and
    elevation, ``turns`` times over the sequence, starting ``phase`` steps past its azimuth
    (0.5: half a step, so that no camera repeats the guidance view)."""
    from clflow.splat.cameras import look_at

    guide = frames.guidance_camera()
    R, t = guide.viewmat[:3, :3], guide.viewmat[:3, 3]
    eye = (-R.T @ t).numpy()
    center = frames.object_center()
    offset = eye - center
    radius = float(np.linalg.norm(offset))
    elevation = math.asin(max(-0.99, min(0.99, offset[1] / radius)))
    azimuth = math.atan2(offset[2], offset[0])
    fov_x = 2 * math.atan(guide.width / (2 * float(guide.K[0, 0])))
    cams = []
    for i in range(count):
        phi = azimuth + 2 * math.pi * turns * (i + phase) / max(1, count)
        direction = np.array(
            [math.cos(elevation) * math.cos(phi), math.sin(elevation), math.cos(elevation) * math.sin(phi)]
        )
        cams.append(
            look_at(
                center + radius * direction,
                center,
                (0.0, 1.0, 0.0),
                fov_x=fov_x,
                width=guide.width,
                height=guide.height,
                name=f"orbit_{i:03d}",
            )
        )
    return cams


def render_4d_size(frames: Frames4D, views: int) -> int:
    """Upper bound of the bytes :func:`render_4d` writes: uncompressed PNG frames and video."""
    width, height = (int(v) for v in frames.arrays["camera_size"])
    return 2 * 3 * width * height * render_4d_frames(frames, views)


def render_4d_frames(frames: Frames4D, views: int) -> int:
    """Frames render_4d renders: the guidance and orbit sequences and ``views`` fixed ones."""
    return (2 + views) * frames.frame_count


def render_4d(
    frames: Frames4D,
    out: Path,
    *,
    views: int = 0,
    turns: float = 1.0,
    video_format: str = "mp4",
    background=(1.0, 1.0, 1.0),
    advance: Callable[[str], None] | None = None,
    source: Path | None = None,
) -> list[Path]:
    """Render the sequence (of the simulation folder ``source``, recorded so that a new
    simulation there removes this stale rendering) into ``out``: ``guidance/`` (the guidance camera), ``orbit/`` (a
    camera circling the object while time runs) and, for ``views`` > 0, ``view_k/`` from k
    fixed novel viewpoints on the same circle, half a step off the guidance camera's azimuth
    (none repeats it). Each folder gets PNG frames and a video
    (``<name>.mp4`` or ``.gif``), all written in a temporary folder and moved into ``out`` at
    the end: a failure leaves ``out`` as it was; ``advance(name)`` is called after each frame
    (render_4d_frames of them). Returns the videos written."""
    from clflow.fileio import atomic_dir
    from clflow.media import to_uint8, write_image, write_video
    from clflow.pipeline.render import render_rgb

    if video_format not in ("mp4", "gif"):
        raise InputError(f"video format must be mp4 or gif, got {video_format!r}")
    if not math.isfinite(turns):
        raise InputError(f"turns of the orbiting camera must be a finite number, got {turns}")
    T = frames.frame_count
    sequences = {"guidance": [frames.guidance_camera()] * T, "orbit": orbit_cameras(frames, T, turns)}
    for k, cam in enumerate(orbit_cameras(frames, views, phase=0.5)):  # between the guidance view's repeats
        sequences[f"view_{k}"] = [cam] * T
    # one result: the earlier sequences (their videos, frames and extra views) go; the record
    # names the simulation it shows, so that simulating there again removes it (stale)
    inputs = [source / NPZ_NAME] if source is not None else []
    with atomic_dir(out, replaces=RENDER_4D_ENTRIES, inputs=inputs, source=source) as tmp:
        for name, cams in sequences.items():
            images = []
            with torch.no_grad():
                for t, cam in enumerate(cams):
                    image = to_uint8(render_rgb(frames.scene_at(t), cam, background))
                    write_image(tmp / name / f"{t:03d}.png", image)
                    images.append(image)
                    if advance is not None:
                        advance(name)
            write_video(tmp / f"{name}.{video_format}", np.stack(images), frames.fps)
    return [out / f"{name}.{video_format}" for name in sequences]


__all__ = [
    "Frames4D",
    "export_gaussians",
    "export_size",
    "file_gaussians",
    "load_frames",
    "orbit_cameras",
    "RENDER_4D_ENTRIES",
    "render_4d",
    "render_4d_frames",
    "render_4d_size",
]
