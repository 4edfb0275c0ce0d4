"""``bmi eval``'s paired comparison of decoders: each decoder's per-tile AbsRel less a reference decoder's on the
same tiles, with the standard error of that mean difference.

Every decoder of a run reads the same rendered tiles with the same noise draw (``evaluate.tile_raw``), so the two
reads of one tile share its scene, its texture and its noise. A row's own standard error (``absrel_se``) is mostly
the spread *between* tiles, which both decoders see alike; the difference's standard error leaves that out and
resolves a change between decoders several times finer than comparing two rows' means would.

A pair is formed within one scene scale, condition and region, between rows of the same tiles in the same order
(``evaluate.score_tiles`` scores every decoder over one list of renders; ``built_camera_sampled`` over every
camera's renders in turn). A tile read by only one of the two (AbsRel NaN: no valid pixel) is left out of the pair.
"""

from __future__ import annotations

import math

import numpy as np


def paired_differences(rows: list[dict], reference: str) -> list[dict]:
    """One dict per row of ``rows`` whose decoder is not ``reference`` and that has a ``reference`` row of the
    same scene scale, condition and region: {scene_scale, condition, region, decoder, reference, tiles (pairs
    used), absrel_diff (mean over the pairs of decoder − reference AbsRel), absrel_diff_se (its standard error,
    ``evaluate.tile_standard_error``), better_share (share of the pairs where the decoder reads lower)}.

    Every row needs ``tile_absrel`` (``evaluate.region_rows``); rows paired with tile lists of different lengths are
    refused (they are not reads of the same tiles)."""
    from bmi_sdk.nn.evaluate import tile_standard_error

    def key(row: dict) -> tuple:
        return row["scene_scale"], row["condition"], row["region"]

    references = {key(r): r for r in rows if r["decoder"] == reference}
    out = []
    for row in rows:
        ref = references.get(key(row))
        if ref is None or row["decoder"] == reference:
            continue
        mine, theirs = np.asarray(row["tile_absrel"], np.float64), np.asarray(ref["tile_absrel"], np.float64)
        if mine.shape != theirs.shape:
            raise ValueError(f"{row['decoder']} and {reference} read {mine.size} and {theirs.size} tiles in "
                             f"{row['condition']} / {row['region']}: a paired difference needs the same tiles")
        diff = (mine - theirs)[np.isfinite(mine) & np.isfinite(theirs)]
        out.append({"scene_scale": row["scene_scale"], "condition": row["condition"], "region": row["region"],
                    "decoder": row["decoder"], "reference": reference, "tiles": int(diff.size),
                    "absrel_diff": float(diff.mean()) if diff.size else math.nan,
                    "absrel_diff_se": tile_standard_error(list(diff)),
                    "better_share": float((diff < 0).mean()) if diff.size else math.nan})
    return out
