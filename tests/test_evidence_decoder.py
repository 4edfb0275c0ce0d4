"""The evidence decoder end to end through the command line: a textured plane at a known range reads that range,
with a 1σ that covers its error, and the report says what the decoder did."""

import json

import numpy as np
import pytest

from bmi_sdk.runtime.evidence import EVIDENCE_MODEL

pytestmark = pytest.mark.skipif(not EVIDENCE_MODEL.exists(), reason="no packaged evidence network")


def test_infer_evidence_reads_a_textured_plane(tmp_path, bmi):
    from bmi_sdk.scenes.procedural import pink_noise

    size, range_m = 192, 2.0
    rng = np.random.default_rng(3)
    texture = np.stack([pink_noise((size, size), rng) for _ in range(3)], axis=-1)
    rgb = np.clip(0.3 * np.exp(0.8 * (texture - texture.mean()) / texture.std()), 0.0, 1.0).astype(np.float32)
    np.save(tmp_path / "rgb.npy", rgb)
    np.save(tmp_path / "depth.npy", np.full((size, size), range_m, np.float32))
    bmi("simulate", "--rgb", tmp_path / "rgb.npy", "--depth", tmp_path / "depth.npy", "--field-deg", 20,
        "--psf-mode", "tensor", "--noise", 0.005, "--out", tmp_path / "f.dng")
    out = bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "o", "--decoder", "evidence", "--quiet").stdout
    assert "evidence" in out
    depth = np.load(tmp_path / "o" / "depth.npy")
    sigma = np.load(tmp_path / "o" / "depth_sigma.npy")
    ok = np.isfinite(depth)
    assert ok.mean() > 0.9 and np.array_equal(ok, np.isfinite(sigma)) and np.all(sigma[ok] > 0)
    inner = ok[32:-32, 32:-32]
    assert abs(np.median(depth[32:-32, 32:-32][inner]) / range_m - 1.0) < 0.05
    z = (depth[ok] - range_m) / sigma[ok]
    assert np.mean(np.abs(z) < 3.0) > 0.9  # the 1σ covers the error (not a σ far too small)
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["decoder"] == "evidence" and 0.0 <= report["confident_coverage"] <= 1.0
    assert set(report["timings_s"]) >= {"evidence_s", "network_s", "upsample_s", "aif_s"}
    assert np.isfinite(np.load(tmp_path / "o" / "aif.npy")).all()


def test_the_reported_sigma_is_the_classical_stages_when_the_manifest_says_so(tmp_path):
    """A manifest's ``sigma_source`` picks the window 1σ: "classical" reports the classical stage's fitted σ model
    (``DecodeResult.grid_sigma_inv``) beside the network's 1/d, "network" the network's own; any other is refused."""
    import shutil
    from types import SimpleNamespace

    from bmi_sdk.model_manifest import ModelError
    from bmi_sdk.runtime.evidence import EvidenceNetwork

    manifest = json.loads(EVIDENCE_MODEL.with_suffix(".manifest.json").read_text())
    rng = np.random.default_rng(7)
    rows, cols, d = 6, 10, len(manifest["candidates_inv_depth_per_m"])
    own = rng.uniform(0, 30, (rows, cols, d)).astype(np.float32)
    own -= own.min(axis=-1, keepdims=True)
    result = SimpleNamespace(grid_pooled=2 * own, grid_curves=own, grid_colour=rng.normal(0, 0.3, (rows, cols, 3)),
                             grid_sigma_inv=rng.uniform(0.01, 0.2, (rows, cols)))
    reads = {}
    for source in ("classical", "network", "guess"):
        path = tmp_path / source / EVIDENCE_MODEL.name
        path.parent.mkdir()
        shutil.copy(EVIDENCE_MODEL, path)
        path.with_suffix(".manifest.json").write_text(json.dumps(dict(manifest, sigma_source=source)))
        if source == "guess":
            with pytest.raises(ModelError, match="sigma_source"):
                EvidenceNetwork(path)
            continue
        reads[source] = EvidenceNetwork(path).read_decode(result)
    np.testing.assert_array_equal(reads["classical"][0], reads["network"][0])
    np.testing.assert_allclose(reads["classical"][1], result.grid_sigma_inv, rtol=1e-6)
    assert not np.allclose(reads["network"][1], result.grid_sigma_inv, rtol=0.1)
