"""Physics-driven decoding: depth evidence from the camera's own kernels, and the classical decoder.

    from bmi_sdk.decode import ClassicalDecoder, ClassicalConfig, inverse_depth_candidates
    decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(candidates=48))
    result = decoder.decode(raw, black_level_dn, white_level_dn, geometry, row0, col0)

Modules: ``bayer`` (raw planes, noise), ``candidates`` (1/d grid), ``evidence`` (the likelihood),
``kernels`` (per-zone kernels and models), ``aif`` (Wiener blend), ``classical`` (the decoder).
Method, knobs and measured accuracy: docs/decoder.md.
"""

from .candidates import Candidates, inverse_depth_candidates
from .classical import ClassicalConfig, ClassicalDecoder, DecodeResult

__all__ = ["Candidates", "inverse_depth_candidates", "ClassicalConfig", "ClassicalDecoder", "DecodeResult"]
