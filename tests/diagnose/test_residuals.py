"""Tests of torchcf.residuals: calibration under the null, power, scipy and
statsmodels references."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchcf.diagnose.signatures import residuals as rs

DT = 0.1


def _ar1(rng: np.random.Generator, n: int, phi: float, sd: float = 1.0) -> np.ndarray:
    e = rng.normal(0.0, sd, n)
    x = np.empty(n)
    x[0] = e[0] / math.sqrt(1 - phi * phi)
    for t in range(1, n):
        x[t] = phi * x[t - 1] + e[t]
    return x


def _speed(rng: np.random.Generator, n: int) -> np.ndarray:
    """Smooth speed profile in roughly [5, 30] m/s."""
    return 17.5 + 12.5 * np.tanh(_ar1(rng, n, 0.995, 0.1) / 1.0)


def _all_tests(rng: np.random.Generator, n: int = 400, n_pairs: int = 2):
    res = [rng.normal(size=n) for _ in range(n_pairs)]
    v = [_speed(rng, n) for _ in range(n_pairs)]
    dv = [_ar1(rng, n, 0.9) for _ in range(n_pairs)]
    drv = [rng.normal(size=n) for _ in range(n_pairs)]
    return [
        rs.ljung_box(res, lags=10),
        rs.cross_correlation(res, drv, DT, 3.0),
        rs.speed_dependence(res, v),
        rs.asymmetry(res, dv),
        rs.spacing_dependence(res, [20 + 2 * x for x in v]),
        rs.position_dependence(res, [np.cumsum(x) * DT for x in v]),
        rs.drift(res, DT),
    ]


# ---------------------------------------------------------------- (a) null


def test_white_noise_not_significant() -> None:
    for r in _all_tests(np.random.default_rng(1)):
        assert r.p_value > 0.01, r.name
        assert r.per_pair is not None and len(r.per_pair) == 2


def test_null_p_values_roughly_uniform() -> None:
    rng = np.random.default_rng(2024)
    p = np.array([[r.p_value for r in _all_tests(rng)] for _ in range(200)])  # (200, 7)
    frac = (p < 0.05).mean(axis=0)
    names = [r.name for r in _all_tests(rng)]
    for name, f in zip(names, frac, strict=True):
        assert 0.01 <= f <= 0.12, (name, f)
    assert np.all((p >= 0) & (p <= 1))


# ---------------------------------------------------------------- (b)-(d) power


def test_ljung_box_ar1() -> None:
    x = _ar1(np.random.default_rng(3), 2000, 0.8)
    r = rs.ljung_box(x, lags=10)
    assert r.p_value < 1e-6
    assert r.effect == pytest.approx(0.8, abs=0.05)
    assert r.dof == 10 and r.n == 2000


def test_cross_correlation_finds_lag() -> None:
    rng = np.random.default_rng(4)
    lag = 10  # 1.0 s at dt = 0.1
    res, drv = [], []
    for _ in range(3):
        u = _ar1(rng, 2000 + lag, 0.5)
        res.append(0.5 * u[:-lag] + rng.normal(size=2000))  # e(t) = 0.5 u(t - 1 s) + w
        drv.append(u[lag:])
    r = rs.cross_correlation(res, drv, DT, max_lag_s=3.0)
    assert r.details["best_lag_s"] == pytest.approx(1.0, abs=1e-12)
    assert int(np.argmax(np.abs(r.details["curve"]))) == lag
    assert r.p_value < 1e-6
    assert r.details["n_lags"] == 31 and len(r.details["curve"]) == 31
    assert r.p_value == pytest.approx(min(1.0, 31 * r.details["p_unadjusted"]))
    assert r.effect > 0.3
    assert all(p.details["best_lag_s"] == pytest.approx(1.0) for p in r.per_pair)


def test_speed_dependence_recovers_coefficients() -> None:
    rng = np.random.default_rng(5)
    v = [_speed(rng, 3000) for _ in range(10)]
    res = [0.3 + 0.02 * x**2 + rng.normal(0, 0.2, x.size) for x in v]
    r = rs.speed_dependence(res, v)
    assert r.p_value < 1e-6 and r.dof == 2
    assert r.effect["v2"] == pytest.approx(0.02, rel=0.1)
    assert r.details["intercept"] == pytest.approx(0.3, rel=0.1)
    assert abs(r.effect["v"]) < 0.01
    assert 0.5 < r.effect["delta_r2"] <= 1.0


def test_asymmetry_detected_and_symmetric_slope_not() -> None:
    rng = np.random.default_rng(6)
    dv = [_ar1(rng, 3000, 0.9) for _ in range(4)]
    sym = [0.4 * d + rng.normal(0, 0.5, d.size) for d in dv]
    asym = [np.where(d < 0, 0.8, 0.2) * d + rng.normal(0, 0.5, d.size) for d in dv]
    assert rs.asymmetry(sym, dv).p_value > 0.01
    r = rs.asymmetry(asym, dv)
    assert r.p_value < 1e-6
    assert r.effect["dv_neg"] == pytest.approx(0.6, abs=0.1)


def test_drift_detected() -> None:
    rng = np.random.default_rng(7)
    res = [0.01 * np.arange(2000) * DT + _ar1(rng, 2000, 0.5) for _ in range(3)]
    r = rs.drift(res, DT)
    assert r.p_value < 1e-6
    assert r.effect["t"] == pytest.approx(0.01, rel=0.1)


def test_cross_correlation_bartlett_keeps_size() -> None:
    """Independent but persistent series: the iid Fisher test rejects far too often."""
    rng = np.random.default_rng(18)
    p_adj, p_iid = [], []
    for _ in range(60):
        e = [_ar1(rng, 1000, 0.9) for _ in range(2)]
        u = [_ar1(rng, 1000, 0.99) for _ in range(2)]
        p_adj.append(rs.cross_correlation(e, u, DT).p_value)
        p_iid.append(rs.cross_correlation(e, u, DT, bartlett=False).p_value)
    assert np.mean(np.array(p_adj) < 0.05) <= 0.12
    assert np.mean(np.array(p_iid) < 0.05) > 0.3


# ---------------------------------------------------------------- (e) references


def test_chi2_sf_matches_scipy() -> None:
    for k in [1, 2, 3, 5, 10, 31, 100, 1000, 20000]:
        for x in np.concatenate([np.linspace(0.01, 3 * k + 30, 25), [k, 0.5 * k]]):
            assert rs.chi2_sf(float(x), k) == pytest.approx(
                stats.chi2.sf(x, k), abs=1e-10, rel=1e-8
            ), (x, k)
    assert rs.chi2_sf(0.0, 3) == 1.0
    assert rs.norm_sf(1.96) == pytest.approx(stats.norm.sf(1.96), abs=1e-14)


def test_ljung_box_matches_direct_numpy() -> None:
    x = np.random.default_rng(8).normal(size=300)
    h, n = 7, x.size
    d = x - x.mean()
    q = 0.0
    for k in range(1, h + 1):
        r_k = np.sum(d[k:] * d[:-k]) / np.sum(d * d)
        q += r_k**2 / (n - k)
    q *= n * (n + 2)
    r = rs.ljung_box(x, lags=h)
    assert r.statistic == pytest.approx(q, rel=1e-12)
    assert r.p_value == pytest.approx(stats.chi2.sf(q, h), abs=1e-10)
    # Pooling adds Q and dof over independent pairs.
    y = np.random.default_rng(9).normal(size=200)
    both = rs.ljung_box([x, y], lags=h)
    assert both.statistic == pytest.approx(q + rs.ljung_box(y, lags=h).statistic)
    assert both.dof == 2 * h


def test_ols_matches_lstsq() -> None:
    rng = np.random.default_rng(10)
    a, b = (
        [rng.normal(size=150) for _ in range(2)],
        [rng.normal(size=150) for _ in range(2)],
    )
    y = [
        1.0 + 0.5 * p - 0.2 * q + rng.normal(size=150)
        for p, q in zip(a, b, strict=True)
    ]
    r = rs.regression_test(y, {"a": a, "b": b})
    x = np.column_stack([np.ones(300), np.concatenate(a), np.concatenate(b)])
    beta = np.linalg.lstsq(x, np.concatenate(y), rcond=None)[0]
    assert r.details["intercept"] == pytest.approx(beta[0], rel=1e-10)
    assert [r.effect["a"], r.effect["b"]] == pytest.approx(beta[1:], rel=1e-10)
    u = np.concatenate(y) - x @ beta
    yc = np.concatenate(y) - np.mean(np.concatenate(y))
    assert r.effect["delta_r2"] == pytest.approx(1 - (u @ u) / (yc @ yc), rel=1e-10)


def test_newey_west_matches_loop() -> None:
    rng = np.random.default_rng(11)
    n, bw = 40, 3
    x = np.column_stack([np.ones(n), rng.normal(size=n), rng.normal(size=n)])
    u = _ar1(rng, n, 0.6)
    s = np.zeros((3, 3))
    for t in range(n):
        s += u[t] ** 2 * np.outer(x[t], x[t])
    for lag in range(1, bw + 1):
        w = 1 - lag / (bw + 1)
        for t in range(lag, n):
            g = u[t] * u[t - lag] * np.outer(x[t], x[t - lag])
            s += w * (g + g.T)
    xtx_inv = np.linalg.inv(x.T @ x)
    ref = xtx_inv @ s @ xtx_inv
    np.testing.assert_allclose(rs.newey_west_cov(x, u, bw), ref, rtol=1e-12)
    assert rs.newey_west_bandwidth(100) == 4
    assert rs.newey_west_bandwidth(2000) == 7


def test_wald_uses_hac_covariance() -> None:
    rng = np.random.default_rng(12)
    n = 500
    t = np.arange(n) * DT
    e = _ar1(rng, n, 0.7)
    r = rs.regression_test(e, {"t": t}, "t", bandwidth=5)
    x = np.column_stack([np.ones(n), t])
    beta = np.linalg.lstsq(x, e, rcond=None)[0]
    cov = rs.newey_west_cov(x, e - x @ beta, 5)
    assert r.statistic == pytest.approx(beta[1] ** 2 / cov[1, 1], rel=1e-10)


def test_ljung_box_matches_statsmodels() -> None:
    sm_diag = pytest.importorskip("statsmodels.stats.diagnostic")
    x = _ar1(np.random.default_rng(14), 400, 0.3)
    for h in (1, 5, 12):
        ours = rs.ljung_box(x, lags=h)
        theirs = sm_diag.acorr_ljungbox(x, lags=[h])
        q, p = (float(theirs[k].iloc[0]) for k in ("lb_stat", "lb_pvalue"))
        assert ours.statistic == pytest.approx(q, rel=1e-10)
        assert ours.p_value == pytest.approx(p, abs=1e-12)


def test_newey_west_and_wald_match_statsmodels() -> None:
    sm = pytest.importorskip("statsmodels.api")
    rng = np.random.default_rng(15)
    n = 600
    v = _speed(rng, n)
    e = 0.02 * (v - 17.5) + _ar1(rng, n, 0.8, 0.3)
    x = sm.add_constant(v)
    for bw in (None, 3, 12):
        lags = rs.newey_west_bandwidth(n) if bw is None else bw
        fit = sm.OLS(e, x).fit(
            cov_type="HAC", cov_kwds={"maxlags": lags, "use_correction": False}
        )
        u = e - x @ fit.params
        ours_cov = rs.newey_west_cov(x, u, lags)
        np.testing.assert_allclose(ours_cov, fit.cov_params(), rtol=1e-10)
        ours = rs.regression_test(e, {"v": v}, "v", bandwidth=bw)
        wald = fit.wald_test(np.array([[0.0, 1.0]]), use_f=False, scalar=True)
        assert ours.statistic == pytest.approx(float(wald.statistic), rel=1e-10)
        assert ours.p_value == pytest.approx(float(wald.pvalue), rel=1e-8, abs=1e-14)


def test_pooled_hac_matches_statsmodels_panel_hac() -> None:
    """Pairs pooled with one intercept and per-pair Newey-West meats summed is
    statsmodels' ``hac-panel`` covariance with the pairs as groups."""
    sm = pytest.importorskip("statsmodels.api")
    rng = np.random.default_rng(16)
    n, pairs, bw = 300, 3, 6
    v = [_speed(rng, n) for _ in range(pairs)]
    e = [0.01 * (x - 17.5) + _ar1(rng, n, 0.7, 0.2) for x in v]
    ours = rs.regression_test(e, {"v": v}, "v", bandwidth=bw)
    x = sm.add_constant(np.concatenate(v))
    fit = sm.OLS(np.concatenate(e), x).fit(
        cov_type="hac-panel",
        cov_kwds={
            "groups": np.repeat(np.arange(pairs), n),
            "maxlags": bw,
            "use_correction": False,
        },
    )
    assert ours.effect["v"] == pytest.approx(float(fit.params[1]), rel=1e-10)
    wald = fit.wald_test(np.array([[0.0, 1.0]]), use_f=False, scalar=True)
    assert ours.statistic == pytest.approx(float(wald.statistic), rel=1e-10)


# ---------------------------------------------------------------- (f) edge cases


def test_input_forms_agree() -> None:
    rng = np.random.default_rng(13)
    arr = rng.normal(size=(200, 3))  # (T, N)
    cols = [arr[:, j] for j in range(3)]
    a = rs.ljung_box(arr, lags=5)
    b = rs.ljung_box(cols, lags=5)
    c = rs.ljung_box([torch.from_numpy(x).float() for x in cols], lags=5)
    assert a.statistic == b.statistic
    assert c.statistic == pytest.approx(b.statistic, rel=1e-5)


def test_constant_series() -> None:
    const = np.full(300, 2.5)
    v = np.linspace(5, 30, 300)
    for r in [
        rs.ljung_box(const),
        rs.cross_correlation(const, v, DT),
        rs.cross_correlation(v, const, DT),
        rs.speed_dependence(const, v),
        rs.drift(const, DT),
    ]:
        assert r.p_value == 1.0, r.name
        eff = (
            r.effect
            if isinstance(r.effect, float)
            else max(map(abs, r.effect.values()))
        )
        assert eff == 0.0
    # A constant pair is excluded from the pooled Ljung-Box, not counted as white.
    x = np.random.default_rng(14).normal(size=300)
    pooled = rs.ljung_box([x, const], lags=5)
    assert pooled.statistic == rs.ljung_box(x, lags=5).statistic and pooled.dof == 5
    assert pooled.per_pair[1].note == "constant series"


def test_nan_dropped_and_counted() -> None:
    rng = np.random.default_rng(15)
    x = rng.normal(size=500)
    v = _speed(rng, 500)
    x[[3, 50, 51]] = np.nan
    v[100] = np.nan
    r = rs.ljung_box(x, lags=5)
    assert r.n == 497 and r.n_dropped == 3 and math.isfinite(r.p_value)
    s = rs.speed_dependence(x, v)
    assert s.n == 496 and s.n_dropped == 4 and math.isfinite(s.statistic)
    c = rs.cross_correlation(x, v, DT, 1.0)
    assert c.n == 496 and c.n_dropped == 4 and math.isfinite(c.statistic)
    a = rs.asymmetry(x, v - 17.0)
    assert a.n == 496 and math.isfinite(a.statistic)


def test_short_series_skipped() -> None:
    rng = np.random.default_rng(16)
    long, short = rng.normal(size=300), rng.normal(size=8)
    r = rs.ljung_box([long, short], lags=10)
    assert r.per_pair[1].note.startswith("skipped") and math.isnan(
        r.per_pair[1].p_value
    )
    assert r.n == 300 and r.dof == 10
    alone = rs.ljung_box(short, lags=10)
    assert math.isnan(alone.p_value) and "long enough" in alone.note
    c = rs.cross_correlation(short, short, DT, 3.0)
    assert math.isnan(c.p_value) and c.per_pair[0].note.startswith("skipped")
    g = rs.speed_dependence(rng.normal(size=3), rng.normal(size=3))
    assert math.isnan(g.p_value) and g.per_pair[0].note.startswith("skipped")


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        rs.ljung_box(np.zeros(10), lags=0)
    with pytest.raises(ValueError):
        rs.regression_test(np.zeros(10), {"a": np.zeros(10)}, test=["b"])
    with pytest.raises(ValueError):
        rs.regression_test([np.zeros(10)], {"a": [np.zeros(9)]})


def test_summarize_sorted_and_json() -> None:
    rng = np.random.default_rng(17)
    results = _all_tests(rng) + [rs.ljung_box(_ar1(rng, 1000, 0.8)), rs.ljung_box([])]
    rows = rs.summarize(results, include_pairs=True)
    json.dumps(rows, allow_nan=False)  # strict JSON: NaN became None
    p = [row["p_value"] for row in rows]
    finite = [x for x in p if x is not None]
    assert finite == sorted(finite) and p[: len(finite)] == finite
    assert rows[0]["name"] == "ljung_box" and rows[-1]["p_value"] is None
    assert len(rs.summarize(results)) == len(results)


def test_lap_dependence_finds_a_wave_round_a_closed_track() -> None:
    """Pairs driving many laps of a 900 m track with a grade-like residual
    ``0.05 sin(2 pi s / C)`` on AR(1) noise: the lap's harmonic finds it and the
    linear trend in the odometer does not; on noise alone neither fires, and a
    wave of another phase is found all the same (both harmonics are tested)."""
    rng = np.random.default_rng(7)
    lap = 900.0
    x = [rng.uniform(0, 5 * lap) + 15.0 * DT * np.arange(2000) for _ in range(20)]
    noise = [0.3 * _ar1(rng, 2000, 0.8) for _ in x]
    wave = [
        0.05 * np.sin(2 * math.pi * p / lap) + n for p, n in zip(x, noise, strict=True)
    ]
    shifted = [
        0.05 * np.cos(2 * math.pi * p / lap) + n for p, n in zip(x, noise, strict=True)
    ]
    assert rs.lap_dependence(wave, x, lap).p_value < 1e-6
    assert rs.lap_dependence(shifted, x, lap).p_value < 0.01
    assert rs.position_dependence(wave, x).p_value > 0.01
    assert rs.lap_dependence(noise, x, lap).p_value > 0.01
    with pytest.raises(ValueError, match="lap length"):
        rs.lap_dependence(wave, x, 0.0)
