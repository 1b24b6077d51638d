"""Where does a coarse grid put a fluid's bulk modulus?  A study of model error on the
pure-torch float64 reference substep (clflow.mpm.reference), no kernels.

A Newtonian sphere (diameter 0.3 m, viscosity 100 Pa s, density 1000 kg/m^3: the droplet
of `clflow eval sysid`) falls 0.1 m onto a sticky floor. The "truth" runs at 2h cells per
diameter and bulk modulus K = 7e5 Pa; the model at h cells per diameter over a scan of K.
Their difference: the squared difference of the momentum density (and of the mass density)
on a common 5 cm voxel grid, blurred by [1 2 1]/4 per axis, over 14 frames at 24 fps,
relative to the truth's. Variants:

  --averaged J     cell-averaged J (anti-locking) in truth and model: after each substep the
                   fluid's J is scattered to the grid (mass-weighted) and gathered back, and
                   F = Jbar^(1/3) I;
  --averaged rate  J advanced by the cell-averaged volume rate instead of its own:
                   J' = J (1 + dt avg(tr C)), so only the rate is smoothed, not the state;
  --offset f   the floor plane f cells above a node row in the model (the benchmark: 0.75,
               in truth and model alike);
  --ramp       the sticky floor scales each node's velocity by its distance from the plane
               (a ramp one cell wide) instead of zeroing the nodes behind it.

    python experiments/fluid_model_study.py --offset 0 0.25 0.5 0.75          # ~15 min on one core
    python experiments/fluid_model_study.py --ramp --offset 0 0.25 0.5 0.75
    python experiments/fluid_model_study.py --averaged rate --offset 0.75 0.5

Findings: docs/mpm.md, "Model error of the fluids".
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from clflow.mpm import reference
from clflow.mpm.boundaries import HalfSpace, boundary_table
from clflow.mpm.constants import BC_SLOTS, COLLIDER_MODES, MATERIAL_IDS
from clflow.mpm.shapes import lattice_fill
from clflow.mpm.substep import Grid, Particles, State

DIAMETER, LIFT, DENSITY, VISCOSITY, BULK_MODULUS = 0.3, 0.1, 1000.0, 100.0, 7e5  # m, m, kg/m^3, Pa s, Pa
WIDTH, HEIGHT, FLOOR_Y = 1.0, 0.6, 0.15  # domain and floor plane (m)
FPS, FRAMES = 24, 14
VOXEL = 0.05  # m
SCALES = (0.33, 0.5, 0.75, 1.0, 1.5, 2.0)  # the model's K over the truth's


def halfspace_boundaries(grid: Grid, table: torch.Tensor, ramp: bool):
    """reference._apply_boundaries for half-spaces alone, their node masks computed once (the
    reference recomputes every node's position each substep: 10x the time of this study).
    ``ramp``: a sticky wall scales a node's velocity by clamp(d / dx + 1/2, 0, 1), d its signed
    distance from the plane (m, positive on the free side), instead of zeroing the nodes
    behind it: a coupling that moves continuously with the plane."""
    nx, ny, nz = grid.resolution
    idx = torch.stack(torch.meshgrid(torch.arange(nx), torch.arange(ny), torch.arange(nz), indexing="ij"), -1)
    xi = torch.tensor(grid.origin) + grid.dx * idx.reshape(-1, 3).double()
    walls = []
    for rec in table.tolist():
        a, b = (torch.tensor(rec[BC_SLOTS[s] : BC_SLOTS[s] + 3]) for s in ("BC_A", "BC_B"))
        distance = ((xi - a) * b).sum(-1)
        sticky = int(rec[BC_SLOTS["BC_MODE"]]) == COLLIDER_MODES["sticky"]
        keep = (distance / grid.dx + 0.5).clamp(0, 1) if sticky and ramp else None
        walls.append((distance < 0, b, sticky, keep))

    def apply(grid_, v, active, boundaries, t):
        for inside, n, sticky, keep in walls:
            if keep is not None:
                v = torch.where(active[:, None], keep[:, None] * v, v)
                continue
            new = torch.zeros_like(v) if sticky else v - (v * n).sum(-1, keepdim=True) * n
            v = torch.where((inside & active)[:, None], new, v)
        return v

    return apply


def averaged_J(grid: Grid, x: torch.Tensor, mass: torch.Tensor, J: torch.Tensor) -> torch.Tensor:
    """Jbar_p = sum_i w_ip J_i, J_i = sum_q w_iq m_q J_q / sum_q w_iq m_q (x: positions the
    substep's transfers used)."""
    node_mass, node_mJ = torch.zeros(grid.nodes), torch.zeros(grid.nodes)
    for node, w, _ in reference._stencil_nodes(grid, x):
        node_mass.index_add_(0, node, w * mass)
        node_mJ.index_add_(0, node, w * mass * J)
    node_J = torch.where(node_mass > 0, node_mJ / node_mass.clamp(min=1e-300), 1.0)
    return sum(w * node_J[node] for node, w, _ in reference._stencil_nodes(grid, x))


def averaged_before_stress(grid: Grid, state: State, mass: torch.Tensor, dt: float, averaged: str) -> State:
    """The fluid's F_n = s I rescaled so that the substep's trial J = det((I + dt C_n) F_n),
    which sets its pressure and becomes J_n+1, is the averaged one: "J" the cell average of
    the trial J, "rate" J_n (1 + dt avg tr C_n). Averaging after the substep instead would
    leave each particle's own rate in that substep's pressure, a bulk viscosity K dt."""
    step = torch.linalg.det(torch.eye(3) + dt * state.C)
    J = torch.linalg.det(state.F)
    if averaged == "rate":
        target = J * (1 + dt * averaged_J(grid, state.x, mass, torch.diagonal(state.C, dim1=-2, dim2=-1).sum(-1)))
    else:
        target = averaged_J(grid, state.x, mass, J * step)
    F = (target / step).pow(1 / 3)[:, None, None] * torch.eye(3)
    return State(state.x, state.v, state.C, F, state.plastic)


def voxel_field(x: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """[X, Y, Z, C] trilinear splat of ``value`` [N, C] per m^3 on the common voxels, blurred."""
    shape = (int(WIDTH / VOXEL), int(HEIGHT / VOXEL), int(WIDTH / VOXEL))
    out = torch.zeros(*shape, value.shape[1])
    g = (x - torch.tensor([0.0, FLOOR_Y - VOXEL, 0.0])) / VOXEL - 0.5
    base = torch.floor(g).long()
    frac = g - base
    for corner in range(8):
        bits = [(corner >> a) & 1 for a in range(3)]
        w = math.prod(frac[:, a] if bits[a] else 1 - frac[:, a] for a in range(3))
        i, j, k = ((base[:, a] + bits[a]).clamp(0, shape[a] - 1) for a in range(3))
        out.index_put_((i, j, k), w[:, None] * value, accumulate=True)
    kernel = (0.25, 0.5, 0.25)
    for axis in range(3):
        out = sum(c * torch.roll(out, s, dims=axis) for c, s in zip(kernel, (-1, 0, 1)))
    return out / VOXEL**3


def simulate(cells: int, K: float, averaged: str | None, offset: float, ramp: bool = False):
    """Per-frame (momentum density, mass density, centroid height above the floor) of the
    droplet at ``cells`` cells per diameter and bulk modulus K (Pa)."""
    dx = DIAMETER / cells
    n_side, n_up = round(WIDTH / dx) + 1, round(HEIGHT / dx) + 1
    grid = Grid((n_side, n_up, n_side), dx, (0.0, FLOOR_Y - (3 + offset) * dx, 0.0))
    x = lattice_fill("sphere", DIAMETER, (WIDTH / 2, FLOOR_Y + LIFT + DIAMETER / 2, WIDTH / 2), dx / 2)
    n = x.shape[0]
    volume = torch.full((n,), (dx / 2) ** 3)
    mass = DENSITY * volume
    param = torch.zeros(n, 5)
    param[:, 0], param[:, 1] = VISCOSITY, K
    material = torch.full((n,), MATERIAL_IDS["newtonian"], dtype=torch.int32)
    unset = torch.full((n,), -1, dtype=torch.int32)
    particles = Particles(mass, volume, material, param, unset, torch.zeros(n), 1e-12 * float(mass.min()))
    walls = [HalfSpace((0, FLOOR_Y, 0), (0, 1, 0), "sticky")]
    for axis in (0, 2):
        for sign, face in ((1.0, 3 * dx), (-1.0, WIDTH - 3 * dx)):
            point, normal = [0.0] * 3, [0.0] * 3
            point[axis], normal[axis] = face, sign
            walls.append(HalfSpace(point, normal, "slip"))
    table = boundary_table(walls, torch.float64)
    reference._apply_boundaries = halfspace_boundaries(grid, table, ramp)
    # clflow's limits (clflow.mpm.simulator): elastic waves, viscous diffusion, CFL at 3 m/s (above the impact's)
    dt_limit = min(0.5 * dx / math.sqrt(K / DENSITY), 0.2 * DENSITY * dx * dx / VISCOSITY, 0.3 * dx / 3.0)
    substeps = math.ceil(1 / FPS / dt_limit)
    dt = 1 / FPS / substeps
    state = State(x, torch.zeros(n, 3), torch.zeros(n, 3, 3), torch.eye(3).repeat(n, 1, 1), torch.zeros(n))
    frames, t = [], 0.0
    for frame in range(FRAMES):
        if frame:
            for _ in range(substeps):
                if averaged:
                    state = averaged_before_stress(grid, state, mass, dt, averaged)
                state, _ = reference.substep(
                    state, particles, grid, t, dt, (0, -9.8, 0), table, torch.zeros(0, 3), 0.99
                )
                t += dt
        centroid = float((mass[:, None] * state.x).sum(0)[1] / mass.sum()) - FLOOR_Y
        frames.append((voxel_field(state.x, mass[:, None] * state.v), voxel_field(state.x, mass[:, None]), centroid))
    return frames, substeps, n


def difference(model, truth, field: int) -> float:
    """Squared difference of one field over every frame, relative to the truth's."""
    num = sum(float(((m[field] - t[field]) ** 2).sum()) for m, t in zip(model, truth))
    return num / sum(float((t[field] ** 2).sum()) for t in truth)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=int, default=8, help="the model's cells per diameter (truth: twice)")
    parser.add_argument(
        "--averaged",
        choices=("J", "rate"),
        help="cell-averaged J, or J advanced by the cell-averaged volume rate tr C, in truth and model",
    )
    parser.add_argument(
        "--offset", type=float, nargs="+", default=[0.75], help="the model's floor plane, cells above a node row"
    )
    parser.add_argument("--ramp", action="store_true", help="the sticky floor's ramp coupling in truth and model")
    args = parser.parse_args()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)  # one core a study: several run side by side
    started = time.time()
    truth, substeps, n = simulate(2 * args.cells, BULK_MODULUS, args.averaged, 0.75, args.ramp)
    print(
        f"truth: {2 * args.cells} cells per diameter, {n} particles, {substeps} substeps a frame ({time.time() - started:.0f} s)"
    )
    print(
        f"floor offset | K / truth's | momentum | mass | last frame's centroid (mm; truth's {1e3 * truth[-1][2]:.0f})"
    )
    for offset in args.offset:
        for scale in SCALES:
            model, _, _ = simulate(args.cells, scale * BULK_MODULUS, args.averaged, offset, args.ramp)
            momentum, mass = difference(model, truth, 0), difference(model, truth, 1)
            print(f"{offset:.2f} | {scale:.2f} | {momentum:.4f} | {mass:.4f} | {1e3 * model[-1][2]:.0f}", flush=True)


if __name__ == "__main__":
    main()
