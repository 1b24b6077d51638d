"""Constants of the splat rasteriser, named once and shared by the kernels (as -D defines),
the torch op and the pure-torch reference (values as in 3DGS and gsplat)."""

TILE_SIZE = (
    16  # pixels per tile side; a tile is a work-item (rasterize_tile_rows.cl) or a work-group (rasterize_workgroup.cl)
)
EPS2D = 0.3  # pixel^2 added to the diagonal of every 2D covariance (low-pass dilation)
ALPHA_MIN = 1.0 / 255.0  # a Gaussian whose alpha at a pixel is below this is skipped there
ALPHA_MAX = 0.99  # alpha = min(ALPHA_MAX, opacity * exp(-sigma))
T_MIN = 1e-4  # compositing stops before a Gaussian that would take T below this
LIM_FOV = 1.3  # J is evaluated at x/z, y/z clamped to 1.3 x the field of view
ROW_CULL_MARGIN = 1e-3  # a tile row is skipped when its smallest sigma exceeds log(o/ALPHA_MIN) by this
MAX_RADIUS = 1 << 24  # pixels; radii are capped here (exact in float32, far past any image)
MIN_RADIUS_EIGEN = 0.1  # lambda_max = mid + sqrt(max(MIN_RADIUS_EIGEN, mid^2 - det))
MIN_QUAT_NORM = 1e-8  # a quaternion shorter than this (Euclidean norm) has no defined rotation
SPLAT_LANES = 8  # Gaussians per work-item (vector lanes) of the forward projection and covariance kernels

SPLAT_DEFINES = {
    "TILE_SIZE": TILE_SIZE,
    "EPS2D": repr(EPS2D),
    "ALPHA_MIN": repr(ALPHA_MIN),
    "ALPHA_MAX": repr(ALPHA_MAX),
    "T_MIN": repr(T_MIN),
    "LIM_FOV": repr(LIM_FOV),
    "MIN_RADIUS_EIGEN": repr(MIN_RADIUS_EIGEN),
    "MAX_RADIUS": MAX_RADIUS,
    "ROW_CULL_MARGIN": repr(ROW_CULL_MARGIN),
    "CLFLOW_SIMD_LANES": SPLAT_LANES,  # common/lanes.h
}
