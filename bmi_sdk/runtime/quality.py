"""Frame-quality gate: is this raw frame worth decoding?

The network turns any frame into a plausible-looking depth map, including a
saturated, black, pure-noise or test-pattern frame. Before inference
``assess_frame`` measures, over the image circle:

* ``saturated_fraction``: pixels at the white level (clipped: their PSF code
  is lost);
* ``signal_fraction``: median signal above black as a fraction of the range
  (black frames, a capped lens);
* ``structure``: correlation of each pixel with its same-colour neighbour two
  pixels along (a blurred optical image is smooth, ~0.9 and above; pure noise,
  a flat field or a dark frame is near 0: there is nothing to decode depth from);
* the frame's ``test_pattern`` flag (pixels from the digital test generator,
  not the sensor).

The thresholds come from measured frames (docs/reliability.md). A frame that
fails one of them is decoded but warned about; a test-pattern frame is refused
unless ``allow_test_pattern``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

MAX_SATURATED_FRACTION = 0.01
MIN_SIGNAL_FRACTION = 0.01
MIN_STRUCTURE = 0.5


class FrameQualityWarning(UserWarning):
    """A frame ``assess_frame`` finds doubtful (saturated, black, no structure); it is still decoded."""


class TestPatternFrameError(ValueError):
    """The frame's pixels come from the camera's test-pattern generator."""

    __test__ = False  # not a pytest test class


@dataclass
class FrameQuality:
    saturated_fraction: float
    signal_fraction: float
    structure: float
    test_pattern: bool
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def _image_circle(frame) -> np.ndarray:
    roi = frame.roi
    mask = frame.geometry.valid_mask(roi.y_px, roi.x_px, roi.height_px, roi.width_px)
    return mask if mask.shape == frame.data.shape and mask.any() else np.ones(frame.data.shape, bool)


CORRELATION_ROWS = 512
"""Rows of a frame correlated at a time: the sums stay float64, the temporaries a few tens of MB."""


def _neighbour_correlation(data: np.ndarray, mask: np.ndarray, offset_dn: float = 0.0) -> float:
    """Correlation of pixel (r, c) with (r, c + 2) (same CFA colour, one cell apart) over the pairs inside ``mask``.

    The correlation does not change under an affine map of the values, so it is taken on the raw numbers less
    ``offset_dn`` (a typical level: the sums' cancellation then costs no digits), accumulated band by band in
    float64: a full frame's float copies would take 0.4 GB at once."""
    n = 0
    sums = np.zeros(5)  # Σa, Σb, Σa², Σb², Σab
    for top in range(0, data.shape[0], CORRELATION_ROWS):
        band = np.asarray(data[top:top + CORRELATION_ROWS], np.float64) - offset_dn
        inside = mask[top:top + CORRELATION_ROWS]
        both = inside[:, :-2] & inside[:, 2:]
        a, b = band[:, :-2][both], band[:, 2:][both]
        n += a.size
        sums += (a.sum(), b.sum(), np.dot(a, a), np.dot(b, b), np.dot(a, b))
    if n < 2:
        return 0.0
    sa, sb, saa, sbb, sab = sums
    var_a, var_b, cov = saa - sa * sa / n, sbb - sb * sb / n, sab - sa * sb / n
    denom = np.sqrt(max(var_a, 0.0) * max(var_b, 0.0))
    return float(cov / denom) if denom > 0 else 0.0


def metadata_warnings(frame) -> list[str]:
    """What the sidecar of ``frame`` says that cannot be true of a capture: an exposure or gain that is not a
    positive number, or a lens SHA-256 that is not the named lens's prescription (the kernels that decode the
    frame are that prescription's, so its depth would be wrong without a word)."""
    found: list[str] = []
    if not getattr(frame, "is_bmi", True):  # another camera's raw file has no sidecar: its placeholders say nothing
        return found
    for field_name in ("exposure_us", "analog_gain"):
        value = getattr(frame, field_name, None)
        if value is not None and not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
            found.append(f"the sidecar's {field_name} is {value!r}, not a positive number: its metadata is damaged")
    lens = getattr(frame, "lens", None) or {}
    name, sha = lens.get("name"), lens.get("sha256")
    if name and sha:
        from ..optics import get_lens

        try:
            expected = get_lens(name).sha256()
        except (KeyError, ValueError):  # an unknown lens is refused, naming it, where the camera is built
            expected = sha
        if sha != expected:
            found.append(f"the sidecar's lens {name!r} has SHA-256 {str(sha)[:12]}…, not the {name} prescription's "
                         f"({expected[:12]}…): the frame is decoded with that prescription's kernels, which may not "
                         "be its lens's")
    return found


def assess_frame(frame) -> FrameQuality:
    """Measure ``frame`` (a ``devices.RawFrame``) and list what is wrong with it, in words a user can act on: its
    pixels (saturated, black, no structure, a test pattern) and its sidecar (``metadata_warnings``)."""
    data = np.asarray(frame.data)
    mask = _image_circle(frame)
    span = max(1.0, float(frame.white_level_dn - frame.black_level_dn))
    inside = data[mask]
    saturated = float(np.count_nonzero(inside >= frame.white_level_dn) / inside.size)
    median_dn = float(np.median(inside))
    del inside
    level = (median_dn - frame.black_level_dn) / span
    structure = _neighbour_correlation(data, mask, median_dn)
    quality = FrameQuality(saturated, level, structure, bool(getattr(frame, "test_pattern", False)))
    if quality.test_pattern:
        quality.warnings.append("the frame is a test pattern (TEST_PATTERN register set), not a sensor image")
    if saturated > MAX_SATURATED_FRACTION:
        quality.warnings.append(f"{saturated:.1%} of the pixels are saturated (limit {MAX_SATURATED_FRACTION:.0%}): "
                                "depth there is unknown; lower the exposure or gain")
    if level < MIN_SIGNAL_FRACTION:
        quality.warnings.append(f"median signal {level:.2%} of the range (limit {MIN_SIGNAL_FRACTION:.0%}): "
                                "the frame is black; raise the exposure or gain, or check the lens cap")
    elif structure < MIN_STRUCTURE and saturated <= MAX_SATURATED_FRACTION:
        quality.warnings.append(f"no optical structure (neighbour correlation {structure:.2f}, limit "
                                f"{MIN_STRUCTURE}): the frame is noise or a flat field; depth will be meaningless")
    quality.warnings += metadata_warnings(frame)
    return quality


def quality_gate(frame, allow_test_pattern: bool = False) -> FrameQuality:
    """``assess_frame``, refusing a test-pattern frame unless ``allow_test_pattern`` (``TestPatternFrameError``)."""
    quality = assess_frame(frame)
    if quality.test_pattern and not allow_test_pattern:
        raise TestPatternFrameError("the frame is a test pattern, not a sensor image: its depth map would be "
                                    "meaningless (turn the camera's test pattern off, or pass --allow-test-pattern)")
    return quality
