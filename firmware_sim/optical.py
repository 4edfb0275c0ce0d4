"""Optical irradiance sources: scenes seen through the lens by the forward simulator.

* ``RenderedScene`` — an RGB + range scene placed at (row0, col0) of the
  sensor, rendered through the lens (``bmi_sdk.render.render_coded``).
* ``procedural:SEED`` — the embedded default: a full-sensor procedural scene
  (``bmi_sdk.scenes.generate_scene``) seen through the lens.

The renderer and the optics are imported where a scene is built and rendered,
not with this module: ``firmware_sim`` imports it to register ``procedural``,
and a process that never builds a scene seen through the lens never loads
them.

The readout asks for strips of any window. A source renders fixed blocks of
``block_px`` (aligned to the sensor grid) with one kernel width of scene
margin and caches them, so every window it is asked for is identical to the
same region of a full-frame render (the renderer anchors its zones to the
sensor too) and each block is rendered once. Outside the scene the
irradiance is 0.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry

from .sources import register_source

BLOCK_PX = 512


@lru_cache(maxsize=4)
def _tensor(lens_name: str):
    from bmi_sdk.optics import PsfTensor, get_lens

    return PsfTensor(get_lens(lens_name))


class RenderedScene:
    """An RGB + range scene at (row0, col0) of the sensor, seen through the lens (see module doc)."""

    def __init__(self, rgb: np.ndarray, range_m: np.ndarray, row0: int = 0, col0: int = 0,
                 lens: str = "bmi_monocentric", geometry: SensorGeometry = BMI_SENSOR, name: str = "scene",
                 psf_mode: str = "exact", zone_px: int | None = None, block_px: int = BLOCK_PX, label: str = "",
                 tensor=None, perturbation=None):
        """``zone_px``: the renderer's zone size (None: its ``DEFAULT_ZONE_PX``, or for a built camera its
        ``BuiltCamera.render_zone_px``, finer where its kernels change fast with θ). ``tensor`` (a PsfTensor)
        overrides the lens's default one; ``perturbation``
        (``optics.perturb.Perturbation``, ``exact`` mode only) makes the camera a built one with those
        hardware errors: every zone's kernels are traced through the perturbed lens, and the image
        lands where the built camera puts it (the decenter's whole-image shift included)."""
        if rgb.ndim != 3 or rgb.shape[2] != 3 or range_m.shape != rgb.shape[:2]:
            raise ValueError(f"scene needs rgb H×W×3 and range_m H×W, got {rgb.shape} and {range_m.shape}")
        self.rgb = np.asarray(rgb, dtype=np.float32)
        self.range_m = np.asarray(range_m, dtype=np.float32)
        self.row0, self.col0 = int(row0), int(col0)
        self.tensor = tensor
        from .device import lens_profile_name

        # the lens profile frames name: a given tensor's lens ("fisheye_matched" → "fisheye")
        self.lens = lens if tensor is None else lens_profile_name(tensor.lens.name)
        self.geometry = geometry
        self.name = name
        self.psf_mode = psf_mode
        self.block_px = block_px
        self.label = label
        self.perturbation = perturbation if perturbation is not None and np.any(perturbation.to_vector()) else None
        if self.perturbation is not None and psf_mode != "exact":
            raise ValueError("a built camera's hardware errors need psf_mode='exact' (the radial tensor cannot "
                             "hold decenter or tilt)")
        if zone_px is None:
            from bmi_sdk.built_camera import BuiltCamera
            from bmi_sdk.render import DEFAULT_ZONE_PX

            zone_px = DEFAULT_ZONE_PX if self.perturbation is None else BuiltCamera(
                self.lens, self.perturbation, geometry).render_zone_px("exact")
        self.zone_px = zone_px
        self._blocks: dict[tuple[int, int], np.ndarray] = {}
        self._psf_map = None  # one kernel memo for all blocks: zones straddle block borders

    def metadata(self) -> dict:
        meta = {"source": self.name, "label": self.label, "lens": self.lens, "psf_mode": self.psf_mode,
                "scene_window": [self.row0, self.col0, *self.rgb.shape[:2]], "zone_px": self.zone_px}
        if self.perturbation is not None:
            meta["injected_perturbation"] = self.perturbation.to_dict()
        return meta

    def _block(self, br: int, bc: int) -> np.ndarray:
        key = (br, bc)
        if key not in self._blocks:
            from bmi_sdk.render import PsfMap, render_coded

            tensor = self.tensor if self.tensor is not None else _tensor(self.lens)
            if self._psf_map is None:
                self._psf_map = PsfMap(tensor, self.geometry, mode=self.psf_mode, perturbation=self.perturbation)
            margin = tensor.spec.kernel_px
            h, w = self.rgb.shape[:2]
            # block in scene coordinates, then with margin, clipped to the scene
            r0, c0 = br * self.block_px - self.row0, bc * self.block_px - self.col0
            r1, c1 = r0 + self.block_px, c0 + self.block_px
            R0, C0 = max(r0 - margin, 0), max(c0 - margin, 0)
            R1, C1 = min(r1 + margin, h), min(c1 + margin, w)
            out = np.zeros((self.block_px, self.block_px, 3), np.float32)
            if R1 > R0 and C1 > C0:
                img = render_coded(self.rgb[R0:R1, C0:C1], self.range_m[R0:R1, C0:C1], tensor, self.geometry,
                                   self.row0 + R0, self.col0 + C0, zone_px=self.zone_px, psf_map=self._psf_map)
                rr0, cc0 = max(r0, 0), max(c0, 0)
                rr1, cc1 = min(r1, h), min(c1, w)
                if rr1 > rr0 and cc1 > cc0:
                    out[rr0 - r0:rr1 - r0, cc0 - c0:cc1 - c0] = img[rr0 - R0:rr1 - R0, cc0 - C0:cc1 - C0]
            self._blocks[key] = out
        return self._blocks[key]

    def _blocks_in(self, row0: int, col0: int, height: int, width: int):
        """(block row, block col) of the blocks that cover the window and hold some of the scene."""
        b = self.block_px
        for br in range(row0 // b, (row0 + height - 1) // b + 1):
            for bc in range(col0 // b, (col0 + width - 1) // b + 1):
                top, left = br * b, bc * b
                if (self.row0 < top + b and top < self.row0 + self.rgb.shape[0]
                        and self.col0 < left + b and left < self.col0 + self.rgb.shape[1]):
                    yield br, bc

    def irradiance(self, row0: int, col0: int, height: int, width: int) -> np.ndarray:
        out = np.zeros((height, width, 3), np.float32)  # blocks outside the scene: no light
        b = self.block_px
        for br, bc in self._blocks_in(row0, col0, height, width):
            top, left = br * b, bc * b
            r0, r1 = max(row0, top), min(row0 + height, top + b)
            c0, c1 = max(col0, left), min(col0 + width, left + b)
            out[r0 - row0:r1 - row0, c0 - col0:c1 - col0] = self._block(br, bc)[r0 - top:r1 - top,
                                                                                    c0 - left:c1 - left]
        return out

    def work(self, row0: int, col0: int, height: int, width: int) -> tuple[int, int]:
        """(blocks rendered, blocks needed) for this window: the render's progress, for heartbeats."""
        needed = list(self._blocks_in(row0, col0, height, width))
        return sum(key in self._blocks for key in needed), len(needed)


class ProceduralOpticalSource(RenderedScene):
    """``procedural:SEED``: the embedded default full-sensor scene through the lens (generated on first use)."""

    def __init__(self, seed: int, geometry: SensorGeometry = BMI_SENSOR, **kwargs):
        self.seed = seed
        self._geometry_for_scene = geometry
        self._kwargs = kwargs
        self.name = "procedural"
        self._ready = False

    def _materialise(self) -> None:
        from bmi_sdk.scenes import generate_scene

        g = self._geometry_for_scene
        scene = generate_scene(g.height_px, g.width_px, self.seed)
        super().__init__(scene.rgb, scene.range_m, 0, 0, geometry=g, name="procedural",
                         label=f"procedural seed {self.seed}", **self._kwargs)
        self._ready = True

    def irradiance(self, row0: int, col0: int, height: int, width: int) -> np.ndarray:
        if not self._ready:
            self._materialise()
        return super().irradiance(row0, col0, height, width)

    def work(self, row0: int, col0: int, height: int, width: int) -> tuple[int, int] | None:
        return super().work(row0, col0, height, width) if self._ready else None

    def metadata(self) -> dict:
        meta = super().metadata() if self._ready else {"source": self.name, "label": f"procedural seed {self.seed}"}
        return dict(meta, seed=self.seed)


def _procedural(arg):
    try:
        seed = 0 if arg is None else int(arg)
    except ValueError:
        raise ValueError(f"procedural:SEED takes an integer seed, got {arg!r}") from None
    return ProceduralOpticalSource(seed)


register_source("procedural", _procedural)
