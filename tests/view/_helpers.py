"""Small scenes for the viewer tests: a 3DGS PLY and a simulation folder, and the scene
messages a browser would get over the viewer's websocket."""

import math
import time

import numpy as np
import torch

from clflow.scene.load import up_rotation
from clflow.splat.cameras import look_at
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import save_ply


def write_ply(path, n=60, seed=0):
    """n random degree-1 Gaussians in [0, 1]^3 written to ``path``; returns them."""
    g = torch.Generator().manual_seed(seed)
    sh = torch.randn(n, 4, 3, generator=g, dtype=torch.float64)
    gaussians = Gaussians.from_activated(
        torch.rand(n, 3, generator=g, dtype=torch.float64),
        torch.randn(n, 4, generator=g, dtype=torch.float64),
        torch.full((n, 3), 0.02, dtype=torch.float64),
        torch.full((n,), 0.7, dtype=torch.float64),
        sh=sh,
    )
    save_ply(path, gaussians)
    return gaussians


def write_simulation(folder, *, up="+z", scale=2.0, frames=4, n=20, static=10, seed=1):
    """A gaussians.npz as `clflow simulate CONFIG` writes it, for a splat file with ``up`` and
    ``scale``: the object falls 0.1 scene units a frame along ``up``. Returns the file-frame
    truth: object means [T, n, 3], static means [S, 3], the guidance camera's eye [3]."""
    g = torch.Generator().manual_seed(seed)
    axis = {"x": 0, "y": 1, "z": 2}[up[1]]
    up_vec = np.zeros(3)
    up_vec[axis] = 1.0 if up[0] == "+" else -1.0
    rest = torch.rand(n, 3, generator=g, dtype=torch.float64).numpy()
    means = np.stack([rest - 0.1 * t * up_vec for t in range(frames)])  # scene units
    static_means = torch.rand(static, 3, generator=g, dtype=torch.float64).numpy() + 2.0
    cov = np.diag([1e-4, 4e-4, 9e-4])  # scene units^2, not isotropic: the rotation shows
    eye = np.array([3.0, 1.0, 2.0])
    cam = look_at(eye, (0.5, 0.5, 0.5), up_vec, fov_x=math.radians(50), width=64, height=48)
    R_up = up_rotation(up).numpy()
    to_sim = lambda x: scale * x @ R_up.T  # noqa: E731
    viewmat = cam.viewmat.numpy().copy()
    viewmat[:3, :3] = viewmat[:3, :3] @ R_up.T  # same pixels in the simulation frame
    viewmat[:3, 3] *= scale
    identity = np.broadcast_to(np.eye(3), (frames, n, 3, 3))
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        folder / "gaussians.npz",
        object_means=to_sim(means).astype(np.float32),
        object_covariances=np.broadcast_to(scale**2 * R_up @ cov @ R_up.T, (frames, n, 3, 3)).astype(np.float32),
        object_sh_rotations=identity.astype(np.float32),
        static_means=to_sim(static_means).astype(np.float32),
        static_covariances=np.broadcast_to(scale**2 * R_up @ cov @ R_up.T, (static, 3, 3)).astype(np.float32),
        static_sh_rotations=np.broadcast_to(np.eye(3), (static, 3, 3)).astype(np.float32),
        opacities=np.full(n + static, 0.8, np.float32),
        sh=np.zeros((n + static, 1, 3), np.float32),
        time=np.arange(frames) / 24.0,
        fps=np.float64(24.0),
        camera_viewmat=viewmat,
        camera_K=cam.K.numpy(),
        camera_size=np.array([64, 48]),
        scale=np.float64(scale),
        up_rotation=R_up,
    )
    return means, static_means, eye, cov


def scene_messages(url, timeout=5.0, **options):
    """The messages the viewer at ``url`` (the address it prints, token included) sends a new
    browser on its websocket until its replay is done: dicts with 'type'
    (GaussianSplatsMessage, GuiSliderMessage, ...) and their props. ``options``: more
    arguments of websockets' ``connect`` (origin=, additional_headers=)."""
    import msgspec
    import viser
    import zstandard
    from websockets.sync.client import connect

    messages = []
    deadline = time.monotonic() + timeout
    ws_url = url.replace("http://", "ws://", 1)
    with connect(ws_url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None, **options) as ws:
        while time.monotonic() < deadline:
            data = ws.recv(timeout=deadline - time.monotonic())
            size = int.from_bytes(data[8:16], "little")  # wire format: viser/infra/_infra.py
            batch = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(data[16 : 16 + size]))
            messages += batch["messages"]
            if any(m["type"] == "ReplayDoneMessage" for m in batch["messages"]):
                return messages
    raise AssertionError(f"no ReplayDoneMessage within {timeout} s; got {[m['type'] for m in messages]}")
