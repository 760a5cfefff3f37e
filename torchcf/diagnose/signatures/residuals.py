"""Statistical tests for structure in car-following residual series.

A residual series is ``e(t) = observed(t) - simulated(t)`` for one follower (spacing,
speed or acceleration, any unit), sampled every ``dt`` seconds. A well specified model
leaves residuals with no structure; each test here looks for one kind of structure and
names the model change it points to:

- :func:`ljung_box`: serial correlation (missing dynamics / state, reaction delay);
- :func:`cross_correlation`: dependence on a lagged driver such as the leader's speed
  (a reaction time the model lacks);
- :func:`regression_test` and its wrappers :func:`speed_dependence`,
  :func:`asymmetry`, :func:`spacing_dependence`, :func:`position_dependence`,
  :func:`drift`: dependence of the residual level on a covariate;
- :func:`summarize`: JSON-able rows sorted by p-value.

**Inputs.** Every series argument is one of: a 1-D array or tensor (one pair), a list
of 1-D arrays or tensors (one per pair, lengths may differ), or a 2-D ``(T, N)`` array
(time-major, NaN-padded). Everything is converted to float64 numpy. Pairs are treated
as independent, so pooled statistics add up per-pair information.

**Missing values.** NaN samples are dropped per pair (for tests on several series, a
time step is dropped when any of them is NaN) and the count is reported as
``n_dropped``. Dropping splices the series, which is harmless for a few isolated NaN
but shortens lags across long gaps.

**Degenerate input.** A pair with zero variance carries no information: it gets
``p_value = 1`` and a zero effect and is left out of the pooled statistic. A pair too
short for the test is skipped with the reason in ``note``.

P-values need no scipy: the chi-square survival function is the regularized upper
incomplete gamma ``Q(k/2, x/2)`` (``torch.special.gammaincc``) and the normal one is
``erfc``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ...system.files import JSON

__all__ = [
    "TestResult",
    "asymmetry",
    "chi2_sf",
    "cross_correlation",
    "drift",
    "ljung_box",
    "newey_west_bandwidth",
    "newey_west_cov",
    "norm_sf",
    "lap_dependence",
    "position_dependence",
    "regression_test",
    "spacing_dependence",
    "speed_dependence",
    "summarize",
]

#: Relative variance below which a series is called constant (rounding noise only).
_CONST_RTOL = 1e-24


@dataclass(frozen=True)
class TestResult:
    """Outcome of one test, pooled over pairs, with the per-pair outcomes.

    Attributes:
        name: test name, ``"<test>"`` pooled or ``"<test>[pair i]"`` per pair.
        statistic: the test statistic (chi-square for Ljung-Box and Wald, standard
            normal z for the cross-correlation).
        p_value: p-value in [0, 1]; NaN when the test could not run (see ``note``).
        effect: effect size, its meaning given by each test (a float, or a dict of
            floats for regressions).
        n: samples used (after dropping NaN; summed over pairs when pooled).
        dof: chi-square degrees of freedom (0 for a z-test or no test).
        n_dropped: NaN samples dropped.
        per_pair: per-pair results (``None`` on a per-pair result).
        note: why a pair was skipped or the result is degenerate; "" otherwise.
        details: test-specific extras (lags, curves, intercept, ...).
    """

    __test__ = False  # not a pytest test class despite its name

    name: str
    statistic: float
    p_value: float
    effect: float | dict[str, float]
    n: int
    dof: int = 0
    n_dropped: int = 0
    per_pair: list[TestResult] | None = None
    note: str = ""
    details: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------- distributions


def chi2_sf(x: float, dof: float) -> float:
    """Chi-square survival function ``P(X > x)`` with ``dof`` degrees of freedom.

    ``sf(x; k) = Q(k/2, x/2)``, the regularized upper incomplete gamma function.

    Args:
        x: statistic (>= 0).
        dof: degrees of freedom (> 0); ``dof <= 0`` means no test and gives 1.

    Returns:
        The p-value as a Python float.
    """
    if dof <= 0 or not x > 0.0:  # `not x > 0` also catches NaN -> no evidence
        return 1.0 if not math.isnan(x) else float("nan")
    a = torch.tensor(0.5 * dof, dtype=torch.float64)
    return float(torch.special.gammaincc(a, torch.tensor(0.5 * x, dtype=torch.float64)))


def norm_sf(z: float) -> float:
    """Standard normal survival function ``P(Z > z) = erfc(z / sqrt(2)) / 2``."""
    return 0.5 * math.erfc(z / math.sqrt(2.0))


# ---------------------------------------------------------------- input handling


def _to_numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _as_pairs(series: Any) -> list[np.ndarray]:
    """Normalize a series argument to a list of 1-D float64 arrays, one per pair."""
    if isinstance(series, list | tuple):
        out = [_to_numpy(s).ravel() for s in series]
    else:
        arr = _to_numpy(series)
        if arr.ndim == 1:
            out = [arr]
        elif arr.ndim == 2:  # (T, N) time-major
            out = [arr[:, j] for j in range(arr.shape[1])]
        else:
            raise ValueError(f"expected 1-D, (T, N) or a list of 1-D, got {arr.shape}")
    return out


def _aligned(*args: list[np.ndarray]) -> list[tuple[list[np.ndarray], int]]:
    """Per pair: the series with rows containing any NaN dropped, and the count."""
    n_pairs = len(args[0])
    for a in args[1:]:
        if len(a) != n_pairs:
            raise ValueError(f"got {n_pairs} residual pairs but {len(a)} of another")
    out = []
    for j in range(n_pairs):
        cols = [a[j] for a in args]
        n = len(cols[0])
        if any(len(c) != n for c in cols):
            raise ValueError(
                f"pair {j}: series lengths differ {[len(c) for c in cols]}"
            )
        keep = np.all(np.isfinite(np.stack(cols)), axis=0) if n else np.ones(0, bool)
        out.append(([c[keep] for c in cols], int(n - keep.sum())))
    return out


def _is_constant(x: np.ndarray) -> bool:
    if x.size < 2:
        return True
    scale = max(float(np.mean(x * x)), 1e-300)
    return float(np.var(x)) <= _CONST_RTOL * scale


def _acf(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation ``r_k``, k = 0..max_lag (biased, sum over n - k terms).

    ``r_k = sum_{t=k}^{n-1} d_t d_{t-k} / sum_t d_t^2`` with ``d = x - mean(x)``.
    """
    d = x - x.mean()
    denom = float(d @ d)
    return np.array(
        [float(d[k:] @ d[: d.size - k]) / denom for k in range(max_lag + 1)]
    )


# ---------------------------------------------------------------- Ljung-Box


def ljung_box(series: Any, lags: int = 10) -> TestResult:
    """Ljung-Box portmanteau test of no serial correlation up to lag ``h = lags``.

    ``Q = n (n + 2) sum_{k=1}^{h} r_k^2 / (n - k)`` is chi-square with ``h`` dof under
    white noise (Ljung & Box 1978), ``r_k`` the lag-k sample autocorrelation. Pairs
    are independent, so the pooled statistic is the sum of per-pair ``Q`` with the sum
    of their dof.

    Args:
        series: residuals per pair (see module docstring), any unit.
        lags: number of lags ``h`` (>= 1), in samples.

    Returns:
        :class:`TestResult` with ``effect = r_1``, the lag-1 autocorrelation
        (dimensionless, in [-1, 1]); pooled, the ``n``-weighted mean of the pairs'
        ``r_1``. ``details["acf"]`` holds per pair ``r_1..r_h``.
    """
    if lags < 1:
        raise ValueError(f"lags must be >= 1, got {lags}")
    per_pair: list[TestResult] = []
    q_sum, dof_sum, n_sum, r1_num, dropped = 0.0, 0, 0, 0.0, 0
    for j, ((x,), n_drop) in enumerate(_aligned(_as_pairs(series))):
        name, n = f"ljung_box[pair {j}]", x.size
        dropped += n_drop
        if n < lags + 2:
            per_pair.append(
                TestResult(name, math.nan, math.nan, math.nan, n, 0, n_drop,
                           note=f"skipped: {n} samples < lags + 2 = {lags + 2}")
            )  # fmt: skip
            continue
        if _is_constant(x):
            per_pair.append(
                TestResult(name, 0.0, 1.0, 0.0, n, 0, n_drop, note="constant series")
            )
            continue
        r = _acf(x, lags)[1:]  # (h,)
        k = np.arange(1, lags + 1)
        q = float(n * (n + 2) * np.sum(r * r / (n - k)))
        per_pair.append(
            TestResult(name, q, chi2_sf(q, lags), float(r[0]), n, lags, n_drop,
                       details={"acf": r.tolist()})
        )  # fmt: skip
        q_sum, dof_sum, n_sum = q_sum + q, dof_sum + lags, n_sum + n
        r1_num += n * float(r[0])
    if dof_sum == 0:
        return _no_pooled("ljung_box", per_pair, dropped)
    return TestResult(
        "ljung_box", q_sum, chi2_sf(q_sum, dof_sum), r1_num / n_sum, n_sum, dof_sum,
        dropped, per_pair, details={"lags": lags},
    )  # fmt: skip


def _no_pooled(name: str, per_pair: list[TestResult], dropped: int) -> TestResult:
    """Pooled result when no pair was informative: constant -> p = 1, else skipped."""
    n = sum(r.n for r in per_pair)
    if any(r.p_value == 1.0 for r in per_pair):
        return TestResult(name, 0.0, 1.0, 0.0, n, 0, dropped, per_pair,
                          note="no informative pair (constant series)")  # fmt: skip
    return TestResult(name, math.nan, math.nan, math.nan, n, 0, dropped, per_pair,
                      note="no pair long enough for the test")  # fmt: skip


# ---------------------------------------------------------------- cross-correlation


def cross_correlation(
    residual: Any,
    driver: Any,
    dt: float,
    max_lag_s: float = 3.0,
    *,
    bartlett: bool = True,
) -> TestResult:
    """Lagged correlation of the residual with a driver, ``corr(e(t), u(t - lag))``.

    For each lag ``l = 0, dt, ..., max_lag_s`` and each pair, the Pearson correlation
    ``r`` of the aligned samples is Fisher-transformed, ``z = atanh(r)`` with variance
    ``1 / (n_eff - 3)``. The pooled correlation is the inverse-variance weighted mean
    ``z_bar = sum w z / sum w`` (``w = n_eff - 3``), tested by
    ``Z = z_bar sqrt(sum w) ~ N(0, 1)`` (two-sided), and reported as ``tanh(z_bar)``.

    ``n_eff``: the sample correlation of two independent but autocorrelated series
    has variance ``(1 + 2 sum_k rho_e(k) rho_u(k)) / n`` (Bartlett 1935), not
    ``1 / n``. Drivers such as speed are strongly autocorrelated and so are model
    residuals, so the naive test rejects far too often. With ``bartlett=True`` we
    use ``n_eff = n / max(1, 1 + 2 sum_{k=1}^{K} r_e(k) r_u(k))`` with
    ``K = floor(sqrt(n))`` and sample autocorrelations; the floor at 1 keeps the
    correction from ever making the test more liberal than the iid one. When either
    series is white the factor is ~1 and the test is asymptotically exact.

    **Multiple lags.** The best lag is the one with the largest ``|pooled r|``; its
    p-value is Bonferroni-corrected, ``p = min(1, n_lags * p_lag)``, because we pick
    the most extreme of ``n_lags`` correlated tests (conservative, valid whatever the
    dependence between lags). ``details["p_unadjusted"]`` keeps ``p_lag``.

    Args:
        residual: residuals per pair (see module docstring).
        driver: driver series per pair, same lengths (e.g. leader speed [m/s]).
        dt: sampling step [s].
        max_lag_s: largest lag tested [s]; lags are the multiples of ``dt`` up to it.
        bartlett: apply the effective-sample-size correction above.

    Returns:
        :class:`TestResult`: ``statistic`` the z at the best lag, ``effect`` the pooled
        correlation there (dimensionless). ``details``: ``best_lag_s`` [s],
        ``lags_s`` (L,) [s], ``curve`` (L,) pooled correlation per lag, ``z`` (L,),
        ``p_unadjusted``, ``n_lags``. Per-pair results use each pair's own best lag.
    """
    n_lag = int(math.floor(max_lag_s / dt + 1e-9)) + 1  # lags 0, dt, ... <= max_lag_s
    lags_s = np.arange(n_lag) * dt  # (L,)
    sum_w, sum_wz = np.zeros(n_lag), np.zeros(n_lag)  # (L,)
    per_pair: list[TestResult] = []
    dropped = n_used = 0
    for j, (e, u) in enumerate(
        zip(_as_pairs(residual), _as_pairs(driver), strict=True)
    ):
        name = f"cross_correlation[pair {j}]"
        if e.size != u.size:
            raise ValueError(f"pair {j}: residual {e.size} vs driver {u.size} samples")
        ok = np.isfinite(e) & np.isfinite(u)
        n_drop, n_ok = int(e.size - ok.sum()), int(ok.sum())
        dropped += n_drop
        # Fisher's variance needs n - 3 > 0 at the largest lag.
        if e.size - (n_lag - 1) < 5 or n_ok < n_lag + 4:
            per_pair.append(
                TestResult(name, math.nan, math.nan, math.nan, n_ok, 0, n_drop,
                           note=f"skipped: {n_ok} samples, need > {n_lag + 3} for "
                                f"{n_lag} lags")
            )  # fmt: skip
            continue
        if _is_constant(e[ok]) or _is_constant(u[ok]):
            per_pair.append(
                TestResult(name, 0.0, 1.0, 0.0, n_ok, 0, n_drop, note="constant series")
            )
            continue
        infl = 1.0
        if bartlett:
            # Autocorrelations on the NaN-free samples; K ~ sqrt(n) trades bias
            # (truncating slow decays) against noise of the summed products.
            k_max = min(int(math.isqrt(n_ok)), n_ok - 2)
            infl = max(
                1.0, 1.0 + 2.0 * float(_acf(e[ok], k_max)[1:] @ _acf(u[ok], k_max)[1:])
            )
        z_pair, w_pair = np.zeros(n_lag), np.zeros(n_lag)
        for lag in range(n_lag):
            a, b = e[lag:], u[: u.size - lag]  # e(t) against u(t - lag)
            m = np.isfinite(a) & np.isfinite(b)
            a, b = a[m], b[m]
            if a.size < 5 or _is_constant(a) or _is_constant(b):
                continue
            r = float(np.corrcoef(a, b)[0, 1])
            w = max(a.size / infl - 3.0, 0.0)
            z_pair[lag] = math.atanh(min(max(r, -1 + 1e-15), 1 - 1e-15))
            w_pair[lag] = w
        sum_w += w_pair
        sum_wz += w_pair * z_pair
        n_used += n_ok
        zs = z_pair * np.sqrt(w_pair)
        best = int(np.argmax(np.abs(z_pair)))
        p_raw = 2.0 * norm_sf(abs(zs[best]))
        per_pair.append(
            TestResult(name, float(zs[best]), min(1.0, n_lag * p_raw),
                       math.tanh(z_pair[best]), n_ok, 0, n_drop,
                       details={"best_lag_s": float(lags_s[best]),
                                "curve": np.tanh(z_pair).tolist(),
                                "p_unadjusted": p_raw, "n_eff_factor": infl})
        )  # fmt: skip
    if not np.any(sum_w > 0):
        return _no_pooled("cross_correlation", per_pair, dropped)
    z_bar = np.divide(sum_wz, sum_w, out=np.zeros(n_lag), where=sum_w > 0)  # (L,)
    z_stat = z_bar * np.sqrt(sum_w)  # (L,)
    curve = np.tanh(z_bar)  # (L,)
    best = int(np.argmax(np.abs(curve)))
    p_raw = 2.0 * norm_sf(abs(float(z_stat[best])))
    return TestResult(
        "cross_correlation", float(z_stat[best]), min(1.0, n_lag * p_raw),
        float(curve[best]), n_used, 0, dropped, per_pair,
        details={"best_lag_s": float(lags_s[best]), "lags_s": lags_s,
                 "curve": curve, "z": z_stat, "p_unadjusted": p_raw,
                 "n_lags": n_lag, "bartlett": bartlett},
    )  # fmt: skip


# ---------------------------------------------------------------- regression


def newey_west_bandwidth(n: int) -> int:
    """Newey & West (1994) rule of thumb ``floor(4 (n / 100)^(2/9))`` [samples]."""
    return int(math.floor(4.0 * (n / 100.0) ** (2.0 / 9.0)))


def _nw_meat(xu: np.ndarray, bandwidth: int) -> np.ndarray:
    """Newey-West meat ``S = G_0 + sum_{l=1}^{L} (1 - l/(L+1)) (G_l + G_l')``.

    ``G_l = sum_t x_t u_t u_{t-l} x_{t-l}'`` (Bartlett kernel, so ``S`` is PSD).

    Args:
        xu: (n, p) rows ``x_t u_t`` of one pair, in time order.
        bandwidth: ``L`` [samples].
    """
    s = xu.T @ xu  # (p, p)
    for lag in range(1, min(bandwidth, xu.shape[0] - 1) + 1):
        g = xu[lag:].T @ xu[:-lag]  # (p, p)
        s += (1.0 - lag / (bandwidth + 1.0)) * (g + g.T)
    return s


def newey_west_cov(
    x: np.ndarray, u: np.ndarray, bandwidth: int | None = None
) -> np.ndarray:
    """Newey-West HAC covariance of OLS coefficients for one series.

    ``V = (X'X)^-1 S (X'X)^-1`` with ``S`` the Bartlett-weighted sum of lagged
    score cross-products (see :func:`_nw_meat`); no small-sample correction.

    Args:
        x: (n, p) design matrix, rows in time order.
        u: (n,) OLS residuals.
        bandwidth: ``L`` [samples]; default :func:`newey_west_bandwidth` of n.

    Returns:
        (p, p) covariance.
    """
    bw = newey_west_bandwidth(x.shape[0]) if bandwidth is None else bandwidth
    bread = np.linalg.inv(x.T @ x)
    return bread @ _nw_meat(x * u[:, None], bw) @ bread


def _ols_wald(
    blocks: list[tuple[np.ndarray, np.ndarray]],
    names: list[str],
    tested: list[int],
    bandwidth: int | None,
) -> tuple[float, int, dict[str, float], float, float, str]:
    """Pooled OLS with per-pair HAC meats; Wald test of ``beta[tested] = 0``.

    Returns:
        (W, dof, coefficients by name, intercept, delta R^2, note).
    """
    x = np.concatenate([b[0] for b in blocks])  # (n, p)
    y = np.concatenate([b[1] for b in blocks])  # (n,)
    zero = {nm: 0.0 for nm in names}
    if _is_constant(y):
        return 0.0, len(tested), zero, float(y.mean()), 0.0, "constant series"
    if np.linalg.matrix_rank(x) < x.shape[1]:
        return 0.0, len(tested), zero, float(y.mean()), 0.0, "collinear regressors"
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)  # (p,)
    u = y - x @ beta
    # Pairs are independent, so cross-pair lag products are zero in expectation:
    # sum the per-pair meats instead of lagging across pair boundaries.
    meat = np.zeros((x.shape[1], x.shape[1]))
    start = 0
    for xb, _ in blocks:
        nb = xb.shape[0]
        bw = newey_west_bandwidth(nb) if bandwidth is None else bandwidth
        meat += _nw_meat(xb * u[start : start + nb, None], bw)
        start += nb
    bread = np.linalg.inv(x.T @ x)
    cov = bread @ meat @ bread  # (p, p)
    b_t = beta[tested]
    v_t = cov[np.ix_(tested, tested)]
    wald = float(b_t @ np.linalg.lstsq(v_t, b_t, rcond=None)[0])
    # Restricted fit: every column except the tested ones (always has the intercept).
    keep = [i for i in range(x.shape[1]) if i not in tested]
    u0 = y - x[:, keep] @ np.linalg.lstsq(x[:, keep], y, rcond=None)[0]
    sst = float(np.sum((y - y.mean()) ** 2))
    d_r2 = float((u0 @ u0 - u @ u) / sst)
    coefs = {nm: float(beta[i + 1]) for i, nm in enumerate(names)}
    return wald, len(tested), coefs, float(beta[0]), d_r2, ""


def regression_test(
    residual: Any,
    regressors: Mapping[str, Any],
    name: str = "regression",
    *,
    test: Sequence[str] | None = None,
    bandwidth: int | None = None,
) -> TestResult:
    """OLS of the residual on an intercept and regressors, HAC Wald test of zero slopes.

    ``e_t = b_0 + sum_j b_j x_{j,t} + u_t``, fitted by ordinary least squares pooled
    over pairs (one common intercept) and per pair. ``H0: b_j = 0`` for every ``j`` in
    ``test`` is tested by ``W = b_T' V_TT^-1 b_T ~ chi2(|T|)``.

    **Why HAC.** Residual series are autocorrelated (a model error persists for
    seconds) and so are the regressors (speed, spacing, position, time). The usual
    OLS covariance ``s^2 (X'X)^-1`` assumes independent errors and then understates
    the slopes' variance by a factor up to ``(1 + rho_e rho_x) / (1 - rho_e rho_x)``
    for AR(1) series, which turns any spurious drift into a "significant" effect.
    Newey-West (1987) covariance ``V = (X'X)^-1 S (X'X)^-1`` with Bartlett weights
    ``1 - l / (L + 1)`` and ``L = floor(4 (n / 100)^(2/9))`` (Newey & West 1994;
    per pair, pairs being independent, their ``S`` summed) stays consistent under
    both autocorrelation and heteroscedasticity. With this short bandwidth it is
    still liberal for very persistent series: for two pairs of n = 1000, an AR(1)
    regressor with phi = 0.99 and an independent AR(1) residual, the 5 % test
    rejected 8 % of the time at residual phi = 0.5 and 24 % at phi = 0.9
    (5-10 % with ``bandwidth=30``, 5 % with 100). Pass a larger ``bandwidth``
    (samples) when the residual ACF decays slowly.

    Args:
        residual: residuals per pair (see module docstring), unit ``[e]``.
        regressors: name -> series per pair, same lengths as the residual.
        name: name of the test in the result.
        test: regressor names whose coefficients are tested; the others are nuisance
            covariates kept in the model. Default: all.
        bandwidth: Newey-West lag truncation [samples]; default the rule above.

    Returns:
        :class:`TestResult` with ``statistic = W``, ``dof = |T|`` and ``effect`` a dict
        of every regressor's coefficient (``[e]`` per regressor unit) plus
        ``"delta_r2"``, the share of residual variance explained by the tested
        regressors (R^2 of the full model minus that of the model without them;
        with no nuisance regressors, the R^2 over the intercept alone).
        ``details["intercept"]`` is ``b_0`` [e].
    """
    names = list(regressors)
    tested_names = names if test is None else list(test)
    unknown = set(tested_names) - set(names)
    if unknown or not tested_names:
        raise ValueError(f"test must be a non-empty subset of {names}, got {test}")
    tested = [names.index(t) + 1 for t in tested_names]  # +1: column 0 is intercept
    p = len(names) + 1
    rows = _aligned(_as_pairs(residual), *(_as_pairs(regressors[k]) for k in names))
    per_pair: list[TestResult] = []
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    dropped = 0
    for j, (cols, n_drop) in enumerate(rows):
        pname, n = f"{name}[pair {j}]", cols[0].size
        dropped += n_drop
        if n < p + 2:
            per_pair.append(
                TestResult(pname, math.nan, math.nan, {}, n, 0, n_drop,
                           note=f"skipped: {n} samples < {p + 2} for {p} coefficients")
            )  # fmt: skip
            continue
        xb = np.column_stack([np.ones(n), *cols[1:]])  # (n, p)
        blocks.append((xb, cols[0]))
        per_pair.append(_regression_result(pname, [blocks[-1]], names, tested,
                                           bandwidth, n_drop))  # fmt: skip
    if not blocks:
        return _no_pooled(name, per_pair, dropped)
    pooled = _regression_result(name, blocks, names, tested, bandwidth, dropped)
    return TestResult(**{**pooled.__dict__, "per_pair": per_pair})


def _regression_result(
    name: str,
    blocks: list[tuple[np.ndarray, np.ndarray]],
    names: list[str],
    tested: list[int],
    bandwidth: int | None,
    n_drop: int,
) -> TestResult:
    wald, dof, coefs, icept, d_r2, note = _ols_wald(blocks, names, tested, bandwidth)
    p_val = 1.0 if note else chi2_sf(wald, dof)
    n = sum(b[1].size for b in blocks)
    return TestResult(name, wald, p_val, {**coefs, "delta_r2": d_r2}, n, dof, n_drop,
                      note=note, details={"intercept": icept})  # fmt: skip


def _map_pairs(fn: Any, *series: Any) -> list[np.ndarray]:
    return [fn(*cols) for cols in zip(*(_as_pairs(s) for s in series), strict=True)]


def speed_dependence(residual: Any, v: Any, **kw: Any) -> TestResult:
    """Does the residual depend on the follower's own speed?

    ``e = b_0 + b_v v + b_v2 v^2 + u``, ``H0: b_v = b_v2 = 0``. A rejection points to
    a missing speed term: a desired speed or time headway that is not constant, or
    air drag (``v^2``). ``v`` in [m/s]; coefficients in ``[e] s/m`` and
    ``[e] s^2/m^2``. Keyword arguments go to :func:`regression_test`.
    """
    vs = _as_pairs(v)
    return regression_test(
        residual, {"v": vs, "v2": [x * x for x in vs]}, "speed_dependence", **kw
    )


def asymmetry(residual: Any, dv: Any, **kw: Any) -> TestResult:
    """Does the model err differently when the speed difference changes sign?

    ``e = b_0 + b_dv dv + b_neg 1[dv < 0] + b_dv_neg dv 1[dv < 0] + u`` with
    ``H0: b_neg = b_dv_neg = 0``; ``dv`` (caller's sign convention; torchcf uses
    ``v - v_lead`` [m/s]) is kept as a nuisance slope so that a residual linear in
    ``dv`` on both sides is not mistaken for asymmetry. A rejection means a
    different level or slope on one side: asymmetric acceleration and braking
    (e.g. stronger reaction to an approaching leader than to a receding one).
    """
    neg = _map_pairs(lambda d: (d < 0).astype(np.float64), dv)
    dvs = _as_pairs(dv)
    # Keep NaN in the indicator so that NaN rows in dv are dropped, not set to 0.
    neg = [np.where(np.isfinite(d), n, np.nan) for d, n in zip(dvs, neg, strict=True)]
    regs = {
        "dv": dvs,
        "neg": neg,
        "dv_neg": [d * n for d, n in zip(dvs, neg, strict=True)],
    }
    return regression_test(residual, regs, "asymmetry", test=["neg", "dv_neg"], **kw)


def spacing_dependence(residual: Any, spacing: Any, **kw: Any) -> TestResult:
    """Does the residual depend on the spacing level?

    ``e = b_0 + b_s s + u``, ``H0: b_s = 0``, spacing ``s`` [m]. A rejection points to
    a spacing-proportional measurement bias (sensor offset or scale error in the
    observed gap, a wrong vehicle length) or a missing spacing term.
    """
    return regression_test(residual, {"spacing": spacing}, "spacing_dependence", **kw)


def position_dependence(residual: Any, x: Any, **kw: Any) -> TestResult:
    """Does the residual trend with position along the road?

    ``e = b_0 + b_x x + u``, ``H0: b_x = 0``, position ``x`` [m]. A rejection points to
    a location effect the model lacks, such as a road grade or a bottleneck. Only a
    linear trend is tested; for a localized effect pass position bins to
    :func:`regression_test`.
    """
    return regression_test(residual, {"x": x}, "position_dependence", **kw)


def lap_dependence(residual: Any, x: Any, period: float, **kw: Any) -> TestResult:
    """Does the residual vary round a closed track's lap?

    ``e = b_0 + b_s sin(2 pi x / C) + b_c cos(2 pi x / C) + u``, ``C = period``
    [m] the lap length, position ``x`` [m] (an odometer over laps), ``H0: b_s =
    b_c = 0`` (chi2 with 2 degrees of freedom). The lap's first harmonic is what a
    tilted circular track leaves (its grade is ``slope sin(2 pi s / C)`` from its
    lowest point); a linear trend in an odometer that runs over many laps would
    test the wrong thing.
    """
    if not (math.isfinite(period) and period > 0):
        raise ValueError(f"period must be a lap length > 0 [m], got {period}")
    turns = [2.0 * math.pi * np.asarray(p, dtype=float) / period for p in _as_pairs(x)]
    regressors = {"sin": [np.sin(t) for t in turns], "cos": [np.cos(t) for t in turns]}
    return regression_test(residual, regressors, "lap_dependence", **kw)


def drift(residual: Any, dt: float, **kw: Any) -> TestResult:
    """Does the residual drift over time within a trajectory?

    ``e = b_0 + b_t t + u``, ``t = 0, dt, 2 dt, ...`` [s] from each pair's start
    (computed before NaN are dropped, so gaps keep their true times), ``H0: b_t = 0``.
    A rejection points to non-stationary behaviour (fatigue, changing conditions) or
    an accumulating integration or calibration error; ``b_t`` in ``[e]/s``.
    """
    times = [np.arange(e.size) * dt for e in _as_pairs(residual)]
    return regression_test(residual, {"t": times}, "drift", **kw)


# ---------------------------------------------------------------- summary


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, np.ndarray | list | tuple):
        return [_jsonable(v) for v in (x.tolist() if isinstance(x, np.ndarray) else x)]
    if isinstance(x, bool | str) or x is None:
        return x
    if isinstance(x, int | np.integer):
        return int(x)
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None  # JSON has no NaN / inf
    return str(x)


def summarize(
    results: Sequence[TestResult], *, include_pairs: bool = False
) -> list[JSON]:
    """JSON-able rows, one per result, sorted by p-value (untestable ones last).

    Args:
        results: pooled test results.
        include_pairs: also add a row for every per-pair result.

    Returns:
        Rows with keys ``name, statistic, p_value, effect, n, dof, n_dropped, n_pairs,
        note, details``; NaN and inf become ``None``.
    """
    flat: list[TestResult] = []
    for r in results:
        flat.append(r)
        if include_pairs and r.per_pair:
            flat.extend(r.per_pair)
    rows = [
        {
            "name": r.name,
            "statistic": _jsonable(r.statistic),
            "p_value": _jsonable(r.p_value),
            "effect": _jsonable(r.effect),
            "n": int(r.n),
            "dof": int(r.dof),
            "n_dropped": int(r.n_dropped),
            "n_pairs": len(r.per_pair) if r.per_pair is not None else None,
            "note": r.note,
            "details": _jsonable(r.details),
        }
        for r in flat
    ]
    return sorted(rows, key=lambda d: (d["p_value"] is None, d["p_value"] or 0.0))
