"""`bmi bench reflectance`: its painted planes and the bands it scores line up with each other."""

import numpy as np
import pytest

from bmi_sdk.bench.decoder import PLANE_MARGIN_PX
from bmi_sdk.bench.reflectance import AWAY_PX, EDGE_BAND_PX, PAINTINGS, SIZE_PX, band_masks, painted_scene


@pytest.mark.parametrize("painting", list(PAINTINGS))
def test_each_paint_edge_lies_in_the_near_band_and_outside_the_away_band(painting):
    painted = PAINTINGS[painting]
    m = PLANE_MARGIN_PX
    ratio = (painted_scene(3, painted, 0.2) / painted_scene(3, painted, 1.0))[m:-m, m:-m, 1]
    assert np.allclose(ratio, ratio[:1])  # the paint runs down whole columns
    dark = np.isclose(ratio[0], 0.2)
    assert dark.any() and np.isclose(ratio[0][~dark], 1.0).all()
    edges = np.flatnonzero(np.diff(dark.astype(int))) + 0.5  # between the last column of one paint and the next
    near, away = band_masks(painted)
    columns = np.arange(SIZE_PX)
    for edge in edges:
        within = np.abs(columns - edge) <= EDGE_BAND_PX - 0.5
        assert near[0][within].all()
        assert not away[0][np.abs(columns - edge) < AWAY_PX - 0.5].any()
    assert away[0].any() and not (near & away).any()
