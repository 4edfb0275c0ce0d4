"""The design camera's two decoders on rendered plane scenes, shared by ``bmi bench reflectance`` and ``bmi bench
texture``: the default evidence decoder and the classical one, on the camera's exact kernels (the simulated device's
and ``bmi infer``'s path)."""

from __future__ import annotations

LENS = "bmi_monocentric"


def design_decoders() -> tuple:
    """(psf_map, geometry, network, stages) of the design camera: its exact kernels (disk-cached), sensor geometry,
    the shipped evidence network, and ``stages`` {"evidence": the network's classical stage, "classical": the
    classical decoder at its defaults}, both on those kernels."""
    from ..built_camera import BuiltCamera
    from ..decode import ClassicalConfig, ClassicalDecoder
    from ..lenses import lens_geometry
    from ..runtime.evidence import EvidenceNetwork
    from ..runtime.model import select_model

    psf_map = BuiltCamera(LENS).psf_map(disk_cache=True)
    network = EvidenceNetwork(select_model(LENS, "evidence"), threads=2)
    stages = {"evidence": ClassicalDecoder.for_psf_map(psf_map, network.stage_config()),
              "classical": ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig())}
    return psf_map, lens_geometry(LENS), network, stages


DECODER_NAMES = ("evidence (default)", "classical")


def decoder_reads(raw, row0: int, col0: int, stages: dict, network) -> dict:
    """{``DECODER_NAMES`` entry: depth_m} of one raw window of the design camera at σ 0.005 (``decoder_reads_sigma``
    without the 1σ)."""
    return {name: depth for name, (depth, _) in decoder_reads_sigma(raw, row0, col0, stages, network).items()}


def decoder_reads_sigma(raw, row0: int, col0: int, stages: dict, network, supports: dict | None = None,
                        volumes: dict | None = None) -> dict:
    """{``DECODER_NAMES`` entry: (depth_m, 1σ in m)} of one raw window of the design camera at σ 0.005: the evidence
    decoder (``stages["evidence"]``, the network's classical stage, then its support read and upsampling as
    ``runtime.evidence.decode_evidence`` runs them) and the classical decoder (``stages["classical"]``); for each
    {name: ``decode.support.SupportConfig``} of ``supports``, the evidence decoder's volume read with that support read
    instead of its manifest's; and for each {name: classical stage} of ``volumes``, that stage's volume read by the
    network as the evidence decoder reads its own."""
    from ..lenses import lens_geometry
    from ..model_io import raw_to_rgb
    from ..nn.data import STANDARD_SIGMA
    from ..sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile
    from .evidence import pixel_read

    geometry = lens_geometry(LENS)
    noise = NoiseProfile.additive(STANDARD_SIGMA)
    decode = lambda stage: stage.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0,  # noqa: E731
                                        noise_profile=noise, aif=False)
    result = decode(stages["evidence"])
    inv_grid, sig_grid = network.read_decode(result)
    rgb = raw_to_rgb(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN)
    read = lambda support: pixel_read(inv_grid, sig_grid, rgb, support, network.colour_sigma,  # noqa: E731
                                      stages["evidence"].config,
                                      network.pixel_select if support is network.support else None)
    classical = decode(stages["classical"])
    reads = dict(zip(DECODER_NAMES, (read(network.support), (classical.depth_m, classical.depth_sigma_m))))
    reads |= {name: read(support) for name, support in (supports or {}).items()}
    for name, stage in (volumes or {}).items():
        inv_grid, sig_grid = network.read_decode(decode(stage))
        reads[name] = pixel_read(inv_grid, sig_grid, rgb, network.support, network.colour_sigma, stage.config,
                                 network.pixel_select)
    return reads
