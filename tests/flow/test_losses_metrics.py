"""Flow losses, EPE/ECMS, .flo files and the Middlebury colouring."""

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.fileio import WRITTEN_RECORD
from clflow.flow.flo import read_flo, write_flo
from clflow.flow.losses import charbonnier_flow_loss, masked_flow_loss, render_loss
from clflow.flow.metrics import ECMS_ALPHA, ecms, endpoint_error, flow_slope
from clflow.flow.visualize import colour_wheel, comparison_panel, flow_to_color, wheel_legend

D = torch.float64


def flows(shape=(2, 4, 5), seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, 2, dtype=D, generator=g), torch.randn(*shape, 2, dtype=D, generator=g)


def test_masked_flow_loss_by_hand():
    sim, obs = flows()
    mask = torch.zeros(4, 5, dtype=torch.bool)
    mask[1:3, 2:] = True
    d2 = ((sim - obs) ** 2).sum(-1)
    assert masked_flow_loss(sim, obs, mask).item() == pytest.approx(d2[:, mask].mean().item(), rel=1e-14)
    assert masked_flow_loss(sim, obs).item() == pytest.approx(d2.mean().item(), rel=1e-14)
    weights = torch.rand(2, 4, 5, dtype=D)
    assert masked_flow_loss(sim, obs, weights).item() == pytest.approx(((weights * d2).sum() / weights.sum()).item())
    eps = 0.5
    expected = torch.sqrt(d2 + eps**2)[:, mask].mean()
    assert charbonnier_flow_loss(sim, obs, mask, eps=eps).item() == pytest.approx(expected.item(), rel=1e-14)


@pytest.mark.parametrize("loss", [masked_flow_loss, charbonnier_flow_loss])
def test_flow_losses_gradcheck(loss):
    sim, obs = flows((2, 3, 3))
    mask = torch.rand(3, 3, dtype=D) > 0.3
    assert torch.autograd.gradcheck(lambda s: loss(s, obs, mask), (sim.requires_grad_(),))


@pytest.mark.parametrize("loss", [masked_flow_loss, charbonnier_flow_loss])
def test_a_pixel_of_zero_weight_changes_neither_the_loss_nor_its_gradient(loss):
    sim, obs = flows()
    weight = torch.rand(2, 4, 5, dtype=D)  # e.g. loss mask x observed-flow confidence
    weight[1, 2, 3] = 0.0
    far = obs.clone()
    far[1, 2, 3] = torch.tensor([40.0, -25.0])  # a wild observed flow where the weight is 0

    def value_and_grad(observed):
        x = sim.clone().requires_grad_()
        value = loss(x, observed, weight)
        value.backward()
        return value.item(), x.grad

    (value, grad), (value_far, grad_far) = value_and_grad(obs), value_and_grad(far)
    assert value_far == value
    assert torch.equal(grad_far, grad) and not grad[1, 2, 3].any()
    assert grad[0, 2, 3].abs().sum() > 0  # the same pixel in the other frame counts


@pytest.mark.parametrize("loss", [masked_flow_loss, charbonnier_flow_loss])
def test_uniform_weights_give_the_unweighted_loss(loss):
    sim, obs = flows()
    mask = torch.zeros(4, 5, dtype=torch.bool)
    mask[1:3, 2:] = True
    uniform = 0.37 * mask * torch.ones(2, 1, 1, dtype=D)  # [T, H, W], the same weight everywhere in the mask
    assert loss(sim, obs, uniform).item() == pytest.approx(loss(sim, obs, mask).item(), rel=1e-14)
    assert loss(sim, obs, torch.full((2, 4, 5), 0.5, dtype=D)).item() == pytest.approx(loss(sim, obs).item(), rel=1e-14)


def test_flow_loss_errors():
    sim, obs = flows()
    with pytest.raises(InputError, match="flow loss: the mask is all zero"):
        masked_flow_loss(sim, obs, torch.zeros(4, 5, dtype=torch.bool))
    bad = obs.clone()
    bad[0, 1, 1, 0] = float("nan")
    with pytest.raises(InputError, match="observed flow contains NaN"):
        masked_flow_loss(sim, bad)
    with pytest.raises(InputError, match="simulated flow contains NaN"):
        charbonnier_flow_loss(bad, obs)
    with pytest.raises(InputError, match=r"one \[..., H, W, 2\] shape"):
        masked_flow_loss(sim, obs[:1])
    with pytest.raises(InputError, match="mask shape"):
        masked_flow_loss(sim, obs, torch.ones(3, 3))
    with pytest.raises(InputError, match="flow loss: the mask has negative weights"):
        masked_flow_loss(sim, obs, -torch.ones(4, 5))


def test_render_loss():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(2, 24, 20, 3, dtype=D, generator=g)
    b = torch.rand(2, 24, 20, 3, dtype=D, generator=g)
    assert render_loss(a, a).item() == pytest.approx(0.0, abs=1e-10)  # kornia adds eps 1e-12
    assert render_loss(a, b, ssim_weight=0.0).item() == pytest.approx((a - b).abs().mean().item(), rel=1e-14)
    # D-SSIM is 1 - SSIM: twice kornia's ssim_loss, which halves it.
    import kornia

    chw = lambda x: x.permute(0, 3, 1, 2)  # noqa: E731
    expected = 2.0 * kornia.losses.ssim_loss(chw(a), chw(b), 11, max_val=1.0)
    assert render_loss(a, b, ssim_weight=1.0).item() == pytest.approx(expected.item(), rel=1e-12)
    small_a, small_b = a[:1, :8, :8, :1].clone().requires_grad_(), b[:1, :8, :8, :1]
    assert torch.autograd.gradcheck(lambda x: render_loss(x, small_b), (small_a,), fast_mode=True)
    with pytest.raises(InputError, match="render loss"):
        render_loss(a, b[..., :2])


def test_endpoint_error():
    flow = np.zeros((1, 2, 2, 2))
    ref = np.zeros((1, 2, 2, 2))
    ref[0, 0, 0] = (3.0, 4.0)
    assert endpoint_error(flow, ref) == pytest.approx(5.0 / 4)
    assert endpoint_error(flow, ref, np.array([[True, False], [False, False]])) == pytest.approx(5.0)
    with pytest.raises(InputError, match="EPE: the mask is all zero"):
        endpoint_error(flow, ref, np.zeros((2, 2), bool))
    ref[0, 1, 1, 1] = np.nan
    with pytest.raises(InputError, match="EPE reference: the flow contains NaN"):
        endpoint_error(flow, ref)


def test_weighted_endpoint_error_and_flow_slope():
    rng = np.random.default_rng(0)
    reference = rng.standard_normal((2, 4, 5, 2))
    across = np.stack([-reference[..., 1], reference[..., 0]], axis=-1)  # perpendicular to the reference
    flow = 0.8 * reference + 0.3 * across
    # slope = sum w flow.ref / sum w |ref|^2: the perpendicular part adds nothing
    assert flow_slope(flow, reference) == pytest.approx(0.8, rel=1e-12)
    weight = rng.random((2, 4, 5))
    assert flow_slope(flow, reference, weight) == pytest.approx(0.8, rel=1e-12)
    flow[0, 1, 1] *= 10.0  # an outlier, then weighted out
    weight[0, 1, 1] = 0.0
    assert flow_slope(flow, reference, weight) == pytest.approx(0.8, rel=1e-12)
    assert flow_slope(flow, reference) > 0.85
    error = np.linalg.norm(flow - reference, axis=-1)
    assert endpoint_error(flow, reference, weight) == pytest.approx((weight * error).sum() / weight.sum(), rel=1e-12)
    assert endpoint_error(flow, reference, weight > 0.5) == pytest.approx(error[weight > 0.5].mean(), rel=1e-12)
    with pytest.raises(InputError, match="flow slope: the reference flow is zero wherever the mask is set"):
        flow_slope(flow, np.zeros_like(reference))
    with pytest.raises(InputError, match="EPE: mask weights must be finite and >= 0"):
        endpoint_error(flow, reference, -weight)


def test_ecms_analytic_cases():
    T, H, W = 4, 6, 7
    # Constant translation (3, 4) px/frame: no change in time, no Laplacian, |v| = 5.
    v = np.broadcast_to(np.array([3.0, 4.0]), (T, H, W, 2))
    assert ecms(v) == pytest.approx(ECMS_ALPHA / (5.0 * T))
    # v_t(x) = (t + x^2, 0): temporal 1 per step, Laplacian 2 everywhere.
    x = np.arange(W, dtype=np.float64)
    v = np.zeros((T, H, W, 2))
    v[..., 0] = np.arange(T)[:, None, None] + x[None, None, :] ** 2
    motion = sum(np.abs(v[t, ..., 0]).mean() for t in range(T))
    assert ecms(v) == pytest.approx((T - 1) * 1.0 + T * 4.0 + ECMS_ALPHA / motion)
    # The mask selects pixels; the Laplacian only where its stencil stays inside the mask.
    mask = np.zeros((H, W), bool)
    mask[1:4, 1:4] = True  # interior of the stencil: the single pixel (2, 2)
    masked_motion = sum(np.abs(v[t, 1:4, 1:4, 0]).mean() for t in range(T))
    assert ecms(v, mask) == pytest.approx((T - 1) + T * 4.0 + ECMS_ALPHA / masked_motion)
    assert ecms(np.zeros((T, H, W, 2))) == float("inf")


def test_flo_round_trip_and_errors(tmp_path):
    flow = np.random.default_rng(0).normal(size=(5, 7, 2)).astype(np.float32)
    write_flo(tmp_path / "a.flo", flow)
    data = (tmp_path / "a.flo").read_bytes()
    assert data[:4] == b"PIEH" and len(data) == 12 + 5 * 7 * 8
    assert np.array_equal(read_flo(tmp_path / "a.flo"), flow)
    (tmp_path / "short.flo").write_bytes(data[:-4])
    with pytest.raises(InputError, match=r"short.flo: header says 7x5 \(292 bytes\) but the file has 288"):
        read_flo(tmp_path / "short.flo")
    (tmp_path / "png.flo").write_bytes(b"\x89PNG" + data[4:])
    with pytest.raises(InputError, match="png.flo: not a Middlebury .flo file"):
        read_flo(tmp_path / "png.flo")
    with pytest.raises(InputError, match="missing.flo: cannot read"):
        read_flo(tmp_path / "missing.flo")
    flow[2, 3, 0] = np.nan
    with pytest.raises(InputError, match="b.flo: the flow contains NaN"):
        write_flo(tmp_path / "b.flo", flow)
    assert not (tmp_path / "b.flo").exists() and sorted(p.name for p in tmp_path.iterdir()) == [
        WRITTEN_RECORD,
        "a.flo",
        "png.flo",
        "short.flo",
    ]


def test_middlebury_colours():
    wheel = colour_wheel()
    assert wheel.shape == (55, 3)
    assert wheel[0].tolist() == [1.0, 0.0, 0.0]  # red starts the wheel
    assert wheel[15].tolist() == [1.0, 1.0, 0.0]  # yellow after the 15 red-yellow steps
    assert wheel[21].tolist() == [0.0, 1.0, 0.0]  # green
    flow = np.zeros((1, 5, 2))
    flow[0, 1] = (1.0, 0.0)  # right
    flow[0, 2] = (-1.0, 0.0)  # left
    flow[0, 3] = (0.5, 0.0)  # right, half speed
    flow[0, 4] = (2.0, 0.0)  # beyond max_flow
    colours = flow_to_color(flow, max_flow=1.0)[0].astype(int)
    assert colours[0].tolist() == [255, 255, 255]  # no motion is white
    assert colours[1].tolist() == [255, 0, 0]  # right is red, the wheel's start (angle -pi)
    assert colours[2, 0] == 0 and colours[2, 1] > 200 and colours[2, 2] == 255  # left is cyan-blue
    assert colours[3].tolist() == [255, 127, 127]  # half saturation: 1 - 0.5 (1 - colour)
    assert colours[4].tolist() == [191, 0, 0]  # beyond the scale: darkened to 0.75
    panel = comparison_panel(np.zeros((5, 6, 3), np.uint8), np.zeros((5, 6, 2)), np.ones((5, 6, 2)))
    assert panel.shape == (5, 24, 3)


def test_colour_wheel_legend_keys_the_flow_colours():
    key = wheel_legend(60, 4.0)
    disc = 60 - 60 // 5  # the label takes the rows below the disc
    cy, cx = disc // 2, 30
    expected = flow_to_color(np.array([[[3.0, 0.0], [0.0, -3.0], [0.0, 0.0]]]), 4.0)[0].astype(int)
    for (y, x), colour in zip([(cy, cx + 18), (cy - 18, cx), (cy, cx)], expected):  # right, up, centre
        assert np.abs(key[y, x].astype(int) - colour).max() <= 12
    assert key[0, 0].tolist() == [0, 0, 0]  # outside the disc
    assert key[disc:].max() == 255  # the "4 px" label
    flow = np.zeros((160, 200, 2))
    flow[..., 0] = 4.0
    panel = comparison_panel(np.zeros((160, 200, 3), np.uint8), flow)
    np.testing.assert_array_equal(panel[-42:-2, -42:-2], wheel_legend(40, 4.0))  # in the guidance flow's corner
    assert (panel[40:100, 200:300] == flow_to_color(flow, 4.0)[40:100, :100]).all()  # below the label: the flow


def test_visualisation_errors(tmp_path):
    from clflow.media import write_video

    frames = np.zeros((2, 8, 8, 3), np.uint8)
    with pytest.raises(InputError, match="out.flv: unsupported video suffix '.flv'"):
        write_video(tmp_path / "out.flv", frames, 10.0)
    with pytest.raises(InputError, match=r"out.mp4: video frames must be \[T, H, W, 3\]"):
        write_video(tmp_path / "out.mp4", frames[..., 0], 10.0)
    with pytest.raises(InputError, match="flow to colour: the flow contains NaN"):
        flow_to_color(np.full((2, 2, 2), np.nan))
    assert list(tmp_path.iterdir()) == []
