"""The paper's metrics (bmi_sdk.metrics) on hand-computed cases, and bmi demo's error report, which uses them."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from bmi_sdk.metrics import SSIM_K1, SSIM_K2, depth_metrics, psnr_db, ssim


def test_depth_metrics_hand_computed():
    true = np.array([1.0, 2.0, 4.0, 5.0, 1.0])
    pred = np.array([1.2, 2.0, 2.0, 10.0, 7.0])
    valid = np.array([True, True, True, True, False])
    m = depth_metrics(pred, true, valid)
    # ratios 1.2, 1, 2, 2 → δ1 = 2/4, δ2 (<1.5625) = 2/4, δ3 (<1.953) = 2/4
    assert m["delta1"] == 0.5 and m["delta2"] == 0.5 and m["delta3"] == 0.5
    assert m["rmse_m"] == pytest.approx(math.sqrt((0.04 + 0 + 4 + 25) / 4))
    assert m["absrel"] == pytest.approx((0.2 + 0 + 0.5 + 1.0) / 4)


def test_psnr_and_ssim_hand_computed():
    a = np.full((32, 32, 3), 0.5)
    assert psnr_db(a + 0.1, a) == pytest.approx(20.0)
    assert ssim(a, a) == pytest.approx(1.0)
    # constant images: σ terms vanish, SSIM = (2ab + C1) / (a² + b² + C1)
    c1 = SSIM_K1 ** 2
    assert ssim(np.full((32, 32, 3), 0.3), a) == pytest.approx((2 * 0.15 + c1) / (0.09 + 0.25 + c1))
    assert SSIM_K2 == 0.03
    valid = np.zeros((32, 32), bool)
    valid[:, :16] = True
    b = a.copy()
    b[:, 16:] = 0.0
    assert psnr_db(b, a, valid) == math.inf


def test_demo_reports_the_metrics_of_bmi_eval_over_pixels_with_both_ranges():
    from bmi_sdk.cli.demo import errors_against_truth

    truth = np.array([[1.0, 2.0, 4.0, np.nan], [5.0, 1.0, 3.0, 2.0]], np.float32)
    pred = np.array([[1.2, 2.0, 2.0, 3.0], [10.0, 7.0, 0.0, np.nan]], np.float32)
    valid = np.array([[True, True, True, True], [True, False, True, True]])
    rgb = np.full((2, 4, 3), 0.5, np.float32)
    aif = rgb + np.float32(0.1)
    err = errors_against_truth(aif, pred, valid, SimpleNamespace(rgb=rgb, range_m=truth))
    # used: ranges (1, 1.2), (2, 2), (4, 2), (5, 10); not the unknown truth, the invalid pixel, a range ≤ 0 or NaN
    assert err["pixels"] == 4
    assert err["depth_abs_rel"] == pytest.approx((0.2 + 0 + 0.5 + 1.0) / 4)
    assert err["depth_delta_1.25"] == 0.5
    assert err["depth_mae_m"] == pytest.approx((0.2 + 0 + 2 + 5) / 4)
    assert err["aif_mae"] == pytest.approx(0.1) and err["aif_psnr_db"] == pytest.approx(20.0, abs=1e-5)
    ok = valid & np.isfinite(truth) & np.isfinite(pred) & (pred > 0)
    assert err["depth_abs_rel"] == depth_metrics(pred, truth, ok)["absrel"]
    with pytest.raises(ValueError, match="no pixel"):
        errors_against_truth(aif, pred, np.zeros_like(valid), SimpleNamespace(rgb=rgb, range_m=truth))
