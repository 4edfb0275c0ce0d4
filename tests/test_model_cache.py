"""The evidence models kept on disk beside the kernels: read back bit for bit, never stale, never damaged; and neither
cache fails a decode when its disk cannot be written."""

import numpy as np
import pytest

from bmi_sdk.decode import inverse_depth_candidates, model_cache
from bmi_sdk.decode.kernels import ZoneKernels
from bmi_sdk.geometry import BMI_SENSOR
from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens
from bmi_sdk.optics.tensor import PsfCacheWarning
from bmi_sdk.render import PsfMap

MONO = get_lens("bmi_monocentric")
SMALL = TensorSpec(field_deg=tuple(np.round(np.arange(0, 101) * 0.6, 6)), depth_m=(0.7, 1.0, 2.0, 10.0))
ZONE = (20.0, 30.0)
_FOLDED_MODEL = model_cache.folded_model


@pytest.fixture(scope="module")
def tensor():
    return PsfTensor(MONO, SMALL)


def _zones(tensor, cache_dir, keep=None, window_px=64, slopes=(2.0,)):
    """A decoder's zone memo over a disk-cached exact map, on every grid depth or those of ``keep``."""
    psf_map = PsfMap(tensor, BMI_SENSOR, mode="exact", cache_dir=cache_dir)
    candidates = inverse_depth_candidates(tensor.depth_m, len(tensor.depth_m))
    return ZoneKernels(psf_map, candidates if keep is None else candidates.subset(np.asarray(keep)), slopes, window_px)


@pytest.mark.parametrize("exact", [False, True])
def test_a_second_process_reads_the_models_bit_for_bit_and_traces_nothing(tensor, tmp_path, exact):
    first = _zones(tensor, tmp_path)
    made = first.models(ZONE, [0, 2, 3], exact)
    assert first.models_computed == 3
    second = _zones(tensor, tmp_path)  # a new process: nothing in memory
    read = second.models(ZONE, [0, 2, 3], exact)
    assert second.models_computed == 0 and second.psf_map.kernels_traced == 0
    np.testing.assert_array_equal(read, made)
    # and what is read equals what the model code makes of the cached kernels now
    kernels = second.kernels(ZONE, [2])
    direct = model_cache.model_function(exact)(kernels[1], 32, 2.0).astype(np.float32)
    np.testing.assert_array_equal(read[1, 0, 1], direct[0])


def test_models_of_another_window_or_slope_live_apart(tensor, tmp_path):
    base = _zones(tensor, tmp_path).models(ZONE, [1])
    for other in (_zones(tensor, tmp_path, window_px=48), _zones(tensor, tmp_path, slopes=(1.5, 2.5))):
        other.models(ZONE, [1])
        assert other.models_computed == 1  # its own shard, not the 64-px slope-2 one
    again = _zones(tensor, tmp_path)
    np.testing.assert_array_equal(again.models(ZONE, [1]), base)
    assert again.models_computed == 0


def test_a_change_in_how_models_are_made_never_reads_an_old_shard(tensor, tmp_path, monkeypatch):
    old = _zones(tensor, tmp_path).models(ZONE, [1])
    monkeypatch.setattr(model_cache, "_FINGERPRINTS", {})
    monkeypatch.setattr(model_cache, "folded_model", lambda k, n, a=2.0: 2.0 * _FOLDED_MODEL(k, n, a))
    changed = _zones(tensor, tmp_path)
    new = changed.models(ZONE, [1])
    assert changed.models_computed == 1
    np.testing.assert_allclose(new, 2.0 * old, rtol=1e-6)


def test_decoders_with_other_candidates_share_a_shard_without_dropping_each_others(tensor, tmp_path):
    every = _zones(tensor, tmp_path)
    some = _zones(tensor, tmp_path, keep=[1, 3])
    every.models(ZONE, [0, 2])  # depths the other decoder does not have
    some.models(ZONE, [0, 1])  # rewrites the shard with its own models and keeps the other decoder's
    again = _zones(tensor, tmp_path)
    again.models(ZONE, np.arange(4))
    assert again.models_computed == 0


def _damage_edit(path):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["models"][0, 0, 0, 3, 3] *= 1.01  # finite, plausible, not what was written
    np.savez(path, **arrays)


def _damage_nan(path):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["models"][0, 0, 0, 3, 3] = np.nan
    arrays["sha256"] = np.array(model_cache._digest(arrays["models"], arrays["depth_index"]))
    np.savez(path, **arrays)


def _damage_truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _damage_shape(path):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["models"] = np.ascontiguousarray(arrays["models"][..., :-1])
    arrays["sha256"] = np.array(model_cache._digest(arrays["models"], arrays["depth_index"]))
    np.savez(path, **arrays)


@pytest.mark.parametrize("damage, reason", [(_damage_edit, "SHA-256"), (_damage_nan, "non-finite"),
                                            (_damage_truncate, "unreadable"), (_damage_shape, "expected")])
def test_a_damaged_model_shard_is_recomputed_never_used(tensor, tmp_path, damage, reason):
    first = _zones(tensor, tmp_path)
    good = first.models(ZONE, [0, 1])
    damage(first.model_cache.path(ZONE, False))
    again = _zones(tensor, tmp_path)
    with pytest.warns(PsfCacheWarning, match=reason):
        remade = again.models(ZONE, [0, 1])
    assert again.models_computed == 2
    np.testing.assert_array_equal(remade, good)
    third = _zones(tensor, tmp_path)  # the shard was written again, whole
    np.testing.assert_array_equal(third.models(ZONE, [0, 1]), good)
    assert third.models_computed == 0


def test_a_map_without_a_disk_cache_writes_no_models(tensor, tmp_path):
    zones = ZoneKernels(PsfMap(tensor, BMI_SENSOR, mode="exact"), inverse_depth_candidates(tensor.depth_m, 4),
                        (2.0,), 64)
    zones.models(ZONE, [0])
    assert zones.model_cache is None and not any(tmp_path.iterdir())


def test_a_cache_it_cannot_write_warns_once_and_the_decode_goes_on(tensor, tmp_path, monkeypatch):
    """A full or read-only disk under the cache: the first failed write is named in one warning, the models stay in
    memory and are the same, and no further write is tried."""
    good = _zones(tensor, tmp_path / "good").models(ZONE, [0, 1])
    tries = []

    def full_disk(*args, **kwargs):
        tries.append(args)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(model_cache, "atomic_path", full_disk)
    zones = _zones(tensor, tmp_path / "full")
    with pytest.warns(PsfCacheWarning, match="No space left on device"):
        made = zones.models(ZONE, [0, 1])
    np.testing.assert_array_equal(made, good)
    zones.models((30.0, 30.0), [0])  # another zone: no second try, no second warning
    assert len(tries) == 1 and not zones.model_cache.writable


def test_a_kernel_cache_it_cannot_write_warns_once_and_keeps_the_kernels(tensor, tmp_path, monkeypatch):
    """The kernels' disk cache on a full or read-only disk: the traced kernels are those of a map without a disk
    cache, one warning names the folder, and no further shard write is tried."""
    from bmi_sdk.render import psf_map as psf_map_module

    plain = PsfMap(tensor, BMI_SENSOR, mode="exact").kernels(*ZONE, [0, 1])
    tries = []

    def full_disk(*args, **kwargs):
        tries.append(args)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(psf_map_module, "write_kernel_shard", full_disk)
    cached = PsfMap(tensor, BMI_SENSOR, mode="exact", cache_dir=tmp_path)
    with pytest.warns(PsfCacheWarning, match="No space left on device"):
        kernels = cached.kernels(*ZONE, [0, 1])
    np.testing.assert_array_equal(kernels, plain)
    cached.kernels(30.0, 30.0, [0])  # another zone: no second try, no second warning
    assert len(tries) == 1 and not cached.disk_writable
