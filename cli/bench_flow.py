"""``clflow bench flow``: observed optical flow of a video and the simulated-flow loss step."""

import click


def _median_ms(times: list[float]) -> float:
    import statistics

    return 1e3 * statistics.median(times)


def bench_observed(frame_count: int, size: int) -> None:
    """DIS presets and Farneback on a synthetic textured video with known motion."""
    import time

    import numpy as np

    from clflow.flow.metrics import endpoint_error
    from clflow.flow.optical_flow import DIS_PRESETS, mask_from_box, observed_flow
    from clflow.flow.synthetic import Motion, moving_texture

    frames, truth = moving_texture(frame_count, size, size, Motion(shift=(1.5, -0.8), angle=0.005, scale=1.004))
    inner = mask_from_box((size / 16, size / 16, size - size / 16, size - size / 16), size, size)
    click.echo(f"observed flow: {frame_count} frames {size}x{size} ({frame_count - 1} pairs), synthetic similarity motion")
    for method, preset in [("dis", p) for p in DIS_PRESETS] + [("farneback", "")]:
        observed_flow(frames[:2], method, preset=preset or "medium")  # warm-up
        t0 = time.perf_counter()
        flow = observed_flow(frames, method, preset=preset or "medium")
        elapsed = time.perf_counter() - t0
        name = f"{method} {preset}".strip()
        click.echo(
            f"  {name:14s} {elapsed:7.2f} s total, {1e3 * elapsed / (frame_count - 1):7.1f} ms/pair, "
            f"EPE {endpoint_error(flow, truth, np.broadcast_to(inner, flow.shape[:-1])):.3f} px"
        )


def bench_simulated(gaussians: int, frame_count: int, size: int, repeat: int) -> None:
    """render_simulated_flow + masked L2 loss + backward over consecutive frame pairs of a
    rotating cloud of Gaussians (float32)."""
    import time

    import torch

    from clflow.flow.losses import masked_flow_loss
    from clflow.flow.simulated import render_simulated_flow

    g = torch.Generator().manual_seed(0)
    means = (torch.rand(gaussians, 3, generator=g) * 2 - 1) + torch.tensor([0.0, 0.0, 4.0])
    scales = torch.exp(torch.empty(gaussians).uniform_(float(torch.log(torch.tensor(0.005))), float(torch.log(torch.tensor(0.03))), generator=g))
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
    for model in ("mean", "affine"):
        runs = []
        for i in range(repeat + 1):  # the first run builds the kernels and is not timed
            positions = [p.clone().requires_grad_() for p in trajectory]
            t0 = time.perf_counter()
            total = 0.0
            for t in range(frame_count):
                flow, _ = render_simulated_flow(
                    positions[t], positions[t + 1], covars, opacities, viewmat, K, size, size,
                    model=model, covars_t1=covars if model == "affine" else None,
                )
                loss = masked_flow_loss(flow, observed, mask)
                loss.backward()
                total += float(loss.detach())
            if i:
                runs.append(time.perf_counter() - t0)
        click.echo(
            f"  {model:6s} render + loss + backward: {_median_ms(runs) / 1e3:7.2f} s for {frame_count} frames "
            f"({_median_ms(runs) / frame_count:7.1f} ms/frame, median of {repeat}); loss sum {total:.3g} px^2"
        )


@click.command()
@click.option("--frames", default=49, show_default=True, help="Frames of the observed-flow video.")
@click.option("--size", default=512, show_default=True, help="Frame width and height (pixels).")
@click.option("-n", "--gaussians", default=100_000, show_default=True, help="Gaussians of the simulated flow.")
@click.option("--sim-frames", default=24, show_default=True, help="Frame pairs of the simulated flow.")
@click.option("--repeat", default=1, show_default=True, help="Timed runs of the simulated flow (median printed).")
@click.option("--observed/--no-observed", default=True, help="Run the observed-flow part.")
@click.option("--simulated/--no-simulated", default=True, help="Run the simulated-flow part.")
@click.pass_obj
def flow(obj, frames, size, gaussians, sim_frames, repeat, observed, simulated) -> None:
    """Observed flow of a FRAMES-frame SIZE^2 video (DIS presets, Farneback) and the
    simulated-flow render + loss + backward of N Gaussians over SIM_FRAMES frames."""
    if observed:
        bench_observed(frames, size)
    if simulated:
        bench_simulated(gaussians, sim_frames, size, repeat)
