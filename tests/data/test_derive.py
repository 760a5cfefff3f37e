"""savgol_derivative against scipy and closed forms; fill_derivatives' invariants."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy.signal import savgol_filter

from torchcf.data.derive import fill_derivatives, savgol_derivative, window_samples
from torchcf.data.pairset import DataError
from torchcf.data.trajectory import TrajectoryTable


def _scipy(values: np.ndarray, dt: float, window: float, order: int, deriv: int):
    m = window_samples(window, dt, order)
    return savgol_filter(
        values, 2 * m + 1, order, deriv, delta=dt, mode="interp", axis=0
    )


@pytest.mark.parametrize("window", [0.3, 1.0, 2.0])
@pytest.mark.parametrize("order", [1, 2, 3, 4])
@pytest.mark.parametrize("deriv", [0, 1, 2])
def test_matches_scipy_interp_mode(window: float, order: int, deriv: int) -> None:
    rng = np.random.default_rng(order * 10 + deriv)
    dt = 0.1
    width = 2 * window_samples(window, dt, order) + 1
    for n_steps in (width, width + 1, 137):
        values = rng.normal(size=(n_steps, 3))
        ours = savgol_derivative(values, dt, window=window, order=order, deriv=deriv)
        theirs = _scipy(values, dt, window, order, deriv)
        scale = max(1.0, float(np.abs(theirs).max()))
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-10 * scale)


def test_window_in_samples() -> None:
    assert window_samples(1.0, 0.1, 2) == 5  # 11 samples, despite 1/0.2 = 4.99..
    assert window_samples(0.5, 0.1, 2) == 3  # 2.5 rounds half up: 7 samples
    assert window_samples(0.0, 0.1, 2) == 1  # at least order + 1 samples
    assert window_samples(0.0, 0.1, 0) == 0
    assert window_samples(1.0, 0.04, 3) == 13  # 12.5 up: 27 samples = 1.04 s


@pytest.mark.parametrize("order", [2, 3])
def test_quadratic_is_exact_everywhere(order: int) -> None:
    dt = 0.1
    t = np.arange(40) * dt
    x = 3.0 + 12.0 * t - 0.8 * t**2  # position [m] with a = -1.6 m/s^2
    v = savgol_derivative(x, dt, order=order)
    a = savgol_derivative(x, dt, order=order, deriv=2)
    np.testing.assert_allclose(v, 12.0 - 1.6 * t, atol=1e-10)
    np.testing.assert_allclose(a, -1.6, atol=1e-9)


def test_cubic_bias_is_the_documented_formula() -> None:
    # For x = t^3 (third derivative 6) the interior bias is exactly
    # 6 dt^2 S4 / (6 S2), the module docstring's 0.0297 s^2 per unit of it.
    dt, m = 0.1, 5
    t = np.arange(60) * dt
    j = np.arange(-m, m + 1)
    bias = 6.0 * dt**2 * np.sum(j**4) / (6 * np.sum(j**2))
    assert bias / 6.0 == pytest.approx(0.0297, abs=5e-5)
    v = savgol_derivative(t**3, dt)
    np.testing.assert_allclose(v[m:-m], 3 * t[m:-m] ** 2 + bias, atol=1e-9)


def test_sine_attenuation_is_the_documented_gain() -> None:
    # Interior estimate of sin' is exactly G(P) * cos for the antisymmetric
    # weights; G(5 s) = 0.954 for 1 s at 0.1 s, as the module docstring says.
    dt, period, m = 0.1, 5.0, 5
    omega = 2 * math.pi / period
    t = np.arange(300) * dt
    estimate = savgol_derivative(np.sin(omega * t), dt)
    j = np.arange(-m, m + 1)
    gain = np.sum(j * np.sin(omega * j * dt)) / (omega * dt * np.sum(j**2))
    assert gain == pytest.approx(0.954, abs=5e-4)
    inner = slice(m, -m)
    np.testing.assert_allclose(
        estimate[inner], gain * omega * np.cos(omega * t[inner]), atol=1e-12
    )
    # edges: evaluated off-centre, 13 % of the derivative's amplitude at worst
    error = np.abs(estimate - omega * np.cos(omega * t))
    assert error[inner].max() < 0.05 * omega
    assert error.max() == pytest.approx(0.13 * omega, abs=0.005 * omega)


def test_columns_are_independent() -> None:
    rng = np.random.default_rng(1)
    values = rng.normal(size=(50, 4))
    together = savgol_derivative(values, 0.1, window=0.7, order=3, deriv=2)
    for n in range(4):
        alone = savgol_derivative(values[:, n], 0.1, window=0.7, order=3, deriv=2)
        np.testing.assert_array_equal(together[:, n], alone)
    assert savgol_derivative(values[:, 0], 0.1).shape == (50,)


def test_short_series_fit_one_polynomial() -> None:
    t = np.arange(5) * 0.1
    x = 1.0 + 2.0 * t + 3.0 * t**2
    np.testing.assert_allclose(savgol_derivative(x, 0.1), 2.0 + 6.0 * t, atol=1e-10)
    # two samples: a line (degree min(2, 1)); one sample: no slope
    np.testing.assert_allclose(savgol_derivative(x[:2], 0.1), [2.3, 2.3], atol=1e-10)
    assert savgol_derivative(x[:1], 0.1).tolist() == [0.0]
    assert savgol_derivative(np.empty(0), 0.1).shape == (0,)


def test_nan_spreads_to_the_samples_whose_fit_used_it() -> None:
    values = np.linspace(0.0, 10.0, 60)
    values[30] = np.nan
    out = savgol_derivative(values, 0.1)  # m = 5
    assert np.flatnonzero(np.isnan(out)).tolist() == list(range(25, 36))
    values = np.linspace(0.0, 10.0, 60)
    values[2] = np.nan  # inside the first window: every edge sample is NaN too
    assert np.flatnonzero(np.isnan(savgol_derivative(values, 0.1))).tolist() == list(
        range(0, 8)
    )


@pytest.mark.parametrize(
    "kwargs", [{"dt": 0.0}, {"dt": 0.1, "window": -1.0}, {"dt": 0.1, "order": -1}]
)
def test_bad_arguments(kwargs) -> None:
    with pytest.raises(DataError):
        savgol_derivative(np.zeros(10), **kwargs)


# -- fill_derivatives ---------------------------------------------------------


def _track(run: str, vehicle: str, t: np.ndarray, x: np.ndarray, **cols):
    return pd.DataFrame(
        {"run": run, "vehicle": vehicle, "time": t, "position": x, **cols}
    )


def _table(*tracks: pd.DataFrame) -> TrajectoryTable:
    return TrajectoryTable.from_frame(pd.concat(tracks, ignore_index=True), source="t")


def test_speed_from_position_and_acceleration_from_speed() -> None:
    t = np.arange(60) * 0.1
    x = 5.0 + 10.0 * t + 0.5 * t**2  # v = 10 + t, a = 1
    table = fill_derivatives(_table(_track("r", "1", t, x)))
    frame = table.frame
    np.testing.assert_allclose(frame["speed"], 10.0 + t, atol=1e-9)
    np.testing.assert_allclose(frame["acceleration"], 1.0, atol=1e-9)
    assert table.notes == (
        "speed derived from position: Savitzky-Golay, window 1.0 s (11 samples at "
        "0.1 s), order 2, for 1 vehicles (60 cells)",
        "acceleration derived from speed: Savitzky-Golay, window 1.0 s (11 samples "
        "at 0.1 s), order 2, for 1 vehicles (60 cells)",
    )


def test_holes_in_a_measured_series_stay_holes() -> None:
    """A track with some speeds keeps its NaN cells (the extraction's missing
    filter reports them); only a column the track lacks entirely is derived."""
    t = np.arange(50) * 0.1
    x = 10.0 * t + 0.5 * t**2
    measured = 10.0 + t + 0.3  # deliberately not d x/dt, so a change would show
    measured[[7, 20, 21]] = np.nan
    accel = np.full(50, np.nan)
    accel[:10] = 9.0
    table = fill_derivatives(
        _table(_track("r", "1", t, x, speed=measured, acceleration=accel))
    )
    speed = table.frame["speed"].to_numpy()
    np.testing.assert_array_equal(speed, measured)  # NaN where NaN
    acc = table.frame["acceleration"].to_numpy()
    np.testing.assert_array_equal(acc, accel)
    assert table.notes == ()
    # no acceleration at all: derived from the measured speed, NaN around its holes
    table = fill_derivatives(_table(_track("r", "1", t, x, speed=measured)))
    acc = table.frame["acceleration"].to_numpy()
    assert np.isnan(acc[[7, 20, 21]]).all()
    np.testing.assert_allclose(acc[30:45], 1.0, atol=1e-9)


def test_no_derivative_across_a_time_gap() -> None:
    # Two pieces of one track, 3 s apart and 500 m apart; each is a quadratic,
    # so the derivative is exact unless a window straddles the gap.
    t1, t2 = np.arange(30) * 0.1, 6.0 + np.arange(30) * 0.1
    x = np.concatenate([2.0 * t1**2, 500.0 + 2.0 * t2**2])
    t = np.concatenate([t1, t2])
    frame = fill_derivatives(_table(_track("r", "1", t, x))).frame
    np.testing.assert_allclose(frame["speed"], 4.0 * t, atol=1e-8)
    np.testing.assert_allclose(frame["acceleration"], 4.0, atol=1e-8)


def test_nan_position_splits_and_single_samples_stay_nan() -> None:
    t = np.arange(40) * 0.1
    x = 3.0 * t
    x[[10, 12]] = np.nan  # sample 11 is alone between two holes
    table = fill_derivatives(_table(_track("r", "1", t, x)))
    speed = table.frame["speed"].to_numpy()
    assert np.flatnonzero(np.isnan(speed)).tolist() == [10, 11, 12]
    np.testing.assert_allclose(np.delete(speed, [10, 11, 12]), 3.0, atol=1e-10)
    assert "3 cell(s) left NaN" in table.notes[0]


def test_independent_of_row_order() -> None:
    rng = np.random.default_rng(3)
    tracks = []
    for run in ("a", "b"):
        for vehicle in ("1", "2", "3"):
            t = np.arange(45) * 0.1 + rng.uniform(0, 100)
            x = np.cumsum(rng.uniform(1.0, 2.0, 45))
            speed = np.where(rng.random(45) < 0.2, np.nan, rng.normal(15, 1, 45))
            tracks.append(_track(run, vehicle, t, x, speed=speed))
    table = _table(*tracks)
    shuffled = TrajectoryTable.from_frame(
        table.frame.sample(frac=1.0, random_state=0), source="t"
    )
    one = fill_derivatives(table).sorted().frame
    two = fill_derivatives(shuffled).sorted().frame
    pd.testing.assert_frame_equal(one, two)
    # rows keep their input order
    filled = fill_derivatives(shuffled).frame
    np.testing.assert_array_equal(filled["time"], shuffled.frame["time"])


def test_nothing_to_fill_adds_no_note() -> None:
    t = np.arange(10) * 0.1
    table = _table(_track("r", "1", t, t, speed=t, acceleration=t))
    out = fill_derivatives(table)
    assert out.notes == ()
    pd.testing.assert_frame_equal(out.frame, table.frame)


def test_duplicate_time_is_an_error() -> None:
    t = np.array([0.0, 0.1, 0.1, 0.2])
    with pytest.raises(DataError, match="run 'r' vehicle '1' has two rows at time"):
        fill_derivatives(_table(_track("r", "1", t, t)))
