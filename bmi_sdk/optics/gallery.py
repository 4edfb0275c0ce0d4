"""PSF gallery figure: kernels across depth (columns) and field (rows), one PNG."""

from __future__ import annotations

import math

import numpy as np

from ..io_atomic import atomic_path
from .prescription import Lens
from .psf import psf_from_pupil
from .pupil import fit_pupils

GALLERY_DEPTHS_M = (0.7, 1.0, 2.0, 4.0, 10.0, math.inf)
GALLERY_FIELDS_DEG = (0.0, 30.0, 45.0, 60.0)
CHANNEL_NM = (656.3, 587.6, 486.1)


def psf_gallery(lens: Lens, path, depths_m=GALLERY_DEPTHS_M, fields_deg=GALLERY_FIELDS_DEG, kernel_px: int = 41) -> None:
    """Write an RGB gallery: each tile is the three channel PSFs as R, G, B (each scaled to its peak^0.5)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    theta, depth, lam = np.meshgrid(fields_deg, depths_m, CHANNEL_NM, indexing="ij")
    fits = fit_pupils(lens, theta.ravel(), depth.ravel(), lam.ravel() * 1e-3)
    kernels = np.array([psf_from_pupil(f, kernel_px).kernel for f in fits]).reshape(theta.shape + (kernel_px, kernel_px))
    fig, axes = plt.subplots(len(fields_deg), len(depths_m), figsize=(1.6 * len(depths_m), 1.7 * len(fields_deg)))
    for i, t in enumerate(fields_deg):
        for j, d in enumerate(depths_m):
            rgb = kernels[i, j].transpose(1, 2, 0)
            rgb = np.sqrt(rgb / rgb.max(axis=(0, 1), keepdims=True))
            ax = axes[i, j]
            ax.imshow(rgb, interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if i == 0:
                ax.set_title("∞" if math.isinf(d) else f"{d:g} m", fontsize=9)
            if j == 0:
                ax.set_ylabel(f"{t:g}°", fontsize=9)
    fig.suptitle(f"{lens.name}: PSF (R,G,B; √ scale), {kernel_px} px = {kernel_px * 2} µm; radial axis →", fontsize=9)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
