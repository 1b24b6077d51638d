"""The 3DGS training recipe (Kerbl et al. 2023) on clflow's OpenCL rasteriser.

    views = load_views("scene/images")
    result = reconstruct(views, "out", Settings(iterations=7000))
    # out/point_cloud.ply, out/cameras.json, out/metrics.json, out/checkpoint.pt

Per iteration one training view (a fresh random order every pass over the views) is
rendered and compared with L1 + 0.2 D-SSIM (kornia); Adam with per-attribute rates: means
``lr_means`` x scene extent decaying exponentially to ``lr_means_final`` x extent, log
scales, quaternions, opacity logits, SH DC and (/20) the higher SH bands, whose degree rises
by one every ``sh_every`` iterations. Densification (clflow.recon.densify) from
``densify_from`` to ``densify_until`` every ``densify_every`` iterations, opacities reset
every ``reset_every`` while densifying, each reset followed by at least ``reset_every``
iterations (3DGS's schedule, 30,000 iterations densified until 15,000, always leaves its last
reset that many; a shorter run that stopped at a reset would end with every Gaussian nearly
transparent: a black scene). Every random draw comes from a generator seeded by (seed, iteration),
so a run on the CPU device is repeatable bit for bit and a resumed run continues exactly.

Scene extent (m): 1.1 x the largest distance of a camera from the cameras' centroid (3DGS).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from clflow.errors import InputError
from clflow.fileio import atomic_path, atomic_write_text
from clflow.recon.densify import DensifySettings, ViewSpaceStats, densify_and_prune, reset_opacities
from clflow.recon.views import View, ViewSet
from clflow.splat.cameras import Camera, save_cameras_json
from clflow.splat.gaussians import Gaussians

CHECKPOINT = "checkpoint.pt"
PARAMETERS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


@dataclass(frozen=True)
class Settings:
    """A training run (3DGS's defaults where it has them; iterations count from 1)."""

    iterations: int = 7000
    seed: int = 0
    sh_degree: int = 3  # highest SH degree
    sh_every: int = 1000  # raise the SH degree by one every this many iterations
    ssim_weight: float = 0.2
    lr_means: float = 1.6e-4  # x extent, at iteration 1
    lr_means_final: float = 1.6e-6  # x extent, at the last iteration
    lr_log_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    densify_from: int = 500
    densify_until: int = 3500
    densify_every: int = 100
    reset_every: int = 3000
    densify: DensifySettings = DensifySettings()
    init_points: int = 10_000  # random initial Gaussians when no point cloud is given
    init_opacity: float = 0.1
    holdout_every: int = 8  # views 0, 8, 16, ... are held out for the metrics
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.sh_every < 1 or self.densify_every < 1 or self.reset_every < 1:
            raise InputError("iterations, sh_every, densify_every and reset_every must be >= 1")
        if not 0 <= self.sh_degree <= 3:
            raise InputError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.init_points < 1:
            raise InputError(f"init_points must be >= 1, got {self.init_points}")

    def sh_degree_at(self, step: int) -> int:
        """The SH degree rendered at iteration ``step`` (from 1)."""
        return min(self.sh_degree, (step - 1) // self.sh_every)


@dataclass
class Result:
    """The trained Gaussians and the metrics written to metrics.json."""

    gaussians: Gaussians
    metrics: dict


def scene_extent(cameras: list[Camera]) -> float:
    """1.1 x the largest distance (m) of a camera centre from the centres' mean (3DGS's radius)."""
    centres = torch.stack([c.position for c in cameras])
    radius = (centres - centres.mean(0)).norm(dim=-1).max().item()
    return 1.1 * radius if radius > 0 else 1.0


def visible_count(points: torch.Tensor, cameras: list[Camera], near: float) -> torch.Tensor:
    """[P] how many of ``cameras`` see each point [P, 3] (m) inside the image, beyond ``near`` m."""
    count = torch.zeros(points.shape[0], dtype=torch.int64)
    for c in cameras:
        p = points @ c.R.T + c.t
        z = p[:, 2].clamp_min(near)
        u, v = c.fx * p[:, 0] / z + c.cx, c.fy * p[:, 1] / z + c.cy
        count += ((p[:, 2] > near) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)).long()
    return count


def random_points(cameras: list[Camera], count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` points [count, 3] (m) uniform in the cameras' common view volume.

    Candidates are drawn in the cube of half-side ``scene_extent`` around the cameras'
    centroid; the points every camera sees (or, if none is, the most cameras) bound a box
    in which points are drawn until ``count`` lie in the volume.
    """
    extent = scene_extent(cameras)
    centre = torch.stack([c.position for c in cameras]).mean(0)
    near = 1e-3 * extent
    candidates = centre + extent * (
        2 * torch.rand(max(20 * count, 50_000), 3, generator=generator, dtype=torch.float64) - 1
    )
    seen = visible_count(candidates, cameras, near)
    need = min(len(cameras), int(seen.max()))
    if need == 0:
        raise InputError("the cameras see nothing within the scene extent around them in common: check the poses")
    inside = candidates[seen >= need]
    low, high = inside.min(0).values, inside.max(0).values
    points = [inside]
    total = len(inside)
    while total < count:
        batch = low + (high - low) * torch.rand(4 * count, 3, generator=generator, dtype=torch.float64)
        batch = batch[visible_count(batch, cameras, near) >= need]
        points.append(batch)
        total += len(batch)
    return torch.cat(points)[:count].float()


def initial_gaussians(views: ViewSet, train: list[View], settings: Settings) -> Gaussians:
    """Degree-0 Gaussians at the COLMAP points (their colours) when the views have them,
    else at ``init_points`` random points in the training cameras' common view volume
    (grey); scales from the 3 nearest neighbours, opacity ``init_opacity`` (3DGS)."""
    if views.points_xyz is not None and len(views.points_xyz) >= 2:
        xyz, rgb = views.points_xyz, views.points_rgb
    else:
        generator = torch.Generator().manual_seed(settings.seed)
        xyz, rgb = random_points([v.camera for v in train], settings.init_points, generator), None
    return Gaussians.from_points(xyz, rgb, opacity=settings.init_opacity)


def _optimizer(params: dict[str, torch.Tensor], settings: Settings, extent: float) -> torch.optim.Adam:
    rates = {
        "means": settings.lr_means * extent,
        "quats": settings.lr_quats,
        "log_scales": settings.lr_log_scales,
        "opacity_logits": settings.lr_opacity,
        "sh0": settings.lr_sh0,
        "shN": settings.lr_shN,
    }
    groups = [
        {"params": [torch.nn.Parameter(params[name].detach().clone())], "lr": rates[name], "name": name}
        for name in PARAMETERS
    ]
    return torch.optim.Adam(groups, eps=1e-15, foreach=False)


def _parameters(gaussians: Gaussians, sh_degree: int) -> dict[str, torch.Tensor]:
    """The optimised table of ``gaussians`` with SH coefficients up to ``sh_degree`` (zeros above 0)."""
    g = gaussians.to(torch.float32)
    n = len(g)
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
    sh[:, : g.sh.shape[1]] = g.sh[:, : sh.shape[1]]
    return {
        "means": g.means,
        "quats": g.quats,
        "log_scales": g.log_scales,
        "opacity_logits": g.opacity_logits,
        "sh0": sh[:, :1],
        "shN": sh[:, 1:],
    }


def _gaussians(params: dict[str, torch.Tensor]) -> Gaussians:
    return Gaussians(
        params["means"],
        params["quats"],
        params["log_scales"],
        params["opacity_logits"],
        sh=torch.cat([params["sh0"], params["shN"]], dim=1),
    )


def render_view(params: dict[str, torch.Tensor], camera: Camera, sh_degree: int, background: torch.Tensor):
    """(image [H, W, 3], meta) of the parameter table seen by ``camera``; differentiable."""
    from clflow.splat.ops import rasterize_gaussians

    image, _, _, meta = rasterize_gaussians(
        params["means"],
        params["quats"],
        params["log_scales"].exp(),
        torch.sigmoid(params["opacity_logits"]),
        torch.cat([params["sh0"], params["shN"]], dim=1),
        camera.viewmat.float(),
        camera.K.float(),
        camera.width,
        camera.height,
        sh_degree=sh_degree,
        background=background,
        render_depth=False,
    )
    return image, meta


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1] (``image`` clamped)."""
    mse = ((image.detach().clamp(0, 1) - target) ** 2).mean().item()
    return 10 * math.log10(1 / max(mse, 1e-20))


def ssim(image: torch.Tensor, target: torch.Tensor) -> float:
    """Mean SSIM (clflow.flow.losses.ssim) of [H, W, 3] images in [0, 1] (``image`` clamped)."""
    from clflow.flow.losses import ssim as mean_ssim

    return mean_ssim(image.detach().clamp(0, 1), target).item()


def evaluate(params: dict[str, torch.Tensor], views: list[View], sh_degree: int, background: torch.Tensor) -> dict:
    """Mean PSNR (dB) and SSIM over ``views`` (3DGS averages per view)."""
    scores = []
    with torch.no_grad():
        for view in views:
            image, _ = render_view(params, view.camera, sh_degree, background)
            scores.append((psnr(image, view.image), ssim(image, view.image)))
    values = np.array(scores).reshape(-1, 2)
    return {
        "views": len(views),
        "psnr": float(values[:, 0].mean()) if len(views) else None,
        "ssim": float(values[:, 1].mean()) if len(views) else None,
    }


def view_order(n: int, step: int, seed: int) -> int:
    """Index of the training view at ``step`` (from 1): a fresh permutation per pass, seeded by (seed, pass)."""
    epoch, position = divmod(step - 1, n)
    generator = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return int(torch.randperm(n, generator=generator)[position])


def reconstruct(
    views: ViewSet,
    out: str | Path,
    settings: Settings = Settings(),
    *,
    resume: bool = False,
    checkpoint_every: int = 1000,
    preview_every: int = 0,
    eval_every: int = 0,
    progress: Callable[[int, dict], None] | None = None,
) -> Result:
    """Train Gaussians on ``views`` and write ``out``/point_cloud.ply, cameras.json,
    metrics.json (held-out PSNR, SSIM, timing) and checkpoint.pt (every
    ``checkpoint_every`` iterations and at the end; ``resume`` continues from it).
    ``preview_every`` > 0 writes ``out``/preview/iter_NNNNNN.png (render | target of the
    first held-out view). ``eval_every`` > 0 records the held-out PSNR every so many
    iterations in metrics["history"] (rows step, training seconds, PSNR dB; evaluation time
    not counted). ``progress(step, info)`` is called every iteration with
    {"psnr": running training PSNR (dB), "gaussians": N}."""
    from clflow.flow.losses import render_loss

    out = Path(out)
    train, test = views.split(settings.holdout_every)
    extent = scene_extent([v.camera for v in views.views])
    background = torch.tensor(settings.background, dtype=torch.float32)
    optimizer, start, stats, seconds, history = _begin(views, train, out, settings, extent, resume)
    params = {g["name"]: g["params"][0] for g in optimizer.param_groups}
    running = None
    began = time.perf_counter()
    for step in range(start + 1, settings.iterations + 1):
        fraction = (step - 1) / max(settings.iterations - 1, 1)
        optimizer.param_groups[0]["lr"] = extent * math.exp(  # group 0: the means
            (1 - fraction) * math.log(settings.lr_means) + fraction * math.log(settings.lr_means_final)
        )
        sh_degree = settings.sh_degree_at(step)
        view = train[view_order(len(train), step, settings.seed)]
        image, meta = render_view(params, view.camera, sh_degree, background)
        meta["means2d"].retain_grad()
        loss = render_loss(image, view.image, settings.ssim_weight)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        value = psnr(image, view.image)
        running = value if running is None else 0.9 * running + 0.1 * value
        if step <= settings.densify_until:
            stats.add(meta["means2d"].grad, meta["radii"], view.camera.width, view.camera.height)
            params, stats = _densify(step, optimizer, stats, params, extent, settings)
        if progress is not None:
            progress(step, {"psnr": running, "gaussians": params["means"].shape[0]})
        if eval_every and test and step % eval_every == 0:
            paused = time.perf_counter()
            history.append([step, seconds + paused - began, evaluate(params, test, sh_degree, background)["psnr"]])
            began += time.perf_counter() - paused
        if preview_every and step % preview_every == 0:
            _write_preview(out / "preview" / f"iter_{step:06d}.png", params, (test or train)[0], sh_degree, background)
        if step % checkpoint_every == 0 or step == settings.iterations:
            _save_checkpoint(
                out / CHECKPOINT, optimizer, stats, step, seconds + time.perf_counter() - began, history, settings
            )
    elapsed = time.perf_counter() - began
    seconds += elapsed
    done = settings.iterations - start
    sh_degree = settings.sh_degree_at(settings.iterations)
    metrics = {
        "test": evaluate(params, test, sh_degree, background),
        "train": evaluate(params, train, sh_degree, background),
        "iterations": settings.iterations,
        "seconds": seconds,
        "iterations_per_second": done / max(elapsed, 1e-9) if done else None,
        "gaussians": params["means"].shape[0],
        "scene_extent_m": extent,
        "history": history,
        "settings": _settings_record(settings),
    }
    return _write_result(out, views, params, metrics)


def _begin(views: ViewSet, train: list, out: Path, settings: Settings, extent: float, resume: bool):
    """Where training starts: the optimiser, the step done, densification statistics,
    training seconds so far and the PSNR history; from the checkpoint with ``resume``."""
    if resume:
        state = _load_checkpoint(out / CHECKPOINT, settings)
        optimizer = _optimizer(state["params"], settings, extent)
        optimizer.load_state_dict(state["optimizer"])
        return optimizer, state["step"], state["stats"], state["seconds"], state["history"]
    gaussians = initial_gaussians(views, train, settings)
    optimizer = _optimizer(_parameters(gaussians, settings.sh_degree), settings, extent)
    stats = ViewSpaceStats.zeros(optimizer.param_groups[0]["params"][0].shape[0])
    return optimizer, 0, stats, 0.0, []


def _densify(step: int, optimizer, stats: ViewSpaceStats, params: dict, extent: float, settings: Settings):
    """At step ``step``: densify and prune on schedule (fresh statistics after), reset the
    opacities on schedule where ``reset_every`` iterations follow; the parameters and
    statistics to go on with."""
    if step > settings.densify_from and step % settings.densify_every == 0:
        params, _ = densify_and_prune(
            optimizer,
            stats,
            extent,
            settings.densify,
            prune_large=step > settings.reset_every,
            generator=torch.Generator().manual_seed(settings.seed * 1_000_003 + step),
        )
        stats = ViewSpaceStats.zeros(params["means"].shape[0])
    if step % settings.reset_every == 0 and settings.iterations - step >= settings.reset_every:
        reset_opacities(optimizer)
    return params, stats


def _write_result(out: Path, views: ViewSet, params: dict, metrics: dict) -> Result:
    """Write point_cloud.ply, cameras.json and metrics.json into ``out``."""
    from clflow.splat.ply import save_ply

    gaussians = _gaussians({k: v.detach() for k, v in params.items()})
    save_ply(out / "point_cloud.ply", gaussians)
    save_cameras_json(out / "cameras.json", [v.camera for v in views.views])
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return Result(gaussians, metrics)


def _settings_record(settings: Settings) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(settings)))


def _save_checkpoint(
    path: Path, optimizer, stats: ViewSpaceStats, step: int, seconds: float, history: list, settings: Settings
) -> None:
    state = {
        "step": step,
        "seconds": seconds,
        "history": history,
        "settings": _settings_record(settings),
        "params": {g["name"]: g["params"][0].detach() for g in optimizer.param_groups},
        "optimizer": optimizer.state_dict(),
        "stats": dataclasses.asdict(stats),
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _load_checkpoint(path: Path, settings: Settings) -> dict:
    if not path.is_file():
        raise InputError(f"{path}: no checkpoint to resume from")
    try:
        state = torch.load(path, weights_only=True)
    except Exception as exc:  # torch raises several types for a damaged or foreign file
        raise InputError(f"{path}: not a readable clflow checkpoint ({exc})") from None
    differ = [k for k, v in _settings_record(settings).items() if state["settings"].get(k) != v]
    if differ:
        raise InputError(
            f"{path}: --resume continues the same run, but these settings differ from it: {', '.join(differ)}"
        )
    state["stats"] = ViewSpaceStats(**state["stats"])
    return state


def _write_preview(path: Path, params, view: View, sh_degree: int, background: torch.Tensor) -> None:
    from clflow.media import to_uint8, write_image

    with torch.no_grad():
        image, _ = render_view(params, view.camera, sh_degree, background)
    write_image(path, np.concatenate([to_uint8(image), to_uint8(view.image)], axis=1))
