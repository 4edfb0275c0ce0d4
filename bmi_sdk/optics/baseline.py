"""The fisheye comparison lens, matched to the monocentric lens.

The paper compares against "a conventional fisheye lens" through the same
simulation. We use a published design (``data/lenses/fisheye.json``: US
7,161,746 B2 Example 9, f = 10.56 mm, F/2.88) scaled to the monocentric
lens's focal length and entrance pupil (hence its F-number, F/1.79 for the
default). Opening an F/2.88 design to F/1.79 needs larger clear apertures:
every semi-diameter is multiplied by the F-number ratio, then capped where
the glass geometry ends (the sphere's radius, or where two surfaces would
cross). The sensor stays in the design's image plane (scaled). This is an
extrapolation of the design, stated as such in docs/optics.md.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .paraxial import first_order
from .prescription import Lens, PrescriptionError, load_lens


def _crossing_height(a, b, thickness_mm, h_max):
    """Largest h ≤ h_max at which surface b (``thickness_mm`` after a) stays behind a."""
    h = np.linspace(0.0, h_max, 2001)
    gap = thickness_mm + b.sag_mm(h) - a.sag_mm(h)
    bad = np.nonzero(gap < 0.02 * max(thickness_mm, 0.05))[0]
    return h_max if len(bad) == 0 else float(h[max(bad[0] - 1, 1)])


def matched_fisheye(reference: Lens | str = "bmi_monocentric", design: Lens | str = "fisheye") -> Lens:
    """The fisheye design scaled to ``reference``'s EFL and EPD (see module doc)."""
    ref = load_lens(reference) if isinstance(reference, str) else reference
    fish = load_lens(design) if isinstance(design, str) else design
    f_ref = first_order(ref).efl_mm
    f_fish = first_order(fish).efl_mm
    scaled = fish.scaled(f_ref / f_fish)
    ratio = ref.entrance_pupil_diameter_mm / scaled.entrance_pupil_diameter_mm
    surfaces = list(scaled.surfaces)
    sd = [min(s.semi_diameter_mm * ratio, abs(s.radius_mm) * 0.999) for s in surfaces]
    for j in range(len(surfaces) - 1):
        h_max = min(sd[j], sd[j + 1])
        cap = _crossing_height(surfaces[j], surfaces[j + 1], surfaces[j].thickness_mm, h_max)
        if cap < h_max:  # the two surfaces would cross: neither may open past the crossing
            sd[j] = min(sd[j], max(cap, surfaces[j].semi_diameter_mm))
            sd[j + 1] = min(sd[j + 1], max(cap, surfaces[j + 1].semi_diameter_mm))
    surfaces = [replace(s, semi_diameter_mm=float(h)) for s, h in zip(surfaces, sd)]
    matched = replace(scaled, surfaces=tuple(surfaces), name="fisheye_matched",
                      description=f"{fish.name} scaled to {ref.name}: EFL {f_ref:.4f} mm, EPD "
                                  f"{ref.entrance_pupil_diameter_mm} mm; clear apertures opened by ×{ratio:.3f}")
    matched = replace(matched, entrance_pupil_diameter_mm=ref.entrance_pupil_diameter_mm)
    matched = replace(matched, raw=matched.to_dict())
    first_order(matched)  # raises PrescriptionError if the stop still cannot pass the pupil
    return Lens.from_dict(matched.to_dict())


__all__ = ["matched_fisheye", "PrescriptionError"]
