"""BD-rate / BD-PSNR (PCHIP mode) on worked examples computed by hand from the formula."""
import math

import numpy as np
import pytest

from baseline.eval.bdrate import BDError, bd_psnr, bd_rate

RATE_A = [1.0, 2.0, 4.0, 8.0]          # MB
PSNR_A = [28.0, 30.0, 31.5, 32.5]      # dB (concave, as real R-D curves)


def test_constant_rate_factor_gives_that_bd_rate():
    # B reaches each PSNR of A with 0.8x the bytes: log10 R_B(D) = log10 R_A(D) + log10 0.8 at the
    # nodes, and PCHIP commutes with adding a constant to y (same secants, same slopes), so the
    # mean log difference is log10 0.8 everywhere -> BD-rate = 0.8 - 1 = -20 %.
    rate_b = [0.8 * r for r in RATE_A]
    assert bd_rate(RATE_A, PSNR_A, rate_b, PSNR_A) == pytest.approx(-20.0, abs=1e-9)
    rate_c = [1.25 * r for r in RATE_A]
    assert bd_rate(RATE_A, PSNR_A, rate_c, PSNR_A) == pytest.approx(25.0, abs=1e-9)
    assert bd_rate(RATE_A, PSNR_A, RATE_A, PSNR_A) == pytest.approx(0.0, abs=1e-12)


def test_constant_psnr_offset_gives_that_bd_psnr():
    psnr_b = [p + 0.5 for p in PSNR_A]
    assert bd_psnr(RATE_A, PSNR_A, RATE_A, psnr_b) == pytest.approx(0.5, abs=1e-12)
    psnr_c = [p - 1.25 for p in PSNR_A]
    assert bd_psnr(RATE_A, PSNR_A, RATE_A, psnr_c) == pytest.approx(-1.25, abs=1e-12)


def test_hand_integrated_bd_psnr():
    # x = log10 R = 0, 1, 2 (R = 1, 10, 100); A: D = 30, 31, 33; B: D = 31, 32, 33 (a line).
    # PCHIP slopes of A (h = 1, secants m0 = 1, m1 = 2):
    #   interior d1 = (w1 + w2) / (w1/m0 + w2/m1), w1 = w2 = 3  -> 6 / (3 + 1.5) = 4/3
    #   ends     d0 = ((2h0+h1) m0 - h0 m1) / (h0+h1) = (3 - 2)/2 = 1/2,
    #            d2 = ((2h1+h0) m1 - h1 m0) / (h0+h1) = (6 - 1)/2 = 5/2
    # A cubic Hermite piece integrates to h (y0+y1)/2 + h^2 (d0-d1)/12:
    #   [0,1]: (30+31)/2 + (1/2 - 4/3)/12 = 30.5 - 5/72
    #   [1,2]: (31+33)/2 + (4/3 - 5/2)/12 = 32 - 7/72          -> int_A = 62.5 - 12/72 = 62.5 - 1/6
    # B is linear (PCHIP reproduces lines): int_B = 2 * 32 = 64.
    # BD-PSNR = (int_B - int_A) / 2 = (64 - 62.5 + 1/6) / 2 = 5/6 dB.
    rate = [1.0, 10.0, 100.0]
    assert bd_psnr(rate, [30.0, 31.0, 33.0], rate, [31.0, 32.0, 33.0]) == pytest.approx(5 / 6, abs=1e-12)


def test_hand_integrated_bd_rate_partial_overlap():
    # A: log10 R = 0.1 (D - 30) at D = 30, 32, 34, 36; B: log10 R = 0.15 (D - 31) at D = 31..37.
    # Both are lines (PCHIP reproduces them). Overlap in PSNR: [31, 36].
    # Difference 0.15 (D - 31) - 0.1 (D - 30) = 0.05 D - 1.65; its mean over [31, 36] is
    # 0.05 * 33.5 - 1.65 = 0.025 -> BD-rate = (10^0.025 - 1) * 100 %.
    da = np.array([30.0, 32.0, 34.0, 36.0])
    db = np.array([31.0, 33.0, 35.0, 37.0])
    ra = 10 ** (0.1 * (da - 30))
    rb = 10 ** (0.15 * (db - 31))
    assert bd_rate(ra, da, rb, db) == pytest.approx((10 ** 0.025 - 1) * 100, abs=1e-9)


def test_point_order_does_not_matter():
    rate_b = [1.1, 2.5, 3.9, 9.0]
    psnr_b = [28.5, 30.2, 31.4, 32.9]
    ref = bd_rate(RATE_A, PSNR_A, rate_b, psnr_b)
    perm = [2, 0, 3, 1]
    got = bd_rate([RATE_A[i] for i in perm], [PSNR_A[i] for i in perm],
                  [rate_b[i] for i in perm], [psnr_b[i] for i in perm])
    assert got == pytest.approx(ref, abs=1e-12)
    assert math.isfinite(bd_psnr(RATE_A, PSNR_A, rate_b, psnr_b))


def test_bad_curves_are_refused():
    with pytest.raises(BDError, match="overlap"):
        bd_rate([1, 2, 3], [20, 21, 22], [1, 2, 3], [30, 31, 32])
    with pytest.raises(BDError, match="at least 2"):
        bd_psnr([1], [30], [1, 2], [30, 31])
    with pytest.raises(BDError, match="same abscissa"):
        bd_rate([1, 2, 3], [30, 30, 31], [1, 2, 3], [30, 31, 32])
    with pytest.raises(BDError, match="positive"):
        bd_psnr([0, 2, 3], [30, 31, 32], [1, 2, 3], [30, 31, 32])


def test_overlap_is_the_common_interval_and_its_share_of_the_wider_span():
    from baseline.eval.bdrate import overlap

    assert overlap([30, 32, 34], [31, 33, 35, 40]) == pytest.approx((31.0, 34.0, 3.0 / 9.0))
    assert overlap([30, 31], [29, 35]) == pytest.approx((30.0, 31.0, 1.0 / 6.0))   # one inside the other
    assert overlap([30, 31], [32, 33])[2] == 0.0                           # disjoint
    assert overlap([30, 31, 32], [32, 33, 34])[2] == 0.0                   # touching only


def test_non_monotone_names_points_without_more_psnr_than_a_smaller_one():
    from baseline.eval.bdrate import non_monotone

    assert non_monotone([1, 2, 3], [30, 31, 32]) == []
    assert non_monotone([3, 1, 2], [32, 30, 31]) == []                      # order given
    # truck HAC seed 0 at 6k: 0.002 and 0.001 below the 0.004 point
    assert non_monotone([4.010, 4.652, 5.274], [26.375, 26.352, 26.355]) == [1, 2]
    assert non_monotone([1, 2, 3], [30, 30, 31]) == [1]                     # equal counts


def test_readings_interpolate_log_rate_on_the_rising_envelope():
    import math

    from baseline.eval.bdrate import psnr_at_rate, rate_at_psnr, rising_envelope

    rate, psnr = [5.0, 10.0, 7.0, 8.0], [25.1, 27.0, 26.2, 26.0]    # 8.0 does not rise: left out
    assert rising_envelope(rate, psnr) == [0, 2, 1]
    # at a curve point: that point's rate and PSNR exactly
    assert rate_at_psnr(rate, psnr, 26.2) == pytest.approx(7.0)
    assert psnr_at_rate(rate, psnr, 7.0) == pytest.approx(26.2)
    # between two points: linear in log-rate, by hand
    t = (26.6 - 26.2) / (27.0 - 26.2)
    assert rate_at_psnr(rate, psnr, 26.6) == pytest.approx(math.exp(
        math.log(7.0) + t * (math.log(10.0) - math.log(7.0))))
    u = math.log(5.6 / 5.0) / math.log(7.0 / 5.0)
    assert psnr_at_rate(rate, psnr, 5.6) == pytest.approx(25.1 + u * (26.2 - 25.1))
    # the 8.0 point (26.0 dB) would have bent the curve between 7 and 10: it is not used
    assert psnr_at_rate(rate, psnr, 8.0) > 26.2
    # never extrapolated; fewer than two envelope points read nothing
    assert rate_at_psnr(rate, psnr, 27.5) is None and psnr_at_rate(rate, psnr, 4.0) is None
    assert rate_at_psnr([1.0, 2.0], [30.0, 29.0], 30.0) is None
    assert psnr_at_rate([1.0], [30.0], 1.0) is None
