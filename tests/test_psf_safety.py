"""PSFs that are never silently wrong (issue 14): exported kernels stay inside the range where the engine is
valid, requests too large for memory are refused with the number, and damaged cache shards are recomputed."""

import math
import re

import numpy as np
import pytest

from bmi_sdk.cli import main
from bmi_sdk.memory_budget import MemoryBudgetError, check_fits
from bmi_sdk.optics import PsfTensor, TensorSpec, fit_pupil, get_lens, psf_from_pupil
from bmi_sdk.optics.tensor import PsfCacheWarning

MONO = get_lens("bmi_monocentric")


def _export(tmp_path, capsys, *args):
    out = tmp_path / f"k{len(list(tmp_path.glob('k*.npy')))}.npy"  # a new file each call: export keeps old ones
    try:
        code = main(["psf", "export", "--out", str(out), *args])
    except SystemExit as exc:  # an option outside its range is argparse's usage error
        code = exc.code
    return code, capsys.readouterr(), out


@pytest.mark.parametrize("args, match", [
    (["--wavelength-nm", "587.6", "--depth-m", "2", "--field-deg", "85"], r"--field-deg: 85 is outside \[0, 80\]"),
    (["--wavelength-nm", "587.6", "--depth-m", "0.001", "--field-deg", "0"], "front surface"),
    (["--wavelength-nm", "587.6", "--depth-m", "0.1", "--field-deg", "0"], "raise --kernel-px"),
    (["--wavelength-nm", "nan", "--depth-m", "2", "--field-deg", "30"], "--wavelength-nm: nan is not a finite number"),
    (["--wavelength-nm", "1e12", "--depth-m", "2", "--field-deg", "30"], r"--wavelength-nm: 1e12 is outside \[365, 1014\]"),
    (["--wavelength-nm", "587.6", "--depth-m", "2", "--field-deg", "30", "--pitch-um", "1e6"],
     r"--pitch-um: 1e6 is outside \[0.5, 5\] µm"),
    (["--wavelength-nm", "587.6", "--depth-m", "2", "--field-deg", "30", "--kernel-px", "-5"],
     r"--kernel-px: -5 is outside \[1, inf\) px, odd"),
    (["--wavelength-nm", "587.6", "--depth-m", "2", "--field-deg", "30", "--oversample", "1001"],
     r"needs about \d+\.\d GiB, more than the 1\.0 GiB limit"),
    (["--wavelength-nm", "587.6", "--depth-m", "2", "--field-deg", "30", "--kernel-px", "4001"],
     r"needs about \d+\.\d GiB"),
    (["--wavelength-nm", "587.6", "--depth-m", "inf", "--field-deg", "0", "--pitch-um", "5"],
     r"adds up to 20\d\.\d% of the PSF's power .* raise --oversample"),
    (["--wavelength-nm", "587.6", "--depth-m", "1.3", "--field-deg", "37", "--kernel-px", "1"], "raise --oversample"),
])
def test_export_refuses_what_it_cannot_get_right(tmp_path, capsys, monkeypatch, args, match):
    monkeypatch.setenv("BMI_MAX_MEMORY_MB", "1024")
    code, out, path = _export(tmp_path, capsys, *args)
    assert code in (1, 2) and re.search(match, out.err), out.err  # 2: an option outside its range
    assert "Traceback" not in out.err and not path.exists()


def test_the_aliasing_remedy_works_a_sharp_psf_on_5_um_pixels_at_9_samples_per_side(tmp_path, capsys):
    """The refusal above names --oversample: at 9 samples per 5 µm pixel (0.56 µm, about the intensity's Nyquist
    step) the same PSF holds its power (0.9998) and is written."""
    code, out, path = _export(tmp_path, capsys, "--wavelength-nm", "587.6", "--depth-m", "inf", "--field-deg", "0",
                              "--pitch-um", "5", "--oversample", "9")
    assert code == 0 and path.exists(), out.err
    assert abs(float(re.search(r"energy captured ([\d.]+)", out.out).group(1)) - 1.0) < 0.005


def test_far_depths_take_the_infinity_path(tmp_path, capsys):
    code, out, path = _export(tmp_path, capsys, "--wavelength-nm", "587.6", "--depth-m", "1e12", "--field-deg", "0")
    assert code == 0
    far = np.load(path)
    assert _export(tmp_path, capsys, "--wavelength-nm", "587.6", "--depth-m", "inf", "--field-deg", "0")[0] == 0
    np.testing.assert_array_equal(far, np.load(path))
    fit = fit_pupil(MONO, 0.0, 1e9, 0.5876)
    assert math.isinf(fit.depth_m) and fit.fit_rms_waves < 1e-3  # was 0.12 waves traced at 1e9 m


def test_the_engine_never_returns_a_non_finite_kernel():
    fit = fit_pupil(MONO, 85.0, math.inf, 0.5876)  # beyond the field the lens images: NaN before
    with pytest.raises(ValueError, match="not finite"):
        psf_from_pupil(fit, 41)


def test_a_nan_wavelength_is_named_as_the_cause():
    with pytest.raises(ValueError, match="wavelength must be a finite"):
        fit_pupil(MONO, 30.0, 2.0, float("nan"))


def test_memory_check_names_the_numbers(monkeypatch):
    monkeypatch.setenv("BMI_MAX_MEMORY_MB", "100")
    check_fits(50 * 2**20, "small")
    with pytest.raises(MemoryBudgetError, match=r"big needs about 0\.2 GiB, more than the 0\.1 GiB limit"):
        check_fits(200 * 2**20, "big")


def test_inference_tile_too_large_is_refused_before_allocating(monkeypatch):
    from bmi_sdk.runtime import Model
    from bmi_sdk.runtime.model import DEFAULT_MODEL

    monkeypatch.delenv("BMI_MAX_MEMORY_MB", raising=False)
    with pytest.raises(MemoryBudgetError, match=r"--tile-px 100000 needs about \d+\.\d GiB"):
        Model(DEFAULT_MODEL, tile_px=100000)


SPEC = TensorSpec(field_deg=(0.0, 30.0), depth_m=(0.7, 2.0), kernel_px=15)


def _fresh(tmp_path):
    tensor = PsfTensor(MONO, SPEC, cache_dir=tmp_path)
    tensor.ensure([1], [0, 1])
    return tensor, tensor._shard_path(1)


def _damage_nan(path):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["psf"] = np.full_like(arrays["psf"], np.nan)
    arrays.pop("sha256")  # as an older SDK wrote shards: only the value checks can catch it
    np.savez(path, **arrays)


def _damage_edit(path):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["psf"][0, 0, 7, 7] += 0.01  # finite, plausible, but not what was written
    np.savez(path, **arrays)


def _damage_truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("damage, reason", [(_damage_nan, "non-finite"), (_damage_edit, "SHA-256"),
                                            (_damage_truncate, "unreadable")])
def test_a_damaged_shard_is_recomputed_never_used(tmp_path, damage, reason):
    good, path = _fresh(tmp_path)
    damage(path)
    again = PsfTensor(MONO, SPEC, cache_dir=tmp_path)
    with pytest.warns(PsfCacheWarning, match=reason):
        computed = again.ensure([1], [0, 1])
    assert computed == 2  # recomputed, not taken from the shard
    np.testing.assert_array_equal(again.data[:, 1], good.data[:, 1])
    third = PsfTensor(MONO, SPEC, cache_dir=tmp_path)  # the shard was rewritten whole
    assert third.ensure([1], [0, 1]) == 0
    np.testing.assert_array_equal(third.data[:, 1], good.data[:, 1])


def test_a_sound_shard_from_before_hashes_is_kept_and_given_one(tmp_path):
    good, path = _fresh(tmp_path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "sha256"}
    np.savez(path, **arrays)
    again = PsfTensor(MONO, SPEC, cache_dir=tmp_path)
    assert again.ensure([1], [0, 1]) == 0
    np.testing.assert_array_equal(again.data[:, 1], good.data[:, 1])
    with np.load(path) as z:
        assert "sha256" in z.files


def test_tensor_metadata_of_the_wrong_json_shape_is_a_clear_error(tmp_path):
    (tmp_path / "t.npz").write_bytes(b"")
    (tmp_path / "t.json").write_text("[]")
    with pytest.raises(ValueError, match="holds a JSON list, expected an object"):
        PsfTensor.load(tmp_path / "t.npz")
