"""``clflow bench flow``: observed optical flow of a video and the simulated-flow loss step."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option


def bench_observed(frame_count: int, size: int) -> dict:
    """DIS presets and Farneback on a synthetic textured video with known motion: per
    method, its timing (one run after a warm-up on two frames) and EPE (px)."""
    import numpy as np

    from clflow.benchmark import measure
    from clflow.flow.metrics import endpoint_error
    from clflow.flow.optical_flow import DIS_PRESETS, mask_from_box, observed_flow
    from clflow.flow.synthetic import Motion, moving_texture

    frames, truth = moving_texture(frame_count, size, size, Motion(shift=(1.5, -0.8), angle=0.005, scale=1.004))
    inner = mask_from_box((size / 16, size / 16, size - size / 16, size - size / 16), size, size)
    click.echo(
        f"observed flow: {frame_count} frames {size}x{size} ({frame_count - 1} pairs), synthetic similarity motion"
    )
    results = {}
    for method, preset in [("dis", p) for p in DIS_PRESETS] + [("farneback", "")]:
        observed_flow(frames[:2], method, preset=preset or "medium")  # warm-up
        timing = measure(lambda: observed_flow(frames, method, preset=preset or "medium"), warmup=0)
        flow, elapsed = timing.result, timing.median_wall
        name = f"{method} {preset}".strip()
        epe = endpoint_error(flow, truth, np.broadcast_to(inner, flow.shape[:-1]))
        click.echo(
            f"  {name:14s} {elapsed:7.2f} s total, {1e3 * elapsed / (frame_count - 1):7.1f} ms/pair, EPE {epe:.3f} px"
        )
        results[name] = {**timing.record(), "epe_px": float(epe)}
    return results


def bench_simulated(gaussians: int, frame_count: int, size: int, repeat: int) -> dict:
    """render_simulated_flow + masked L2 loss + backward over consecutive frame pairs of a
    rotating cloud of Gaussians (float32): the timing of each flow model."""
    import torch

    from clflow.benchmark import measure
    from clflow.flow.losses import masked_flow_loss
    from clflow.flow.simulated import render_simulated_flow

    g = torch.Generator().manual_seed(0)
    means = (torch.rand(gaussians, 3, generator=g) * 2 - 1) + torch.tensor([0.0, 0.0, 4.0])
    scales = torch.exp(
        torch.empty(gaussians).uniform_(
            float(torch.log(torch.tensor(0.005))), float(torch.log(torch.tensor(0.03))), generator=g
        )
    )
    covars = scales[:, None, None] ** 2 * torch.eye(3)
    opacities = torch.rand(gaussians, generator=g) * 0.8 + 0.1
    viewmat = torch.eye(4)
    K = torch.tensor([[float(size), 0.0, size / 2], [0.0, float(size), size / 2], [0.0, 0.0, 1.0]])
    angle = torch.tensor(0.01)  # rad per frame about the cloud's vertical axis
    c, s = torch.cos(angle), torch.sin(angle)
    R = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    centre = torch.tensor([0.0, 0.0, 4.0])
    trajectory = [means]
    for _ in range(frame_count):
        trajectory.append((trajectory[-1] - centre) @ R.T + centre)
    observed = torch.zeros(size, size, 2)
    mask = torch.ones(size, size, dtype=torch.bool)
    click.echo(f"simulated flow: {gaussians} Gaussians, {frame_count} frame pairs, {size}x{size}, float32")
    results = {}

    def frames_loss(positions, model) -> float:
        total = 0.0
        for t in range(frame_count):
            flow, _ = render_simulated_flow(
                positions[t],
                positions[t + 1],
                covars,
                opacities,
                viewmat,
                K,
                size,
                size,
                model=model,
                covars_t1=covars if model == "affine" else None,
            )
            loss = masked_flow_loss(flow, observed, mask)
            loss.backward()
            total += float(loss.detach())
        return total

    for model in ("mean", "affine"):  # a warm-up run builds the kernels
        timing = measure(
            lambda positions: frames_loss(positions, model),
            repeat,
            setup=lambda: [p.clone().requires_grad_() for p in trajectory],
        )
        ms = 1e3 * timing.median_wall
        click.echo(
            f"  {model:6s} render + loss + backward: {ms / 1e3:7.2f} s for {frame_count} frames "
            f"({ms / frame_count:7.1f} ms/frame, median of {repeat}); loss sum {timing.result:.3g} px^2"
        )
        results[model] = {**timing.record(), "loss_sum_px2": timing.result}
    return results


@bench_command("flow")
@count_option("--frames", default=49, help="Frames of the observed-flow video.")
@count_option("--size", default=512, help="Frame width and height (pixels).")
@count_option("-n", "--gaussians", default=100_000, help="Gaussians of the simulated flow.")
@count_option("--sim-frames", default=24, help="Frame pairs of the simulated flow.")
@count_option('--repeat', default=1, help="Timed runs of the simulated flow (median printed).")  # fmt: skip
@click.option("--observed/--no-observed", default=True, help="Run the observed-flow part.")
@click.option("--simulated/--no-simulated", default=True, help="Run the simulated-flow part.")
@click.pass_obj
def flow(obj, frames, size, gaussians, sim_frames, repeat, observed, simulated) -> dict:
    """Observed flow of a FRAMES-frame SIZE^2 video (DIS presets, Farneback) and the
    simulated-flow render + loss + backward of N Gaussians over SIM_FRAMES frames."""
    return {
        "observed": bench_observed(frames, size) if observed else None,
        "simulated": bench_simulated(gaussians, sim_frames, size, repeat) if simulated else None,
    }
