"""taichi's MLS-MPM (Hu et al. 2018, the scheme of taichi's own mpm examples) as the peer of
``clflow bench mpm --peer taichi``: the same particle lattice, grid, step size and elastic
material as clflow's benchmark, on taichi's backend for the device class (``cpu`` or
``cuda``). Written here against taichi's public API; not code from its examples.

One substep, as in clflow (docs/mpm.md): F <- (I + dt C) F, fixed-corotated Kirchhoff stress
from the SVD of F, APIC P2G with quadratic B-splines, grid update with gravity and sticky
walls ``WALL_CELLS`` cells thick (clflow's default walls separate instead; the benchmark's block
reaches neither), G2P; float32, the precision of the benchmark's targets.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from clflow.errors import ClflowError

WALL_CELLS = 3  # grid nodes zeroed against the domain's faces (clflow's default walls: 3)


@dataclass(frozen=True)
class PeerTiming:
    """Substeps timed after a warm-up (taichi compiles on first call)."""

    arch: str
    particles: int
    substeps: int
    seconds: float  # wall time of the timed substeps, synchronised
    centre_drop: float  # m the particles' centre fell: the run moved as gravity says

    @property
    def particle_substeps_per_s(self) -> float:
        return self.particles * self.substeps / self.seconds


def taichi_version() -> str | None:
    """taichi's version, or None when the ``peers`` extra is not installed."""
    try:
        import taichi
    except ImportError:
        return None
    return ".".join(str(v) for v in taichi.__version__)


def run_taichi_mpm(
    positions: np.ndarray,
    grid_nodes: int,
    dx: float,
    dt: float,
    substeps: int,
    *,
    youngs_modulus: float,
    poissons_ratio: float,
    density: float,
    particle_volume: float,
    gravity: float = 9.81,
    arch: str = "cpu",
) -> PeerTiming:
    """Time ``substeps`` substeps of an elastic body of ``positions`` [N, 3] (m) at rest on a
    ``grid_nodes``^3 grid of spacing ``dx`` (m, origin 0) with step ``dt`` (s)."""
    try:
        import taichi as ti
    except ImportError as err:
        raise ClflowError("the taichi peer needs the peers extra: pip install 'clflow[peers]'") from err
    ti.init(arch=getattr(ti, arch), default_fp=ti.f32, log_level=ti.WARN, offline_cache=False)
    mu = youngs_modulus / (2 * (1 + poissons_ratio))
    lam = youngs_modulus * poissons_ratio / ((1 + poissons_ratio) * (1 - 2 * poissons_ratio))
    substep, x = _elastic_substep(ti, positions, grid_nodes, dx, dt, mu, lam, density, particle_volume, gravity)
    substep()  # compiles
    ti.sync()
    t0 = time.perf_counter()
    for _ in range(substeps):
        substep()
    ti.sync()
    seconds = time.perf_counter() - t0
    end = x.to_numpy().astype(np.float64)  # float32 sums of 10^5 rows lose millimetres
    ti.reset()
    if not np.isfinite(end).all():
        raise ClflowError("the taichi peer's run became NaN/inf")
    drop = float(positions.mean(0)[1] - end.mean(0)[1])
    return PeerTiming(arch, positions.shape[0], substeps, seconds, drop)


def _elastic_substep(ti, positions, grid_nodes, dx, dt, mu, lam, density, particle_volume, gravity):
    """(the substep kernel, the positions field) of an elastic body at rest at ``positions``:
    Lame parameters mu, lam (Pa), density (kg/m^3), gravity (m/s^2) along -y."""
    n = positions.shape[0]
    mass, inv_dx = density * particle_volume, 1.0 / dx
    x = ti.Vector.field(3, ti.f32, n)
    v = ti.Vector.field(3, ti.f32, n)
    C = ti.Matrix.field(3, 3, ti.f32, n)
    F = ti.Matrix.field(3, 3, ti.f32, n)
    grid_v = ti.Vector.field(3, ti.f32, (grid_nodes,) * 3)
    grid_m = ti.field(ti.f32, (grid_nodes,) * 3)

    @ti.func
    def weights(p):
        base = ti.cast(x[p] * inv_dx - 0.5, ti.i32)
        fx = x[p] * inv_dx - ti.cast(base, ti.f32)
        w = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
        return base, fx, w  # w[i, d]: the B-spline weight of node base + i along axis d

    @ti.kernel
    def substep():
        for node in ti.grouped(grid_m):
            grid_v[node] = ti.Vector.zero(ti.f32, 3)
            grid_m[node] = 0.0
        for p in x:  # P2G
            base, fx, w = weights(p)
            F[p] = (ti.Matrix.identity(ti.f32, 3) + dt * C[p]) @ F[p]
            U, sig, V = ti.svd(F[p])
            J = sig[0, 0] * sig[1, 1] * sig[2, 2]
            shear = 2.0 * mu * (F[p] - U @ V.transpose()) @ F[p].transpose()
            tau = shear + lam * J * (J - 1.0) * ti.Matrix.identity(ti.f32, 3)
            affine = -dt * particle_volume * 4.0 * inv_dx * inv_dx * tau + mass * C[p]
            for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                dpos = (ti.cast(offset, ti.f32) - fx) * dx
                weight = w[offset[0], 0] * w[offset[1], 1] * w[offset[2], 2]
                grid_v[base + offset] += weight * (mass * v[p] + affine @ dpos)
                grid_m[base + offset] += weight * mass
        for node in ti.grouped(grid_m):  # grid update
            if grid_m[node] > 0:
                vel = grid_v[node] / grid_m[node]
                vel[1] -= dt * gravity
                for d in ti.static(range(3)):
                    if node[d] < WALL_CELLS or node[d] >= grid_nodes - WALL_CELLS:
                        vel = ti.Vector.zero(ti.f32, 3)
                grid_v[node] = vel
        for p in x:  # G2P
            base, fx, w = weights(p)
            new_v = ti.Vector.zero(ti.f32, 3)
            new_C = ti.Matrix.zero(ti.f32, 3, 3)
            for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                dpos = (ti.cast(offset, ti.f32) - fx) * dx
                weight = w[offset[0], 0] * w[offset[1], 1] * w[offset[2], 2]
                g = grid_v[base + offset]
                new_v += weight * g
                new_C += 4.0 * inv_dx * inv_dx * weight * g.outer_product(dpos)
            v[p], C[p] = new_v, new_C
            x[p] += dt * new_v

    x.from_numpy(positions.astype(np.float32))
    F.from_numpy(np.broadcast_to(np.eye(3, dtype=np.float32), (n, 3, 3)).copy())
    return substep, x
