"""The calibration's PNG report: measured vs fitted PSF patches and the residual map over the field."""

from __future__ import annotations

import numpy as np

from bmi_sdk.io_atomic import atomic_path

from .targets import Target


def write_report(path, result, doc: dict, max_spots: int = 6) -> None:
    """Rows of (measured, fitted, normalised residual) patches, then χ²/dof and centroid residuals over the sensor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bmi_sdk.geometry import BMI_SENSOR

    data, model, used = result.patches["data"], result.patches["model"], result.patches["used"]
    order = np.linspace(0, len(data) - 1, min(max_spots, len(data))).round().astype(int)
    fig = plt.figure(figsize=(12, 2.4 * len(order) + 5))
    grid = fig.add_gridspec(len(order) + 2, 3)
    target = Target.from_dict(doc["captures"]["target"])
    by_source = {c["source"]: c for c in doc["residuals"]["per_capture"]}
    for row, i in enumerate(order):
        src = target.sources[result.patches["index"][i]]
        d = np.where(used[i], data[i], np.nan)
        m = np.where(used[i], model[i], np.nan)
        sigma = np.sqrt(np.maximum(np.abs(model[i]), 1.0))
        vmax = np.nanmax(d) ** 0.5
        for col, (img, title) in enumerate([(np.sqrt(np.maximum(d, 0)), "measured (√DN)"),
                                            (np.sqrt(np.maximum(m, 0)), "fitted (√DN)"),
                                            ((d - m) / sigma, "(measured − fitted)/√model")]):
            ax = fig.add_subplot(grid[row, col])
            kw = dict(vmin=0, vmax=vmax, cmap="magma") if col < 2 else dict(vmin=-4, vmax=4, cmap="RdBu_r")
            im = ax.imshow(img, **kw)
            ax.set_xticks([])
            ax.set_yticks([])
            chi = by_source[result.patches["index"][i]]["chi2_reduced"]
            ax.set_title(f"θ {src.field_deg:.0f}°, φ {src.azimuth_deg:.0f}°, {src.depth_m} m — {title}"
                         + (f", χ²/dof {chi:.2f}" if col == 2 else ""), fontsize=7)
            fig.colorbar(im, ax=ax, fraction=0.046)
    ax = fig.add_subplot(grid[len(order):, :])
    g = BMI_SENSOR
    ax.set_xlim(0, g.width_px)
    ax.set_ylim(g.height_px, 0)
    ax.set_aspect("equal")
    for group, marker, label in ((doc["residuals"]["per_capture"], "o", "fitted sources"),
                                 (doc["residuals"]["held_out"], "s", "held-out sources")):
        if not group:
            continue
        src = [target.sources[c["source"]] for c in group]
        rows, cols = g.pixel_of_field(np.array([s.field_deg for s in src]), np.array([s.azimuth_deg for s in src]))
        chi = np.array([c["chi2_reduced"] for c in group])
        sc = ax.scatter(cols, rows, c=chi, marker=marker, s=80, cmap="viridis", vmin=0.5, vmax=2.0, label=label,
                        edgecolors="k")
        res = np.array([c["centroid_residual_px"] for c in group])
        ax.quiver(cols, rows, res[:, 1], res[:, 0], angles="xy", scale_units="xy", scale=0.002, color="r", width=0.002)
    fig.colorbar(sc, ax=ax, label="χ²/dof per capture")
    ax.legend(loc="upper right", fontsize=8)
    params = doc["parameters"]
    text = ", ".join(f"{k} {v['value'] if not isinstance(v['value'], list) else [round(x, 3) for x in v['value']]}"
                     for k, v in params.items())
    ax.set_title("Residual map over the sensor: colour χ²/dof, red arrows centroid residual ×500\n" + text, fontsize=8)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
