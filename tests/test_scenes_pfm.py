"""PFM read/write against hand-built files in the published format (bottom-to-top rows, signed scale)."""

import numpy as np
import pytest

from bmi_sdk.scenes import PfmError, read_pfm, write_pfm


def hand_written_pfm(path, array, big_endian):
    """Build a PFM byte by byte as the format description says, independently of write_pfm."""
    magic = b"PF" if array.ndim == 3 else b"Pf"
    scale = b"1.0" if big_endian else b"-1.0"
    rows = array[::-1].astype(">f4" if big_endian else "<f4")
    path.write_bytes(magic + b"\n" + f"{array.shape[1]} {array.shape[0]}\n".encode() + scale + b"\n" + rows.tobytes())


@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("channels", [1, 3])
def test_read_hand_written(tmp_path, big_endian, channels):
    rng = np.random.default_rng(0)
    shape = (5, 7) if channels == 1 else (5, 7, 3)
    a = rng.normal(size=shape).astype(np.float32)
    a.flat[3] = np.inf
    hand_written_pfm(tmp_path / "a.pfm", a, big_endian)
    b = read_pfm(tmp_path / "a.pfm")
    assert b.dtype == np.float32 and b.shape == shape
    np.testing.assert_array_equal(a, b)
    assert b[0].ravel()[3] == np.inf  # row 0 is the top row


@pytest.mark.parametrize("little_endian", [True, False])
def test_write_then_read_round_trip_and_layout(tmp_path, little_endian):
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_pfm(tmp_path / "b.pfm", a, little_endian=little_endian)
    raw = (tmp_path / "b.pfm").read_bytes()
    header = b"Pf\n4 3\n" + (b"-1.0\n" if little_endian else b"1.0\n")
    assert raw.startswith(header)
    first_stored_row = np.frombuffer(raw[len(header):len(header) + 16], dtype="<f4" if little_endian else ">f4")
    np.testing.assert_array_equal(first_stored_row, a[-1])  # bottom row first on disk
    np.testing.assert_array_equal(read_pfm(tmp_path / "b.pfm"), a)


def test_header_with_odd_whitespace(tmp_path):
    a = np.ones((2, 3), dtype=np.float32)
    (tmp_path / "c.pfm").write_bytes(b"Pf 3\t2\n-1\n" + a.astype("<f4").tobytes())
    np.testing.assert_array_equal(read_pfm(tmp_path / "c.pfm"), a)


@pytest.mark.parametrize("content, message", [
    (b"P6\n3 2\n255\n" + bytes(18), "not a PFM"),
    (b"Pf\n3 x\n-1\n" + bytes(24), "bad PFM size"),
    (b"Pf\n3 2\n0\n" + bytes(24), "scale"),
    (b"Pf\n3 2\n-1\n" + bytes(20), "truncated"),
    (b"Pf\n3 2\n", "not followed by data|ends early"),
    (b"Pf\n-3 2\n-1\n" + bytes(24), "positive"),
])
def test_bad_files_are_named(tmp_path, content, message):
    (tmp_path / "bad.pfm").write_bytes(content)
    with pytest.raises(PfmError, match=message):
        read_pfm(tmp_path / "bad.pfm")


def test_missing_file_and_bad_array(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.pfm"):
        read_pfm(tmp_path / "missing.pfm")
    with pytest.raises(ValueError, match="H×W"):
        write_pfm(tmp_path / "x.pfm", np.zeros((2, 3, 2), dtype=np.float32))
