"""Named constants of the splat stage (one place; the fast kernels, the torch projection and the dense reference
all read them from here).

Compositing follows the INRIA / gsplat rasterisers: ``alpha = min(MAX_ALPHA, o * exp(-0.5 d^T Sigma^-1 d))``,
a (Gaussian, pixel) pair with ``alpha < ALPHA_THRESHOLD`` is skipped, and a pixel stops at the first Gaussian
that would bring its transmittance below ``TRANSMITTANCE_THRESHOLD`` (that Gaussian is not composited, so the
final transmittance is always ``>= TRANSMITTANCE_THRESHOLD``).
"""

from __future__ import annotations

import math

#: Tile edge in pixels (16 x 16 tiles as in the INRIA rasteriser and gsplat).
TILE_SIZE: int = 16
#: Largest opacity of one (Gaussian, pixel) pair.
MAX_ALPHA: float = 0.99
#: Pairs with alpha below this are skipped (INRIA: 1/255).
ALPHA_THRESHOLD: float = 1.0 / 255.0
#: A pixel stops when its transmittance would drop below this.
TRANSMITTANCE_THRESHOLD: float = 1e-4
#: ``ln(1 / ALPHA_THRESHOLD)``: a Gaussian of opacity ``o`` reaches ``alpha >= ALPHA_THRESHOLD`` only where
#: ``0.5 d^T Sigma^-1 d <= ln(o / ALPHA_THRESHOLD)``.
LOG_INV_ALPHA_THRESHOLD: float = math.log(255.0)

#: Low-pass filters (screen-space dilation) added to the 2D covariance, pixels^2.
#: ``"inria"``: +0.3 px^2, no compensation (INRIA 3DGS, diff-gaussian-rasterization);
#: ``"mip"``: +0.1 px^2 with opacity compensation ``sqrt(det(Sigma) / det(Sigma + 0.1 I))`` (Mip-Splatting's 2D
#: filter, gsplat ``antialiased``); ``"none"``: no filter (LichtFeld reports +0.46 dB on fisheye for this).
FILTER_DILATION: dict[str, float] = {"none": 0.0, "inria": 0.3, "mip": 0.1}
#: Filters with opacity compensation.
FILTER_COMPENSATED: frozenset[str] = frozenset({"mip"})
#: Default filter of :func:`umi_aug.splat.render`.
DEFAULT_FILTER: str = "inria"

#: Default near sphere (metres): Gaussians whose centre is closer to the camera centre than this are culled.
DEFAULT_NEAR: float = 0.01
#: Gaussians whose centre is farther than this along the ray are culled (metres).
DEFAULT_FAR: float = 1e10
#: A 2D covariance with ``det <= MIN_DET_2D * (trace/2)^2`` (near-singular, e.g. a needle viewed end-on with no
#: filter) is culled; keeps the conic finite in float32.
MIN_DET_2D_REL: float = 1e-10
#: Absolute floor on ``det(Sigma_2D)`` in pixels^4 (culls numerically degenerate footprints).
MIN_DET_2D_ABS: float = 1e-20
#: Safety margin added to the opacity-aware bounding box (pixels) so that rounding never drops a pixel whose
#: alpha passes the threshold.
BBOX_MARGIN_PX: float = 1e-3
#: Relative safety margin on the bounding-box half-extent.
BBOX_MARGIN_REL: float = 1e-5

#: Spherical harmonics: largest supported degree and coefficient counts per degree.
MAX_SH_DEGREE: int = 3
SH_COEFFS: tuple[int, ...] = (1, 4, 9, 16)
#: Real SH constants (INRIA ``utils/sh_utils.py``, gsplat ``_spherical_harmonics``).
SH_C0: float = 0.28209479177387814
SH_C1: float = 0.4886025119029199
SH_C2: tuple[float, ...] = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3: tuple[float, ...] = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
