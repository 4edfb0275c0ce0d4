"""The evidence decoder: the camera's own evidence volume, read by a small network, then guided to every pixel.

Steps for one frame (docs/decoder.md):

1. the classical decoder over the camera's kernels (``BuiltCamera.psf_map``: the design's, or a calibrated
   camera's exact kernels) scores every window against every depth candidate, with the knobs of the network's
   manifest, and keeps its cost volume (``decode.DecodeResult.grid_pooled`` / ``grid_curves``);
2. the network (``evidence.onnx``, ``nn.volume_net``) turns the volume into logits over the candidates; 1/d is
   the mean of the posterior they describe, continuous between candidates (``decode.volume.posterior``, read here
   from the graph's logits), its 1σ the posterior spread, scaled and floored as fitted on held-out pairs. The grid is
   padded to a multiple of 4 windows and read in bands of ``BAND_ROWS`` grid rows (with a halo of
   ``HALO_ROWS``, the network's reach), so memory stays bounded on a full frame;
3. each window's read becomes the mixture of its like-coloured neighbours whose support holds one colour
   (``decode.support.frame_support_read``, the manifest's ``support``): a window straddling an occlusion takes the
   read of the windows that see one surface of its colour;
4. 1/d and its variance go to every pixel by colour-guided upsampling (``decode.volume.guided_upsample``) over
   the demosaiced frame: a pixel between windows takes those of its own colour, and its σ includes the
   spread of the windows it mixes; where a pixel's windows disagree, its depth is the mixture of the 4 × 4 windows'
   reads around it scored by the manifest's fitted ``pixel_select`` (``decode.pixel_select``);
5. the AiF is the Wiener deconvolution of the frame with the kernels at that depth
   (``ClassicalDecoder.restore_aif`` without a prior).

No step is retrained for a calibrated camera: its kernels change the volume, and the network reads the volume.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..built_camera import BuiltCamera
from ..decode import ClassicalConfig, ClassicalDecoder
from ..decode.classical import with_texture_exponent
from ..decode.pixel_select import Grids, PixelSelect, select_depth
from ..decode.support import SupportConfig, frame_support_read, support_colours
from ..decode.volume import guided_upsample, pixel_log_colour, posterior, volume_inputs
from ..model_io import raw_to_rgb
from ..model_manifest import ModelError, verify_model
from ..sensor import NoiseProfile
from .decoders import DecodedFrame
from .pipeline import check_decodable

EVIDENCE_MODEL = Path(__file__).resolve().parents[1] / "models" / "evidence.onnx"
PAD_MULTIPLE = 4
"""The network halves the grid twice: its rows and columns are padded to a multiple of this."""
BAND_ROWS = 64
"""Grid rows the network reads at once (a full frame has ~280): bounds onnxruntime's arena."""
HALO_ROWS = 28
"""Grid rows read above and below a band and dropped: the network's reach across rows (``tests/
test_evidence_volume.py`` measures it), so a band reads what the whole grid would."""


class EvidenceNetwork:
    """A verified evidence network (manifest and SHA-256 checked) in one onnxruntime session."""

    def __init__(self, path: str | os.PathLike = EVIDENCE_MODEL, threads: int | None = None, providers=None):
        import onnxruntime as ort

        from .model import choose_providers, session_options

        t0 = time.perf_counter()
        self.path = Path(path)
        self.manifest = verify_model(self.path)
        if self.manifest.get("decoder") != "evidence":
            raise ModelError(f"model {self.path.name} is a {self.manifest.get('decoder', 'cnn')} model, not an "
                             "evidence network")
        self.inv_depth_per_m = np.asarray(self.manifest["candidates_inv_depth_per_m"], np.float64)
        self.classical_config = dict(self.manifest["classical_config"])
        self.colour_sigma = float(self.manifest["upsample_colour_sigma"])
        self.sigma_source = self.manifest.get("sigma_source", "network")
        self.support = self._support(self.manifest.get("support"))
        self.pixel_select = self._pixel_select(self.manifest.get("pixel_select"))
        self.session = ort.InferenceSession(str(self.path), sess_options=session_options(threads),
                                            providers=choose_providers(providers))
        self.provider = self.session.get_providers()[0]
        # a network whose residual is zero reads no guide, and its exported graph has no such input
        self.input_names = {i.name for i in self.session.get_inputs()}
        self.load_s = time.perf_counter() - t0
        self.warmup_s = 0.0  # the grid's shape changes with the frame: there is no one shape to warm up

    def _support(self, knobs) -> SupportConfig | None:
        """The manifest's ``support`` knobs (``decode.support``); None (each window keeps its own read) without.
        Knobs that name no ``estimate`` were chosen for the mixture's mean, and read with it; knobs that name no
        ``attribution`` were chosen with reads compared by their cell colours, and read so."""
        if knobs is None:
            return None
        try:
            return SupportConfig(**{"estimate": "mean", "attribution": "cell", **knobs})
        except (TypeError, ValueError) as e:
            raise ModelError(f"manifest of {self.path.name}: its support knobs {knobs!r} are not valid: {e}") from None

    def _pixel_select(self, weights) -> PixelSelect | None:
        """The manifest's fitted ``pixel_select`` scorer (``decode.pixel_select``); None (the guided read everywhere)
        without. It scores the support read's candidates, so a manifest with it needs ``support``."""
        if weights is None:
            return None
        if self.support is None:
            raise ModelError(f"manifest of {self.path.name}: pixel_select scores support reads, but it has no support")
        try:
            return PixelSelect.from_dict(weights)
        except ValueError as e:
            raise ModelError(f"manifest of {self.path.name}: its pixel_select weights are not valid: {e}") from None

    def stage_config(self, threads: int | None = None) -> ClassicalConfig:
        """The classical decoder's knobs that make this network's volume (its manifest's), on ``threads`` threads."""
        knobs = self.classical_config
        return ClassicalConfig(**{**knobs, "slopes": tuple(knobs.get("slopes", (2.0,))), "threads": threads})

    def read_decode(self, result) -> tuple[np.ndarray, np.ndarray]:
        """(1/d, 1σ of 1/d) on the window grid of a classical decode of its knobs (NaN 1/d where a window has no
        decode): its volume (``volume_inputs``) read by the network (``read``); the 1σ is the network's, or with
        the manifest's ``sigma_source`` "classical" the classical stage's own (``DecodeResult.grid_sigma_inv``)."""
        if result.grid_pooled is None or result.grid_curves is None or result.grid_colour is None:
            raise ModelError(f"evidence network {self.path.name}: its classical_config decodes without pooling "
                             "(pool_sigma_px = 0), so there is no volume to read")
        volume, guide, grid_valid = volume_inputs(result.grid_pooled, result.grid_curves, result.grid_colour)
        inv_grid, sig_grid = self.read(volume, guide)
        if self.sigma_source == "classical":
            sig_grid = result.grid_sigma_inv.astype(np.float32)
        return np.where(grid_valid, inv_grid, np.nan), sig_grid

    def describe(self) -> dict:
        return {"path": str(self.path), "sha256": self.manifest["sha256"], "decoder": "evidence",
                "preset": self.manifest["preset"], "lens": self.manifest["lens"],
                "psf_tensor_key": self.manifest["psf_tensor_key"], "execution_provider": self.provider,
                "load_s": self.load_s, "warmup_s": self.warmup_s}

    def read(self, volume: np.ndarray, guide: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(1/d, 1σ of 1/d), each R × C, of a (2, D, R, C) volume and (4, R, C) guide (``volume_inputs``): the 1/d
        ``decode.volume.posterior`` reads from the graph's logits, the 1σ the graph's own."""
        rows, cols = guide.shape[1:]
        inv = np.empty((rows, cols), np.float32)
        sig = np.empty((rows, cols), np.float32)
        for top in range(0, rows, BAND_ROWS):
            bottom = min(rows, top + BAND_ROWS)
            lo, hi = max(0, top - HALO_ROWS), min(rows, bottom + HALO_ROWS)
            pad_r = -(hi - lo) % PAD_MULTIPLE
            pad_c = -cols % PAD_MULTIPLE
            vol = np.pad(volume[:, :, lo:hi], ((0, 0), (0, 0), (0, pad_r), (0, pad_c)))[None]
            gd = np.pad(guide[:, lo:hi], ((0, 0), (0, pad_r), (0, pad_c)))[None]
            feeds = {name: value for name, value in (("volume", vol), ("guide", gd)) if name in self.input_names}
            logits, sigma = self.session.run(["logits", "sigma_inv"], feeds)
            inv[top:bottom] = posterior(logits[0, :, top - lo:bottom - lo, :cols], self.inv_depth_per_m)[0]
            sig[top:bottom] = sigma[0, top - lo:bottom - lo, :cols]
        return inv, sig


def evidence_stage(network: EvidenceNetwork, camera: BuiltCamera, threads: int | None = None,
                   texture_exponent: str = "prior") -> ClassicalDecoder:
    """The classical decoder whose volume ``network`` reads: the camera's kernels, the manifest's knobs (with
    ``texture_exponent``'s, ``decode.classical.TEXTURE_EXPONENTS``), and the candidates the network was trained on
    (refused, naming both, when the camera's kernels give others)."""
    config = with_texture_exponent(network.stage_config(threads), texture_exponent)
    stage = ClassicalDecoder.for_psf_map(camera.psf_map(disk_cache=True), config)
    got = stage.candidates.inv_depth_per_m
    if got.shape != network.inv_depth_per_m.shape or not np.allclose(got, network.inv_depth_per_m, rtol=1e-5):
        raise ModelError(f"evidence network {network.path.name} reads {len(network.inv_depth_per_m)} depth "
                         f"candidates, but camera {camera.lens_name}'s kernels give {len(got)} others")
    return stage


@dataclass
class PixelReads:
    """``read_pixels``' result: 1/d and its variance at every pixel (H × W), the window grid after the support read,
    the windows' own reads, the pixels the selection scored and the steps' times."""

    inv_px: np.ndarray
    var_px: np.ndarray
    inv_grid: np.ndarray
    var_grid: np.ndarray
    inv_own: np.ndarray
    var_own: np.ndarray
    selected: int
    timings: dict


def read_pixels(inv_own: np.ndarray, var_own: np.ndarray, rgb: np.ndarray, support: SupportConfig | None,
                colour_sigma: float, select: PixelSelect | None, window_px: int, stride_px: int,
                threads: int = 1) -> PixelReads:
    """Steps 3–4 (module doc) from the windows' own reads (1/d and variance on the window grid) and the frame's
    H × W × 3 linear RGB: the support read (``support`` None: off), the colour-guided upsampling, then the pixel
    selection where the windows disagree (``select`` None: off; it needs the support read). The colours the support
    read takes serve the selection too."""
    timings: dict[str, float] = {}
    inv_grid, var_grid, colours = inv_own, var_own, None
    if support is not None:
        t0 = time.perf_counter()
        colours = support_colours(rgb, support, inv_own.shape, window_px, stride_px, threads)
        inv_grid, var_grid = frame_support_read(inv_own, var_own, rgb, support, window_px, stride_px, threads, colours)
        timings["support_s"] = time.perf_counter() - t0
    log_rgb = pixel_log_colour(rgb)
    inv_px, var_px = guided_upsample(inv_grid, var_grid, log_rgb, stride_px, colour_sigma, threads=threads)
    selected = 0
    if select is not None and support is not None:
        t0 = time.perf_counter()
        grids = Grids.of_frame(inv_grid, var_grid, inv_own, var_own, rgb, log_rgb, stride_px, window_px,
                               support.dark_floor, threads, colours)
        selected = select_depth(select, grids, inv_px, var_px, threads)
        timings["pixel_select_s"] = time.perf_counter() - t0
    return PixelReads(inv_px, var_px, inv_grid, var_grid, inv_own, var_own, selected, timings)


def decode_evidence(network: EvidenceNetwork, stage: ClassicalDecoder, frame, camera: BuiltCamera,
                    progress: bool = False) -> DecodedFrame:
    """Decode a ``devices.RawFrame`` of ``camera`` (module doc); ``parts["classical"]`` holds the classical
    stage's whole result (its own read, the volume)."""
    check_decodable(frame, camera.lens_name, "the decoder's camera has", "the evidence decoder")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    row0, col0 = frame.roi.y_px, frame.roi.x_px
    result = stage.decode(frame.data, frame.black_level_dn, frame.white_level_dn, frame.geometry, row0=row0,
                          col0=col0, cfa=frame.cfa, progress=progress, noise_profile=frame.noise_profile, aif=False)
    timings["evidence_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    inv_grid, sig_grid = network.read_decode(result)
    timings["network_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rgb = raw_to_rgb(frame.data, frame.black_level_dn, frame.white_level_dn, frame.cfa)
    stride_px = stage.config.stride_px
    pixels = read_pixels(inv_grid, sig_grid.astype(np.float32) ** 2, rgb, network.support, network.colour_sigma,
                         network.pixel_select, stage.config.window_px, stride_px, stage.threads)
    inv_px, var_px, inv_grid, var_grid = pixels.inv_px, pixels.var_px, pixels.inv_grid, pixels.var_grid
    timings.update(pixels.timings)
    del rgb
    valid = result.valid & np.isfinite(inv_px) & (inv_px > 0)
    depth = np.where(valid, np.float32(1.0) / np.where(valid, inv_px, np.float32(1.0)), np.float32(np.nan))
    sigma = np.where(valid, np.sqrt(np.maximum(var_px, np.float32(0.0))) * depth * depth, np.float32(np.nan))
    timings["upsample_s"] = (time.perf_counter() - t0 - timings.get("support_s", 0.0)
                             - timings.get("pixel_select_s", 0.0))
    t0 = time.perf_counter()
    noise = NoiseProfile(**result.stats["noise_profile"])  # the noise the stage decoded with
    aif = stage.restore_aif(frame.data, frame.black_level_dn, frame.white_level_dn, frame.geometry, depth, None,
                            noise, row0, col0, frame.cfa)
    timings["aif_s"] = time.perf_counter() - t0
    stats = dict(result.stats, camera_sha256=camera.sha256(), calibration_id=camera.calibration_id)
    confident = valid & (sigma <= 0.1 * np.where(valid, depth, 1.0))
    report = {"valid_fraction": float(valid.mean()),
              "confident_coverage": float(confident.sum() / max(valid.sum(), 1)),
              "blocks_run": stats["blocks_run"], "blocks_skipped": stats["blocks_skipped"],
              "support": None if network.support is None else network.support.to_dict(),
              "pixels_selected": pixels.selected,
              "decoder_stats": stats, "timings_s": {**stats["timings_s"], **timings}}
    return DecodedFrame(aif, depth, valid, sigma, report,
                        {"classical": result, "grid_inv_depth": inv_grid, "grid_sigma_inv": np.sqrt(var_grid),
                       "grid_inv_depth_own": pixels.inv_own, "grid_sigma_inv_own": np.sqrt(pixels.var_own)})

