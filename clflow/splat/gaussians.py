"""The :class:`Gaussians` container: a set of 3D Gaussian splats as torch tensors.

Parameters are stored the way 3DGS trainers optimise and save them (and the PLY file holds
them): raw quaternions, log scales and opacity logits. The activated values the rasteriser
and the simulator use are properties::

    g = load_ply("point_cloud.ply")
    g.means          # [N, 3] m, world frame
    g.scales         # [N, 3] m        = exp(log_scales)
    g.opacities      # [N]   in (0, 1) = sigmoid(opacity_logits)
    g.unit_quats     # [N, 4] wxyz, normalised
    g.sh             # [N, K, 3] SH coefficients, K = (sh_degree + 1)^2 (or None: g.colors)
    obj = g.select_sphere(center=(0, 0, 0.5), radius=0.3)

The simulation moves and deforms them without touching the stored parameters: optional
per-Gaussian deformation gradients F (covariance F Sigma F^T) and SH rotations (the turn of
each Gaussian since its SH were fitted)::

    sim = g.transformed(R_up, scale)     # x' = scale R_up x: deformations scale R_up
    moved = sim.deformed(x, F, R)        # centres x, deformations F scale R_up, sh_rotations R R_up
    moved.covariances                    # [N, 3, 3] m^2 = F Sigma F^T (computed once, by deformed)

Storing the raw values makes a PLY round trip bit-exact and lets an optimiser work on
unconstrained parameters.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

import torch

from clflow.errors import InputError
from clflow.splat.constants import MIN_QUAT_NORM
from clflow.splat.geometry import covariances_of, deformed_covariances, nearest_neighbour_rms, quat_to_rotmat
from clflow.splat.sh import rgb_to_sh0, sh_degree_of

TensorLike = torch.Tensor | Sequence[float]


@dataclass(eq=False)
class Gaussians:
    """N 3D Gaussians (world frame, SI units) in their stored parameterisation.

    Attributes:
        means: [N, 3] centres, m.
        quats: [N, 4] rotations as w, x, y, z quaternions, not necessarily normalised.
        log_scales: [N, 3] log of the standard deviations along the local axes (log m).
        opacity_logits: [N] logit of the peak opacity.
        sh: [N, K, 3] spherical-harmonics coefficients of R, G, B, K = (degree + 1)^2;
            ``sh[:, 0]`` is the 3DGS file's ``f_dc``. None when ``colors`` are given instead.
        colors: [N, C] view-independent colours or features, blended as they are. Exactly
            one of ``sh`` and ``colors`` is set.
        features: [N, F] optional extra per-Gaussian channels (e.g. labels, flow), named by
            ``feature_names``; rendered as additional channels.
        deformations: [N, 3, 3] deformation gradients F applied to the rest shape the
            parameters describe (covariance F Sigma F^T); None: undeformed.
        sh_rotations: [N, 3, 3] rotations of each Gaussian since its SH were fitted (the view
            direction is turned back by their transpose); None: identity.
        covariance_cache: [N, 3, 3] the covariances (m^2) when already computed (by
            :meth:`deformed`, :meth:`from_covariances`), so that a deformed copy costs one
            F Sigma F^T; None: computed from the parameters on each access.
    """

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor | None = None
    colors: torch.Tensor | None = None
    features: torch.Tensor | None = None
    feature_names: tuple[str, ...] = ()
    deformations: torch.Tensor | None = None
    sh_rotations: torch.Tensor | None = None
    covariance_cache: torch.Tensor | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.feature_names = tuple(self.feature_names)
        if (self.sh is None) == (self.colors is None):
            raise InputError("Gaussians need exactly one of sh (SH coefficients) and colors")
        n = self.means.shape[0] if isinstance(self.means, torch.Tensor) and self.means.dim() == 2 else -1
        expected = {  # None: any size
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
            "sh": (n, None, 3),
            "colors": (n, None),
            "features": (n, None),
            **{name: (n, 3, 3) for name in MATRIX_FIELDS},
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is None and name in ("sh", "colors", "features", *MATRIX_FIELDS):
                continue
            if not isinstance(value, torch.Tensor) or not _shape_matches(value, shape):
                got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
                raise InputError(f"Gaussians.{name} must have shape {_shape_text(shape)}, got {got}")
        if self.sh is not None:
            sh_degree_of(self.sh.shape[1])
        if self.features is None:
            if self.feature_names:
                raise InputError(f"feature_names {self.feature_names} given without features")
        elif len(self.feature_names) != self.features.shape[1]:
            raise InputError(
                f"{self.features.shape[1]} feature channels but {len(self.feature_names)} "
                f"feature_names {self.feature_names}"
            )

    # -- construction ---------------------------------------------------------------------

    @classmethod
    def from_activated(
        cls,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        *,
        sh: torch.Tensor | None = None,
        colors: torch.Tensor | None = None,
        features: torch.Tensor | None = None,
        feature_names: Sequence[str] = (),
    ) -> "Gaussians":
        """Gaussians from activated values: ``scales`` [N, 3] > 0 m, ``opacities`` [N] in (0, 1).

        Raises :class:`InputError` for non-positive scales or opacities outside (0, 1), which
        have no log / logit.
        """
        scales = torch.as_tensor(scales)
        opacities = torch.as_tensor(opacities)
        _check_finite("scales", scales)
        _check_finite("opacities", opacities)
        if bool((scales <= 0).any()):
            bad = (scales <= 0).nonzero()
            i, axis = bad[0].tolist()
            raise InputError(
                f"{len(bad)} scales are <= 0 (first: Gaussian {i}, axis {axis}, "
                f"{scales[i, axis].item():g} m); a scale is a standard deviation and must be > 0"
            )
        outside = (opacities <= 0) | (opacities >= 1)
        if bool(outside.any()):
            bad = outside.nonzero().flatten()
            i = bad[0].item()
            raise InputError(
                f"{len(bad)} opacities are outside (0, 1) (first: Gaussian {i}, {opacities[i].item():g}); "
                "opacities are stored as logits, so 0 and 1 themselves are not representable"
            )
        gaussians = cls(
            means=torch.as_tensor(means),
            quats=torch.as_tensor(quats),
            log_scales=torch.log(scales),
            opacity_logits=torch.logit(opacities),
            sh=sh,
            colors=colors,
            features=features,
            feature_names=tuple(feature_names),
        )
        gaussians.validate()
        return gaussians

    @classmethod
    def from_covariances(
        cls,
        means: torch.Tensor,
        covariances: torch.Tensor,
        opacities: torch.Tensor,
        *,
        sh: torch.Tensor | None = None,
        colors: torch.Tensor | None = None,
        sh_rotations: torch.Tensor | None = None,
    ) -> "Gaussians":
        """Gaussians of centres ``means`` [N, 3] m and ``covariances`` [N, 3, 3] m^2 (kept as
        given in ``covariance_cache``): unit Gaussians (1 m, identity rotation) deformed by a
        factor L of each covariance, L L^T = Sigma (Cholesky; the eigen-factor where Sigma is
        singular). Cheap (no diagonalisation, no :meth:`validate`), as a per-frame render
        needs. ``opacities`` [N] clamped into [1e-6, 1 - 1e-6] (their logits are stored)."""
        n, dtype = means.shape[0], means.dtype
        factors, failed = torch.linalg.cholesky_ex(covariances.detach())
        singular = failed != 0
        if bool(singular.any()):
            variances, axes = torch.linalg.eigh(covariances.detach()[singular])
            factors[singular] = axes * variances.clamp(min=0).sqrt().unsqueeze(-2)
        quats = torch.zeros(n, 4, dtype=dtype, device=means.device)
        quats[:, 0] = 1
        return cls(
            means=means,
            quats=quats,
            log_scales=torch.zeros(n, 3, dtype=dtype, device=means.device),
            opacity_logits=torch.logit(opacities.clamp(1e-6, 1 - 1e-6)),
            sh=sh,
            colors=colors,
            deformations=factors,
            sh_rotations=sh_rotations,
            covariance_cache=covariances,
        )

    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,
        rgb: torch.Tensor | None = None,
        *,
        scale: float | None = None,
        opacity: float = 0.1,
    ) -> "Gaussians":
        """Isotropic degree-0 Gaussians at ``points`` [N, 3] m, as 3DGS initialises from a point cloud.

        Args:
            rgb: [N, 3] colours in [0, 1]; mid grey when None.
            scale: standard deviation in m for every Gaussian; default: the root mean
                square distance to each point's three nearest neighbours (3DGS's rule).
            opacity: peak opacity in (0, 1); 0.1 is 3DGS's initial value.
        """
        points = torch.as_tensor(points)
        if points.dim() != 2 or points.shape[1] != 3:
            raise InputError(f"points must have shape [N, 3], got {tuple(points.shape)}")
        n = points.shape[0]
        _check_finite("points", points)
        if scale is None:
            if n < 2:
                raise InputError(f"{n} point(s): cannot derive a scale from neighbours; pass scale=")
            scales = nearest_neighbour_rms(points, k=3).clamp_min(math.sqrt(1e-7))
        else:
            if not scale > 0:
                raise InputError(f"scale must be > 0 m, got {scale}")
            scales = torch.full((n,), float(scale), dtype=points.dtype)
        if rgb is None:
            rgb = torch.full((n, 3), 0.5, dtype=points.dtype)
        rgb = torch.as_tensor(rgb, dtype=points.dtype)
        if tuple(rgb.shape) != (n, 3):
            raise InputError(f"rgb must have shape [N={n}, 3], got {tuple(rgb.shape)}")
        quats = torch.zeros(n, 4, dtype=points.dtype)
        quats[:, 0] = 1
        return cls.from_activated(
            points,
            quats,
            scales[:, None].expand(n, 3).contiguous(),
            torch.full((n,), float(opacity), dtype=points.dtype),
            sh=rgb_to_sh0(rgb)[:, None, :],
        )

    # -- activated values -----------------------------------------------------------------

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        """[N, 3] standard deviations along the local axes, m."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """[N] peak opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def unit_quats(self) -> torch.Tensor:
        """[N, 4] normalised wxyz quaternions."""
        return torch.nn.functional.normalize(self.quats, dim=-1)

    @property
    def rotations(self) -> torch.Tensor:
        """[N, 3, 3] local-to-world rotation matrices."""
        return quat_to_rotmat(self.quats)

    @property
    def covariances(self) -> torch.Tensor:
        """[N, 3, 3] world covariances, m^2: F R diag(s^2) R^T F^T (F = I when undeformed; in
        F's dtype when set)."""
        if self.covariance_cache is not None:
            return self.covariance_cache
        rest = covariances_of(self.scales, self.rotations)
        F = self.deformations
        return rest if F is None else deformed_covariances(rest.to(F.dtype), F)

    @property
    def sh_degree(self) -> int | None:
        """SH degree 0..3, or None when the Gaussians carry plain colours."""
        return None if self.sh is None else sh_degree_of(self.sh.shape[1])

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    # -- checks ----------------------------------------------------------------------------

    def validate(self, where: str = "Gaussians") -> "Gaussians":
        """Raise :class:`InputError` (prefixed by ``where``) for values no renderer can use.

        Checks: every value finite, quaternions of norm >= MIN_QUAT_NORM (1e-8), scales > 0 after
        activation (a log scale below about -87 underflows to 0 in float32).
        """
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh", "colors", "features", *MATRIX_FIELDS):
            value = getattr(self, name)
            if value is not None:
                _check_finite(name, value, where)
        with torch.no_grad():
            short = torch.linalg.vector_norm(self.quats, dim=-1) < MIN_QUAT_NORM
            if bool(short.any()):
                bad = short.nonzero().flatten()
                i = bad[0].item()
                raise InputError(
                    f"{where}: {len(bad)} degenerate quaternions of norm < {MIN_QUAT_NORM:g} "
                    f"(first: Gaussian {i}, wxyz {self.quats[i].tolist()}); a rotation needs a non-zero quaternion"
                )
            zero = self.scales <= 0
            if bool(zero.any()):
                bad = zero.nonzero()
                i, axis = bad[0].tolist()
                raise InputError(
                    f"{where}: {len(bad)} scales are 0 after activation (first: Gaussian {i}, "
                    f"log scale_{axis} = {self.log_scales[i, axis].item():g}); exp() underflows below "
                    f"{math.log(torch.finfo(self.dtype).tiny):.1f}"
                )
        return self

    def check_undeformed(self, where: str) -> None:
        """Raise :class:`InputError` when deformations or SH rotations are set: a 3DGS file
        holds the parameters alone (frames4d's ``file_gaussians`` writes moved Gaussians)."""
        if self.deformations is not None or self.sh_rotations is not None:
            raise InputError(
                f"{where}: these Gaussians are deformed or turned (deformations / sh_rotations), "
                "which a splat file cannot hold (clflow.pipeline.frames4d.file_gaussians writes them)"
            )

    # -- deformation ------------------------------------------------------------------------

    def deformed(self, means: torch.Tensor, F: torch.Tensor, rotations: torch.Tensor) -> "Gaussians":
        """A copy centred at ``means`` [N, 3] m and deformed by ``F`` [N, 3, 3] on top of any
        deformation so far: deformations F D, covariances F Sigma F^T (computed here, in F's
        dtype), sh_rotations ``rotations`` [N, 3, 3] times the ones so far (``rotations``: the
        turn of each Gaussian, R of F = R S: :func:`clflow.scene.deform.polar_rotations`).
        Differentiable in ``means`` and ``F``."""
        return dataclasses.replace(
            self,
            means=means,
            deformations=F if self.deformations is None else F @ self.deformations.to(F.dtype),
            sh_rotations=rotations if self.sh_rotations is None else rotations @ self.sh_rotations.to(rotations.dtype),
            covariance_cache=deformed_covariances(self.covariances.to(F.dtype), F),
        )

    def transformed(self, rotation: torch.Tensor | None = None, scale: float = 1.0) -> "Gaussians":
        """The Gaussians in the frame x' = scale R x (``rotation`` R [3, 3] proper, default
        identity): a uniform deformation scale R with sh_rotations R; means, deformations,
        sh_rotations and covariances in float64, the stored parameters as they are (call
        ``.to(dtype)`` before rendering)."""
        R = torch.eye(3, dtype=torch.float64) if rotation is None else rotation.double()
        Rs = R.expand(len(self), 3, 3)
        return self.deformed(scale * self.means.double() @ R.T, scale * Rs, Rs)

    # -- selection and assembly ------------------------------------------------------------

    def select(self, mask: torch.Tensor) -> "Gaussians":
        """The Gaussians picked by a boolean ``mask`` [N] or an index tensor (may be empty)."""
        mask = torch.as_tensor(mask)
        if mask.dtype == torch.bool:
            if tuple(mask.shape) != (len(self),):
                raise InputError(f"selection mask has shape {tuple(mask.shape)}, expected [{len(self)}]")
        elif mask.dtype in (torch.int32, torch.int64) and mask.dim() == 1:
            if len(mask) and (mask.min() < -len(self) or mask.max() >= len(self)):
                raise InputError(f"selection index out of range for {len(self)} Gaussians")
        else:
            raise InputError(f"select takes a bool mask or a 1-D integer index, got {mask.dtype} {tuple(mask.shape)}")
        return self._map(lambda t: t[mask])

    def box_mask(self, low: TensorLike, high: TensorLike) -> torch.Tensor:
        """[N] bool: centres inside the axis-aligned box ``low`` <= x <= ``high`` (m)."""
        low, high = self._point(low, "box low"), self._point(high, "box high")
        if not bool((low <= high).all()):
            raise InputError(f"box low {low.tolist()} is not <= high {high.tolist()} on every axis")
        return ((self.means >= low) & (self.means <= high)).all(dim=-1)

    def sphere_mask(self, center: TensorLike, radius: float) -> torch.Tensor:
        """[N] bool: centres within ``radius`` m of ``center``."""
        if not radius >= 0:
            raise InputError(f"sphere radius must be >= 0 m, got {radius}")
        center = self._point(center, "sphere center")
        return ((self.means - center) ** 2).sum(-1) <= radius**2

    def select_box(self, low: TensorLike, high: TensorLike) -> "Gaussians":
        """The Gaussians whose centres lie in the box ``low`` <= x <= ``high`` (m)."""
        return self.select(self.box_mask(low, high))

    def select_sphere(self, center: TensorLike, radius: float) -> "Gaussians":
        """The Gaussians whose centres lie within ``radius`` m of ``center``."""
        return self.select(self.sphere_mask(center, radius))

    @staticmethod
    def cat(parts: Sequence["Gaussians"]) -> "Gaussians":
        """Concatenate Gaussians with the same colour model, SH degree, features and dtype."""
        if not parts:
            raise InputError("Gaussians.cat needs at least one set of Gaussians")
        first = parts[0]
        for i, g in enumerate(parts[1:], start=1):
            mismatch = [
                what
                for what, a, b in (
                    ("SH degree", first.sh_degree, g.sh_degree),
                    ("colour channels", _width(first.colors), _width(g.colors)),
                    ("feature names", first.feature_names, g.feature_names),
                    ("dtype", first.dtype, g.dtype),
                )
                if a != b
            ]
            if mismatch:
                raise InputError(f"cannot concatenate Gaussians: part {i} differs from part 0 in {', '.join(mismatch)}")
        fields = {
            f.name: (torch.cat([getattr(g, f.name) for g in parts]) if getattr(first, f.name) is not None else None)
            for f in dataclasses.fields(first)
            if f.name not in ("feature_names", *MATRIX_FIELDS)
        }
        for name in MATRIX_FIELDS:  # a part without them: identity, or its covariances
            given = [getattr(g, name) for g in parts if getattr(g, name) is not None]
            if given:
                fields[name] = torch.cat([_matrices(g, name).to(given[0].dtype) for g in parts])
        return Gaussians(**fields, feature_names=first.feature_names)

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> "Gaussians":
        """A copy with floating-point tensors in ``dtype`` and/or on ``device``."""
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "Gaussians":
        return self._map(torch.Tensor.detach)

    def bounds(self, quantile: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """(low, high) [3] of the centres, m; ``quantile`` > 0 ignores that fraction of outliers per side."""
        if len(self) == 0:
            raise InputError("the bounds of an empty set of Gaussians are undefined")
        if not 0 <= quantile < 0.5:
            raise InputError(f"quantile must be in [0, 0.5), got {quantile}")
        means = self.means.detach().double()
        if quantile == 0:
            return means.min(0).values, means.max(0).values
        # k-th smallest per axis (1-based k); torch.quantile refuses more than 2^24 values.
        last = len(self) - 1
        low = torch.kthvalue(means, math.floor(quantile * last) + 1, dim=0).values
        high = torch.kthvalue(means, math.ceil((1 - quantile) * last) + 1, dim=0).values
        return low, high

    def _map(self, fn) -> "Gaussians":
        fields = {
            f.name: (fn(v) if isinstance(v := getattr(self, f.name), torch.Tensor) else v)
            for f in dataclasses.fields(self)
        }
        return Gaussians(**fields)

    def _point(self, value: TensorLike, what: str) -> torch.Tensor:
        point = torch.as_tensor(value, dtype=self.dtype, device=self.means.device)
        if tuple(point.shape) != (3,):
            raise InputError(f"{what} must be 3 numbers (m), got shape {tuple(point.shape)}")
        return point


MATRIX_FIELDS = ("deformations", "sh_rotations", "covariance_cache")  # the optional [N, 3, 3] fields


def _matrices(g: Gaussians, name: str) -> torch.Tensor:
    """The [N, 3, 3] field ``name`` of ``g``, or what None stands for: identity, or the covariances."""
    value = getattr(g, name)
    if value is not None:
        return value
    if name == "covariance_cache":
        return g.covariances
    return torch.eye(3, dtype=g.dtype, device=g.means.device).expand(len(g), 3, 3)


def _check_finite(name: str, value: torch.Tensor, where: str = "") -> None:
    with torch.no_grad():
        if bool(torch.isfinite(value).all()):
            return
        bad = (~torch.isfinite(value)).nonzero()
    if len(bad):
        prefix = f"{where}: " if where else ""
        first = tuple(bad[0].tolist())
        raise InputError(
            f"{prefix}{len(bad)} non-finite values in {name} (first at index {first}: {value[first].item()})"
        )


def _width(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.shape[1]


def _shape_matches(value: torch.Tensor, shape: tuple[int | None, ...]) -> bool:
    return value.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, value.shape))


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "[" + ", ".join("N" if s == -1 else "*" if s is None else str(s) for s in shape) + "]"
