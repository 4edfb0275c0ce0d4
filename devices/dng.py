"""Raw frames as DNG (uncompressed, written with tifffile, read back with rawpy) plus a JSON sidecar.

The DNG carries what DNG has tags for: CFA pattern (RGGB), black and white
level, camera make/model/serial, exposure, and the camera's colour
(``ColorMatrix1`` under ``CalibrationIlluminant1`` D65, ``AsShotNeutral``), so
that raw viewers and LibRaw render the frame's colours as the scene had them, and, when the frame has one,
its noise (``NoiseProfile``, tag 51041: one (S, O) pair for all colour planes, Var[x] = S·x + O for
x = (DN − black) / (white − black)). The sidecar ``<name>.json`` carries
the rest (curved-sensor geometry, lens identity, ROI, frame metadata,
calibration id) and the SHA-256 of the pixels, so a sidecar that belongs to
another file is detected. Both are written atomically (temp name + rename),
DNG first: an interrupted save leaves at worst a DNG without sidecar, which
``load_raw`` flags.

``load_raw`` refuses (``RawFileError``) a DNG that is not from a BMI camera
(UniqueCameraModel tag), has no sidecar, or whose sidecar does not match, unless
``require_bmi=False``: then it returns the raw data with ``is_bmi=False``.
A NoiseProfile tag that is malformed (not 2 values, or 2 per colour plane that differ; negative,
non-finite or all zero) or disagrees with the sidecar makes a BMI file a ``RawFileError``: the file was
damaged or edited, and a decoder told the wrong noise would be silently wrong. In another camera's file
(``require_bmi=False``) it is a ``NoiseProfileWarning`` and ``noise_profile`` None: that camera's tag
should not stop its pixels from loading.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry
from bmi_sdk.io_atomic import atomic_path, write_json
from bmi_sdk.json_files import read_json_object
from bmi_sdk.protocol.wire import MODEL_NAME
from bmi_sdk.sensor import NoiseProfile

from .errors import NoiseProfileWarning, RawFileError
from .frame import SIDECAR_SCHEMA, FrameStatus, RawFrame, Roi

MAKE = "BMI"
_CFA_CODES = {"R": 0, "G": 1, "B": 2}
_TAG_UNIQUE_MODEL = 50708
_TAG_NOISE_PROFILE = 51041
_COLOR_PLANES = 3  # CFAPlaneColor (R, G, B): the DNG allows one NoiseProfile pair per plane

SRGB_TO_XYZ_D65 = np.array([[0.4124564, 0.3575761, 0.1804375],
                            [0.2126729, 0.7151522, 0.0721750],
                            [0.0193339, 0.1191920, 0.9503041]])
"""IEC 61966-2-1: linear sRGB → CIE XYZ, D65 white."""
XYZ_TO_CAMERA = np.linalg.inv(SRGB_TO_XYZ_D65)
"""``ColorMatrix1`` (XYZ under D65 → camera RGB). The simulated sensor records the scene's linear sRGB
channels with equal gains (``firmware_sim`` renders linear sRGB per CFA colour; ``SensorModel`` applies one
gain to all), so its native primaries are sRGB's; it maps D65 white to (1, 1, 1), as DNG asks."""
AS_SHOT_NEUTRAL = (1.0, 1.0, 1.0)
"""``AsShotNeutral``: the camera RGB of a neutral (D65 white) surface: equal, the sensor has no channel gains."""
_RATIONAL_DENOMINATOR = 1_000_000


def _rationals(values, signed: bool) -> tuple[int, ...]:
    """DNG (S)RATIONAL pairs (numerator, denominator) for ``values``."""
    pairs = []
    for v in np.asarray(values, dtype=np.float64).ravel():
        num = int(round(v * _RATIONAL_DENOMINATOR))
        if not signed and num < 0:
            raise ValueError(f"{v} cannot be an unsigned DNG rational")
        pairs += [num, _RATIONAL_DENOMINATOR]
    return tuple(pairs)


def sidecar_path(path) -> Path:
    return Path(path).with_suffix(".json")


def pixel_sha256(data: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(data, dtype="<u2").tobytes()).hexdigest()


def _is_sidecar_of(side: Path, dng: Path) -> bool:
    """Whether ``side`` is a BMI raw sidecar written for a DNG named like ``dng`` (so replacing it loses nothing
    that the DNG beside it does not carry)."""
    try:
        doc = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("schema") == SIDECAR_SCHEMA and doc.get("dng") == dng.name


def save_dng(frame: RawFrame, path, overwrite: bool = False) -> None:
    """Write ``frame`` to ``path`` (a .dng) and its sidecar, atomically.

    An existing DNG or sidecar is refused (``FileExistsError``, nothing
    written) unless ``overwrite=True``, as the command line refuses one
    without ``--overwrite``: a capture is not lost to a repeated call. Even
    then the sidecar ``<name>.json`` never replaces a JSON file that is not
    the sidecar of ``<name>.dng`` (e.g. a calibration file of the same name).
    """
    import tifffile

    path = Path(path)
    if path.suffix.lower() != ".dng":
        raise ValueError(f"DNG files end in .dng, got {path}")
    side = sidecar_path(path)
    if side.exists() and not _is_sidecar_of(side, path):
        raise FileExistsError(f"{side} exists and is not the sidecar of {path.name}; refusing to replace it "
                              "(choose another name for the DNG)")
    if not overwrite:
        for existing in (path, side):
            if existing.exists():
                raise FileExistsError(f"{existing} exists; refusing to replace it (overwrite=True replaces it)")
    data = np.ascontiguousarray(frame.data, dtype=np.uint16)
    if data.ndim != 2:
        raise ValueError(f"a raw frame is H×W, got shape {data.shape}")
    if len(frame.cfa) != 4 or set(frame.cfa) - set(_CFA_CODES):
        raise ValueError(f"CFA must be a 2×2 pattern like 'RGGB', got {frame.cfa!r}")
    model = f"{MODEL_NAME} {frame.device.get('serial', '')}".strip() if frame.is_bmi else "unknown"
    exposure = max(1, int(frame.exposure_us))
    extratags: list[tuple[int, str, int, object, bool]] = [  # tifffile's (code, dtype, count, value, writeonce)
        (271, "s", 0, MAKE, True),                                  # Make
        (272, "s", 0, MODEL_NAME, True),                            # Model
        (50706, "B", 4, (1, 4, 0, 0), True),                        # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),                        # DNGBackwardVersion
        (_TAG_UNIQUE_MODEL, "s", 0, model, True),                   # UniqueCameraModel
        (50735, "s", 0, str(frame.device.get("serial", "")), True),  # CameraSerialNumber
        (33421, "H", 2, (2, 2), True),                              # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in frame.cfa), True),  # CFAPattern
        (50710, "B", 3, (0, 1, 2), True),                           # CFAPlaneColor
        (50714, "H", 1, (int(frame.black_level_dn),), True),        # BlackLevel
        (50717, "H", 1, (int(frame.white_level_dn),), True),        # WhiteLevel
        (50721, "2i", 9, _rationals(XYZ_TO_CAMERA, signed=True), True),     # ColorMatrix1: XYZ (D65) → camera
        (50778, "H", 1, (21,), True),                               # CalibrationIlluminant1 = D65
        (50728, "2I", 3, _rationals(AS_SHOT_NEUTRAL, signed=False), True),  # AsShotNeutral
        (33434, "2I", 1, (exposure, 1_000_000), True),              # ExposureTime (s)
    ]
    if frame.noise_profile is not None:
        profile = frame.noise_profile
        extratags.append((_TAG_NOISE_PROFILE, "d", 2, (profile.scale, profile.offset), True))  # NoiseProfile
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, data, photometric=32803, subfiletype=0, compression=None,
                         metadata=None, extratags=extratags)
    write_json(side, frame.metadata | {"dng": path.name, "pixel_sha256": pixel_sha256(data)})


def _noise_profile_from_tag(path: Path, value) -> NoiseProfile | None:
    """The NoiseProfile tag's value (None: no tag) as one pair; ``RawFileError`` naming the file and the tag
    if it is not 2 doubles, or 2 per colour plane that all agree, forming a valid ``NoiseProfile``."""
    if value is None:
        return None
    try:
        pairs = np.asarray(value, dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError):
        raise RawFileError(f"{path}: NoiseProfile tag ({_TAG_NOISE_PROFILE}) holds {value!r}, "
                           "expected pairs of numbers (S, O)") from None
    if len(pairs) not in (1, _COLOR_PLANES) or not np.array_equal(pairs, np.broadcast_to(pairs[0], pairs.shape),
                                                                  equal_nan=True):
        raise RawFileError(f"{path}: NoiseProfile tag ({_TAG_NOISE_PROFILE}) holds {pairs.size} values "
                           f"{pairs.ravel().tolist()}; expected one pair (S, O), or {_COLOR_PLANES} equal ones")
    try:
        return NoiseProfile(float(pairs[0, 0]), float(pairs[0, 1]))
    except ValueError as exc:
        raise RawFileError(f"{path}: NoiseProfile tag ({_TAG_NOISE_PROFILE}) is invalid ({exc})") from None


def _cfa_string(raw) -> str:
    desc = raw.color_desc.decode()
    pattern = np.asarray(raw.raw_pattern)
    if pattern.shape != (2, 2):
        raise RawFileError(f"not a 2×2 Bayer raw file (CFA pattern shape {pattern.shape})")
    return "".join(desc[i] for i in pattern.reshape(-1))  # LibRaw names the second green 'G' too


_SIDECAR_FIELDS = ("frame_id", "status", "cfa", "black_level_dn", "white_level_dn", "exposure_us", "analog_gain",
                   "temperature_c", "device_timestamp_ns", "readout_timestamp_ns", "host_timestamp_ns", "roi",
                   "geometry", "lens", "device", "skipped_frames", "test_pattern", "source", "calibration_id")


def _read_sidecar(side: Path) -> dict:
    """The sidecar as a JSON object; ``RawFileError`` naming the problem for bad JSON or another shape."""
    return read_json_object(side, RawFileError, f"sidecar {side}")


def _check_sidecar_fields(path: Path, meta: dict, shape: tuple) -> None:
    """Refuse a sidecar whose fields are missing, of the wrong shape, or whose ROI does not lie on the sensor
    and match the pixels: a wrong ROI would give every pixel the wrong field angle."""
    missing = [k for k in _SIDECAR_FIELDS if k not in meta]
    if missing:
        raise RawFileError(f"{path}: sidecar lacks {', '.join(missing)}")
    for key in ("roi", "geometry", "lens", "device"):
        if not isinstance(meta[key], dict):
            raise RawFileError(f"{path}: sidecar field {key!r} is a JSON {type(meta[key]).__name__}, "
                               "expected an object")
    try:
        roi = Roi(**meta["roi"])
        geometry = SensorGeometry.from_dict(meta["geometry"])
    except (TypeError, KeyError, ValueError) as exc:
        raise RawFileError(f"{path}: sidecar roi/geometry malformed ({exc})") from None
    values = (roi.x_px, roi.y_px, roi.width_px, roi.height_px)
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        raise RawFileError(f"{path}: sidecar ROI values must be integers (px), got {roi}")
    if roi.x_px < 0 or roi.y_px < 0 or roi.x_px + roi.width_px > geometry.width_px \
            or roi.y_px + roi.height_px > geometry.height_px:
        raise RawFileError(f"{path}: sidecar ROI {roi} lies outside the "
                           f"{geometry.width_px}×{geometry.height_px} sensor")
    if (roi.height_px, roi.width_px) != tuple(shape):
        raise RawFileError(f"{path}: sidecar ROI {roi.width_px}×{roi.height_px} does not match the "
                           f"{shape[1]}×{shape[0]} pixels")
    if "shape" in meta and meta["shape"] != list(shape):
        raise RawFileError(f"{path}: sidecar shape {meta['shape']} (H, W) does not match the DNG's "
                           f"{list(shape)}: it is not this DNG's sidecar")


def load_raw(path, require_bmi: bool = True) -> RawFrame:
    """Read a raw file through rawpy (pixels, levels, CFA) and its sidecar (everything else).

    A file that is not a BMI raw frame raises ``RawFileError`` naming why, or with
    ``require_bmi=False`` comes back with ``is_bmi=False`` and nominal geometry. ``noise_profile`` comes from
    the DNG NoiseProfile tag (None without one); a malformed one is handled as the module doc says.
    """
    import rawpy
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no raw file at {path}")
    if path.stat().st_size == 0:  # LibRaw's own word for it is "Input/output error"
        raise RawFileError(f"{path} is empty (0 bytes): not a DNG or any raw file")
    try:
        with rawpy.imread(str(path)) as raw:
            data = raw.raw_image_visible.copy()
            cfa = _cfa_string(raw)
            black = [int(b) for b in raw.black_level_per_channel]
            white = int(raw.white_level)
    except rawpy.LibRawError as exc:
        raise RawFileError(f"{path}: rawpy cannot read it as a raw file ({exc})") from exc
    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages.first.tags
            tag = tags.get(_TAG_UNIQUE_MODEL)
            camera_model = str(tag.value) if tag is not None else ""
            tag = tags.get(_TAG_NOISE_PROFILE)
            noise_value = tag.value if tag is not None else None
    except tifffile.TiffFileError:
        camera_model, noise_value = "", None  # not a TIFF-based raw: certainly not ours
    problem = None
    side = sidecar_path(path)
    meta: dict = {}
    if not camera_model.startswith(MODEL_NAME):
        problem = f"it comes from another camera (UniqueCameraModel {camera_model or 'missing'!r})"
    elif not side.is_file():
        problem = f"its sidecar {side.name} is missing (geometry and lens identity unknown)"
    else:
        meta = _read_sidecar(side)
        if meta.get("schema") != SIDECAR_SCHEMA:
            problem = f"sidecar {side.name} has schema {meta.get('schema')!r}, expected {SIDECAR_SCHEMA!r}"
        elif meta.get("pixel_sha256") != pixel_sha256(data):
            problem = f"sidecar {side.name} does not belong to these pixels (SHA-256 mismatch)"
    if problem is not None:
        if require_bmi:
            raise RawFileError(f"{path} is not a BMI raw frame: {problem}")
        try:
            noise_profile = _noise_profile_from_tag(path, noise_value)
        except RawFileError as exc:
            warnings.warn(f"{exc}; loading it without a noise profile", NoiseProfileWarning, stacklevel=2)
            noise_profile = None
        h, w = data.shape
        return RawFrame(data=data, frame_id=-1, status=FrameStatus.COMPLETE, black_level_dn=black[0],
                        white_level_dn=white, exposure_us=0, analog_gain=float("nan"),
                        temperature_c=float("nan"), device_timestamp_ns=0, readout_timestamp_ns=0,
                        host_timestamp_ns=0, roi=Roi(0, 0, w, h), geometry=BMI_SENSOR, lens={},
                        device={"model": camera_model}, cfa=cfa, is_bmi=False,
                        source={"foreign_raw_reason": problem}, noise_profile=noise_profile)
    _check_sidecar_fields(path, meta, data.shape)
    if cfa != meta["cfa"] or black[0] != meta["black_level_dn"] or white != meta["white_level_dn"]:
        raise RawFileError(f"{path}: DNG tags (CFA {cfa}, black {black[0]}, white {white}) disagree with the "
                           f"sidecar ({meta['cfa']}, {meta['black_level_dn']}, {meta['white_level_dn']})")
    noise_profile = _noise_profile_from_tag(path, noise_value)
    tagged = None if noise_profile is None else noise_profile.to_dict()
    if "noise_profile" in meta and meta["noise_profile"] != tagged:  # sidecars of older SDKs lack the key
        raise RawFileError(f"{path}: NoiseProfile tag ({_TAG_NOISE_PROFILE}) {tagged} disagrees with the "
                           f"sidecar's {meta['noise_profile']}")
    return RawFrame(
        data=data, frame_id=meta["frame_id"], status=FrameStatus(meta["status"]), black_level_dn=black[0],
        white_level_dn=white, exposure_us=meta["exposure_us"], analog_gain=meta["analog_gain"],
        temperature_c=meta["temperature_c"], device_timestamp_ns=meta["device_timestamp_ns"],
        readout_timestamp_ns=meta["readout_timestamp_ns"], host_timestamp_ns=meta["host_timestamp_ns"],
        roi=Roi(**meta["roi"]), geometry=SensorGeometry.from_dict(meta["geometry"]), lens=meta["lens"],
        device=meta["device"], cfa=cfa, skipped_frames=meta["skipped_frames"], test_pattern=meta["test_pattern"],
        source=meta["source"], calibration_id=meta["calibration_id"], noise_profile=noise_profile)
