"""Portable FloatMap (PFM) read/write: the disparity format of FlyingThings3D and Middlebury.

Format: ASCII header ``PF`` (3 channels) or ``Pf`` (1 channel), then
``width height``, then a scale whose sign gives the byte order (negative =
little endian) and whose magnitude is unused by these datasets, each token
separated by whitespace and the header closed by a single whitespace byte;
then float32 samples, rows stored *bottom to top*. Arrays here are top-to-bottom
(row 0 is the top of the image), so both functions flip.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bmi_sdk.io_atomic import write_bytes


class PfmError(ValueError):
    """A file that is not a well-formed PFM."""


def _header_tokens(data: bytes, path) -> tuple[list[bytes], int]:
    """The four header tokens (magic, width, height, scale) and the offset where samples start."""
    tokens, pos = [], 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos:pos + 1].isspace():
            pos += 1
        if pos < len(data) and data[pos:pos + 1] == b"#":  # comment line (tolerated)
            pos = data.find(b"\n", pos) + 1 or len(data)
            continue
        start = pos
        while pos < len(data) and not data[pos:pos + 1].isspace():
            pos += 1
        if start == pos:
            raise PfmError(f"{path}: PFM header ends early (got {len(tokens)} of 4 fields)")
        tokens.append(data[start:pos])
        if len(tokens) == 1 and tokens[0] not in (b"PF", b"Pf"):
            raise PfmError(f"{path}: not a PFM file (magic {tokens[0][:8]!r}, expected b'PF' or b'Pf')")
    if pos >= len(data):
        raise PfmError(f"{path}: PFM header is not followed by data")
    return tokens, pos + 1  # exactly one whitespace byte closes the header


def read_pfm(path: str | os.PathLike) -> np.ndarray:
    """Read a PFM as float32, H×W (``Pf``) or H×W×3 (``PF``), row 0 at the top."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PFM file not found: {path}")
    data = path.read_bytes()
    (magic, w_tok, h_tok, s_tok), offset = _header_tokens(data, path)
    try:
        width, height, scale = int(w_tok), int(h_tok), float(s_tok)
    except ValueError:
        raise PfmError(f"{path}: bad PFM size/scale fields {w_tok!r} {h_tok!r} {s_tok!r}") from None
    if width <= 0 or height <= 0:
        raise PfmError(f"{path}: PFM size must be positive, got {width}×{height}")
    if scale == 0 or not np.isfinite(scale):
        raise PfmError(f"{path}: PFM scale must be a finite non-zero number (its sign is the byte order), got {scale}")
    channels = 3 if magic == b"PF" else 1
    count = width * height * channels
    if len(data) - offset < 4 * count:
        raise PfmError(f"{path}: PFM data truncated: {len(data) - offset} bytes for {width}×{height}×{channels} "
                       f"float32 ({4 * count} bytes)")
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    samples = np.frombuffer(data, dtype=dtype, count=count, offset=offset).astype(np.float32)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.ascontiguousarray(samples.reshape(shape)[::-1])


def write_pfm(path: str | os.PathLike, array: np.ndarray, little_endian: bool = True) -> None:
    """Write an H×W or H×W×3 array (row 0 at the top) as a PFM, atomically."""
    a = np.asarray(array)
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)) or a.size == 0:
        raise ValueError(f"PFM holds an H×W or H×W×3 array, got shape {a.shape}")
    magic = b"PF" if a.ndim == 3 else b"Pf"
    dtype = np.dtype("<f4" if little_endian else ">f4")
    header = b"%s\n%d %d\n%s\n" % (magic, a.shape[1], a.shape[0], b"-1.0" if little_endian else b"1.0")
    write_bytes(path, header + np.ascontiguousarray(a[::-1], dtype=dtype).tobytes())
