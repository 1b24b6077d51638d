"""Pure-torch reference of one MLS-MPM substep (small sizes; used by the tests and by
experiments/fluid_model_study.py).

Written from the equations, vectorised over particles, independent of the kernels except
for the shared constants; the tests compare the float64 kernels against it.
"""

from __future__ import annotations

import math

import torch

from clflow.mpm.constants import (
    BC_BOX,
    BC_CYLINDER,
    BC_HALFSPACE,
    BC_SLOTS,
    CLAMP_MARGIN,
    COLLIDER_MODES,
    HENCKY_S_MIN,
    MATERIAL_IDS,
    NEWTONIAN_J_MIN,
    SAFE_NORM_EPS2,
    SAND_S_MIN,
)
from clflow.mpm.substep import Grid, Particles, State


def signed_svd(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """F [..., 3, 3] = U diag(s) V^T with U, V rotations and s sorted by |s| (s2 < 0 iff det F < 0)."""
    U, s, Vh = torch.linalg.svd(F)
    V = Vh.transpose(-1, -2)
    flip_u = torch.linalg.det(U) < 0
    flip_v = torch.linalg.det(V) < 0
    sign = torch.ones_like(s)
    U = U.clone()
    V = V.clone()
    U[..., :, 2] = torch.where(flip_u[..., None], -U[..., :, 2], U[..., :, 2])
    V[..., :, 2] = torch.where(flip_v[..., None], -V[..., :, 2], V[..., :, 2])
    sign[..., 2] = torch.where(flip_u ^ flip_v, -1.0, 1.0)
    return U, s * sign, V


def _udvt(U, d, V):
    return U @ torch.diag_embed(d) @ V.transpose(-1, -2)


def _safe_norm(x):
    return torch.sqrt((x * x).sum(-1) + SAFE_NORM_EPS2)


def _deviator(eps):
    return eps - eps.mean(-1, keepdim=True)


def _hencky_tau(U, eps, mu, lam):
    return _udvt(U, 2 * mu[:, None] * eps + lam[:, None] * eps.sum(-1, keepdim=True), U)


def fixed_corotated_tau(F, U, s, V, mu, lam):
    R = U @ V.transpose(-1, -2)
    J = s.prod(-1)
    eye = torch.eye(3, dtype=F.dtype)
    return 2 * mu[:, None, None] * (F - R) @ F.transpose(-1, -2) + (lam * (J - 1) * J)[:, None, None] * eye


def _von_mises(eps, mu, tau_Y):
    eps_hat = _deviator(eps)
    norm = _safe_norm(eps_hat)
    dgamma = norm - math.sqrt(2 / 3) * tau_Y / (2 * mu)
    yielded = dgamma > 0
    eps_new = torch.where(yielded[:, None], eps - dgamma[:, None] * eps_hat / norm[:, None], eps)
    return eps_new, dgamma, yielded


def _log_strain(s):
    return torch.log(torch.clamp(s, min=HENCKY_S_MIN))


def _exp_f(U, eps, V):
    return _udvt(U, torch.exp(eps), V)


def constitutive(material_id: int, F_tr, C, q, plastic, dt):
    """(F_new, plastic_new, tau) of particles of one material; q [n, PARAM_COUNT]."""
    eye = torch.eye(3, dtype=F_tr.dtype)
    ids = MATERIAL_IDS
    if material_id == ids["elastic"]:
        U, s, V = signed_svd(F_tr)
        return F_tr, plastic, fixed_corotated_tau(F_tr, U, s, V, q[:, 0], q[:, 1])
    if material_id == ids["neo_hookean"]:
        J = torch.clamp(torch.linalg.det(F_tr), min=HENCKY_S_MIN**3)
        tau = (
            q[:, 0, None, None] * (F_tr @ F_tr.transpose(-1, -2) - eye) + (q[:, 1] * torch.log(J))[:, None, None] * eye
        )
        return F_tr, plastic, tau
    if material_id == ids["newtonian"]:
        J = torch.clamp(torch.linalg.det(F_tr), min=NEWTONIAN_J_MIN)
        p = q[:, 1] / 7 * (J**-7 - 1)
        D = 0.5 * (C + C.transpose(-1, -2))
        D_dev = D - D.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] * eye
        tau = 2 * (q[:, 0] * J)[:, None, None] * D_dev - (p * J)[:, None, None] * eye
        return torch.pow(J, 1 / 3)[:, None, None] * eye, plastic, tau
    U, s, V = signed_svd(F_tr)
    mu, lam = q[:, 0], q[:, 1]
    if material_id == ids["snow"]:
        s_E = torch.minimum(torch.maximum(s, 1 - q[:, 2:3]), 1 + q[:, 3:4])
        F_E = _udvt(U, s_E, V)
        J_P = plastic * s.prod(-1) / s_E.prod(-1)
        h = torch.exp(q[:, 4] * (1 - J_P))
        return F_E, J_P, fixed_corotated_tau(F_E, U, s_E, V, mu * h, lam * h)
    F_elastic = F_tr  # F' where the return leaves the strain as it is
    if material_id in (ids["plasticine"], ids["metal"]):
        eps = _log_strain(s)
        hardening = plastic if material_id == ids["metal"] else torch.zeros_like(plastic)
        eps, dgamma, yielded = _von_mises(eps, mu, q[:, 2] + hardening)
        if material_id == ids["metal"]:
            plastic = torch.where(yielded, plastic + 2 * mu * q[:, 3] * dgamma, plastic)
    elif material_id in (ids["foam"], ids["non_newtonian"]):
        eps = _log_strain(s)
        eps_hat = _deviator(eps)
        s_norm = 2 * mu * _safe_norm(eps_hat)
        y = s_norm - math.sqrt(2 / 3) * q[:, 2]
        mu_hat = mu * (s * s).sum(-1) / 3
        s_norm_new = s_norm - y / (1 + q[:, 3] / (2 * mu_hat * dt))
        yielded = y > 0
        eps = torch.where(yielded[:, None], (s_norm_new / s_norm)[:, None] * eps_hat + eps.mean(-1, keepdim=True), eps)
    elif material_id in (ids["sand"], ids["sand_volume_corrected"]):
        # Tampubolon et al. 2017: eps = log|s| + v_c/3, v_c' = v_c + log det F_tr - log det F'
        corrected = material_id == ids["sand_volume_corrected"]
        v_c = plastic if corrected else torch.zeros_like(plastic)
        eps_tr = torch.log(torch.clamp(s.abs(), min=SAND_S_MIN))
        eps = eps_tr + v_c[:, None] / 3
        F_elastic = torch.exp(v_c / 3)[:, None, None] * F_tr
        c = q[:, 3]
        excess = eps.sum(-1) - 3 * c
        eps_hat = _deviator(eps)
        norm = _safe_norm(eps_hat)
        dgamma = norm + (3 * lam + 2 * mu) / (2 * mu) * excess * q[:, 2]
        tip = excess >= 0
        cone = ~tip & (dgamma > 0)
        eps = torch.where(tip[:, None], c[:, None].expand(-1, 3), eps)
        eps = torch.where(cone[:, None], eps - dgamma[:, None] * eps_hat / norm[:, None], eps)
        yielded = tip | cone
        if corrected:
            plastic = v_c + eps_tr.sum(-1) - eps.sum(-1)
    else:
        raise ValueError(f"unknown material id {material_id}")
    F_new = torch.where(yielded[:, None, None], _exp_f(U, eps, V), F_elastic)
    return F_new, plastic, _hencky_tau(U, eps, mu, lam)


def _stencil(grid: Grid, x: torch.Tensor):
    """base [N, 3] (long), fx [N, 3], w [N, 3, 3] (axis, offset) of the quadratic B-spline."""
    origin = torch.tensor(grid.origin, dtype=x.dtype)
    xi = (x - origin) / grid.dx
    upper = torch.tensor(grid.resolution) - 3
    base = torch.minimum(torch.clamp(torch.floor(xi - 0.5).long(), min=0), upper)
    fx = xi - base
    w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2], dim=-1)
    return base, fx, w


def _stencil_nodes(grid: Grid, x: torch.Tensor):
    """Yield (node index [N], weight [N], d [N, 3]) for each of the 27 stencil offsets."""
    base, fx, w = _stencil(grid, x)
    nx, ny, nz = grid.resolution
    for i in range(3):
        for j in range(3):
            for k in range(3):
                off = torch.tensor([i, j, k], dtype=x.dtype)
                node = ((base[:, 0] + i) * ny + base[:, 1] + j) * nz + base[:, 2] + k
                yield node, w[:, 0, i] * w[:, 1, j] * w[:, 2, k], (off - fx) * grid.dx


def _apply_boundaries(grid: Grid, v, active, boundaries, t):
    nx, ny, nz = grid.resolution
    idx = torch.stack(torch.meshgrid(torch.arange(nx), torch.arange(ny), torch.arange(nz), indexing="ij"), -1)
    xi = torch.tensor(grid.origin, dtype=v.dtype) + grid.dx * idx.reshape(-1, 3).to(v.dtype)
    for rec in boundaries.to(torch.float64).tolist():
        kind, t0, t1 = int(rec[BC_SLOTS["BC_KIND"]]), rec[BC_SLOTS["BC_T_START"]], rec[BC_SLOTS["BC_T_END"]]
        if not (t0 <= t < t1):
            continue
        a, b, c = (
            torch.tensor(rec[BC_SLOTS[name] : BC_SLOTS[name] + 3], dtype=v.dtype) for name in ("BC_A", "BC_B", "BC_C")
        )
        if kind == BC_HALFSPACE:
            inside = active & (((xi - a) * b).sum(-1) < 0)
            vn = (v * b).sum(-1)
            mode = int(rec[BC_SLOTS["BC_MODE"]])
            if mode == COLLIDER_MODES["sticky"]:
                new = torch.zeros_like(v)
            else:
                vt = v - vn[:, None] * b
                vt_norm = vt.norm(dim=-1)
                friction = rec[BC_SLOTS["BC_FRICTION"]] * torch.clamp(
                    -vn, min=0
                )  # Coulomb: only while moving into the surface
                keep = torch.where(
                    vt_norm > friction,
                    1 - friction / torch.where(vt_norm > 0, vt_norm, 1.0),
                    (friction == 0).to(v.dtype),
                )
                new = keep[:, None] * vt
                if mode == COLLIDER_MODES["separate"]:
                    inside = inside & (vn < 0)
        elif kind == BC_BOX:
            inside = active & ((xi >= a) & (xi <= b)).all(-1)
            new = c.expand_as(v)
        elif kind == BC_CYLINDER:
            r = xi - a
            along = (r * b).sum(-1)
            radial = r - along[:, None] * b
            inside = (
                active
                & (along.abs() <= rec[BC_SLOTS["BC_HALF_LENGTH"]])
                & ((radial * radial).sum(-1) <= rec[BC_SLOTS["BC_RADIUS"]] ** 2)
            )
            new = rec[BC_SLOTS["BC_OMEGA"]] * torch.cross(b.expand_as(r), r, dim=-1)
        else:
            raise ValueError(f"unknown boundary kind {kind}")
        v = torch.where(inside[:, None], new, v)
    return v


def substep(
    state: State,
    particles: Particles,
    grid: Grid,
    t: float,
    dt: float,
    gravity,
    boundaries: torch.Tensor,
    accel: torch.Tensor,
    flip: float = 0.0,
) -> tuple[State, int]:
    """One substep from state n at time t: (state n+1, number of clamped particles); ``flip``
    is the PIC/FLIP blend (0: APIC)."""
    dtype = state.x.dtype
    n = state.x.shape[0]
    eye = torch.eye(3, dtype=dtype)
    F_tr = (eye + dt * state.C) @ state.F
    F_new = torch.empty_like(F_tr)
    plastic_new = state.plastic.clone()
    tau = torch.empty_like(F_tr)
    for mid in particles.material.unique().tolist():
        sel = particles.material == mid
        F_m, pl_m, tau_m = constitutive(mid, F_tr[sel], state.C[sel], particles.param[sel], state.plastic[sel], dt)
        F_new[sel], plastic_new[sel], tau[sel] = F_m, pl_m, tau_m

    m = particles.mass
    affine = -dt * (particles.volume * 4 / grid.dx**2)[:, None, None] * tau + m[:, None, None] * state.C
    group = particles.group.long()
    a_p = torch.where((group >= 0)[:, None], accel[group.clamp(min=0)] if accel.numel() else 0.0, 0.0)
    momentum = m[:, None] * (state.v + dt * a_p)
    grid_m = torch.zeros(grid.nodes, dtype=dtype)
    grid_mv = torch.zeros(grid.nodes, 3, dtype=dtype)
    grid_mv0 = torch.zeros(grid.nodes, 3, dtype=dtype)  # momentum before the forces (FLIP)
    for node, w, d in _stencil_nodes(grid, state.x):
        grid_m.index_add_(0, node, w * m)
        grid_mv.index_add_(0, node, w[:, None] * (momentum + (affine @ d[:, :, None])[..., 0]))
        grid_mv0.index_add_(0, node, (w * m)[:, None] * (state.v + (state.C @ d[:, :, None])[..., 0]))

    active = grid_m > particles.mass_eps
    g = torch.tensor(gravity, dtype=dtype)
    mass = torch.where(active, grid_m, 1.0)[:, None]
    grid_v = torch.where(active[:, None], grid_mv / mass + dt * g, 0.0)
    grid_v = _apply_boundaries(grid, grid_v, active, boundaries, t)
    grid_dv = torch.where(active[:, None], grid_v - grid_mv0 / mass, 0.0)

    v_pic = torch.zeros(n, 3, dtype=dtype)
    dv = torch.zeros(n, 3, dtype=dtype)
    C_new = torch.zeros(n, 3, 3, dtype=dtype)
    for node, w, d in _stencil_nodes(grid, state.x):
        vi = grid_v[node]
        v_pic += w[:, None] * vi
        dv += w[:, None] * grid_dv[node]
        C_new += (4 / grid.dx**2) * w[:, None, None] * vi[:, :, None] * d[:, None, :]
    v_new = flip * (state.v + dv) + (1 - flip) * v_pic
    released = t >= particles.release_time
    v_new = torch.where(released[:, None], v_new, 0.0)
    C_new = torch.where(released[:, None, None], C_new, 0.0)
    moved = state.x + dt * torch.where(released[:, None], v_pic, 0.0)
    lo = torch.tensor(grid.origin, dtype=dtype) + CLAMP_MARGIN * grid.dx
    hi = (
        torch.tensor(grid.origin, dtype=dtype)
        + (torch.tensor(grid.resolution, dtype=dtype) - 1 - CLAMP_MARGIN) * grid.dx
    )
    x_new = torch.minimum(torch.maximum(moved, lo), hi)
    clamped = int(((x_new != moved).any(-1) & released).sum())
    x_new = torch.where(released[:, None], x_new, state.x)
    return State(x_new, v_new, C_new, F_new, plastic_new), clamped
