"""Forward simulator: PSF map and occlusion-aware layered rendering of RGB + range scenes.

Public API: :func:`render_coded` (zone overlap-add, scales to the full frame),
:func:`render_reference` (brute force, small windows), :class:`PsfMap`,
:func:`layer_index`.
"""

from .compose import DEFAULT_RAMP_PX, DEFAULT_ZONE_PX, render_coded, render_reference
from .layers import layer_index
from .psf_map import PsfMap, rotate_kernel

__all__ = ["render_coded", "render_reference", "PsfMap", "layer_index", "rotate_kernel", "DEFAULT_ZONE_PX", "DEFAULT_RAMP_PX"]
