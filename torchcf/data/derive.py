"""Derivatives of sampled signals by local polynomial regression (Savitzky-Golay).

Raw trajectories often lack a series: OpenACC records speed but no acceleration,
NGSIM's speeds and accelerations are themselves noisy differences of positions.
:func:`fill_derivatives` fills the speed [m/s] and acceleration [m/s^2] a
vehicle's record lacks in a :class:`~torchcf.data.trajectory.TrajectoryTable`
from position [m] and speed, and :func:`savgol_derivative` is the filter it uses
(numpy only).

The filter
----------
Over a window of 2m+1 samples (m = round(window / (2 dt))), the least-squares
polynomial of degree ``order`` is fitted and differentiated at the window's
centre. The estimate is linear in the samples: a fixed set of weights slides over
the series. At the first and last m samples, where no centred window fits, the
polynomial of the first / last full window is evaluated at the edge samples, as
``scipy.signal.savgol_filter(..., mode="interp")`` does (the results agree to
rounding).

What the smoothing does (defaults: window 1 s, order 2, first derivative)
--------------------------------------------------------------------------
* A polynomial of degree <= ``order`` is differentiated exactly, edges included.
* For the first derivative, order 2 gives the same weights as order 1: the slope
  of a least-squares line, w_j = j / (dt * S2) with S2 = sum_j j^2 over
  j = -m..m (S2 = 110 for m = 5).
* Bias on a smooth signal: to leading order the estimate of f' is
  f' + f''' * dt^2 * S4 / (6 * S2) (S4 = sum_j j^4): 0.0297 s^2 * f''' for
  1 s at 0.1 s. A speed derived from positions is off by 0.03 m/s per m/s^3 of
  jerk; an acceleration derived from speed by 0.03 m/s^2 per m/s^4 of the
  speed's third derivative.
* Frequency response: for f = sin(2 pi t / P) the estimate is G(P) * f' with
  G(P) = sum_j j sin(w j dt) / (w dt S2), w = 2 pi / P (continuous limit:
  G = 3 (sin x - x cos x) / x^3, x = w m dt). Measured for 1 s at 0.1 s:
  G = 0.736 (P = 2 s), 0.876 (3 s), 0.954 (5 s), 0.988 (10 s). Speed or
  acceleration swings faster than about 3 s are damped; the car-following
  dynamics ACC and drivers produce (periods of 5 s and more) lose < 5 %. An
  acceleration derived from a derived speed is smoothed twice: G(P)^2 (0.910 at
  P = 5 s).
* Noise: independent noise of standard deviation sigma on the samples gives
  sigma / (dt sqrt(S2)) on the derivative, 0.95 sigma per second for 1 s at
  0.1 s, against 7.1 sigma per second for a central difference.
* At the edges the polynomial is evaluated off its centre: the bias and noise
  of the first and last m samples are larger (for order 2 and 11 samples the
  noise grows to 3.7 times the interior's at the very first sample, and the
  error on a sine of period 5 s reaches 13 % of its derivative's amplitude).

Why 1 s: OpenACC's GNSS logged at 3-5 Hz and was cubic-spline interpolated to
10 Hz, so the 10 Hz samples carry nothing real above about 2 Hz, and the spline
passes through every noisy fix; NGSIM's video-tracked positions are noisy enough
that twice-differenced positions give unrealistic accelerations (Punzo,
Borzacchiello & Ciuffo 2011; Montanino & Punzo 2015). Measured on the four
OpenACC sample files: a central difference of the Doppler speed gives up to
5.9 m/s^2 (Ispra, the leader in stop-and-go; 99th percentile 2.3 m/s^2), this
filter 1.5 m/s^2 (1.3), and the two differ by 0.04-0.53 m/s^2 rms per vehicle.
A 1 s window (11 samples at 10 Hz) removes that noise while keeping the
car-following swings of 5 s and more within 5 %.

Missing values
--------------
:func:`savgol_derivative` is purely linear: an output sample is NaN when any
sample its polynomial was fitted to is non-finite (within m samples of it in the
interior, within the first / last window at the edges). :func:`fill_derivatives`
therefore differentiates each run of finite samples on its own, so a hole costs
only its own samples.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from torchcf.data.pairset import DataError, positive_float
from torchcf.data.trajectory import TrajectoryTable

__all__ = ["fill_derivatives", "savgol_derivative", "window_samples"]

#: A step longer than this many times the track's median step splits the track.
GAP_FACTOR: float = 1.5


def window_samples(window: float, dt: float, order: int) -> int:
    """Half-width m of the window: 2m+1 samples span ``window`` seconds.

    m = round(window / (2 dt)) with halves rounded up, raised to ceil(order / 2)
    so that the window holds at least order + 1 samples (a fit of degree
    ``order`` needs them).

    Args:
        window: window length [s], >= 0.
        dt: sampling interval [s], > 0.
        order: polynomial degree, >= 0.

    Returns:
        m >= 0.
    """
    # The small epsilon keeps 1.0 / (2 * 0.1) = 4.999... from rounding down.
    m = int(math.floor(window / (2.0 * dt) + 0.5 + 1e-9))
    return max(m, (order + 1) // 2)


def savgol_derivative(
    values: np.ndarray,
    dt: float,
    *,
    window: float = 1.0,
    order: int = 2,
    deriv: int = 1,
) -> np.ndarray:
    """The ``deriv``-th derivative of uniformly sampled ``values`` (Savitzky-Golay).

    Interior samples use the centred window of 2m+1 samples
    (m = :func:`window_samples`), the first and last m samples the polynomial of
    the first / last full window (scipy's ``mode="interp"``). A series shorter
    than a window is fitted by one polynomial of degree min(order, T - 1); a
    single sample has derivative 0. See the module docstring for the bias and
    the rule on NaN.

    Args:
        values: (T,) or (T, N) samples, time along axis 0.
        dt: sampling interval [s], > 0.
        window: window length [s], >= 0.
        order: degree of the local polynomial, >= 0.
        deriv: order of the derivative, >= 0 (0 smooths); above ``order`` the
            result is 0.

    Returns:
        float64 array of the shape of ``values``, in [values' unit / s^deriv].

    Raises:
        DataError: ``dt`` not > 0, ``window`` < 0, or a negative ``order`` /
            ``deriv``, or ``values`` of more than two dimensions.
    """
    dt = positive_float(dt, "dt", "s")
    if not (math.isfinite(window) and window >= 0):
        raise DataError(f"window must be finite and >= 0 [s], got {window}")
    if order < 0 or deriv < 0:
        raise DataError(f"order and deriv must be >= 0, got {order} and {deriv}")
    y = np.asarray(values, dtype=np.float64)
    if y.ndim not in (1, 2):
        raise DataError(f"values must be (T,) or (T, N), got shape {y.shape}")
    n_steps = y.shape[0]
    if n_steps == 0:
        return y.copy()
    y2 = y.reshape(n_steps, -1)  # (T, N)
    out = np.empty_like(y2)
    m = window_samples(window, dt, order)
    width = 2 * m + 1
    if n_steps < width:
        weights = _fit_weights(n_steps, min(order, n_steps - 1), deriv, 0, n_steps)
        out[:] = _apply(weights, y2)
    else:
        centre = _fit_weights(width, order, deriv, m, m + 1)  # (1, 2m+1)
        inner = n_steps - 2 * m
        # Sliding sum over offsets: T * (2m+1) flops and no (T, 2m+1, N) copy.
        acc = np.zeros((inner, y2.shape[1]))
        for j in range(width):
            acc += centre[0, j] * y2[j : j + inner]
        out[m : n_steps - m] = acc
        if m:
            out[:m] = _apply(_fit_weights(width, order, deriv, 0, m), y2[:width])
            out[n_steps - m :] = _apply(
                _fit_weights(width, order, deriv, width - m, width), y2[-width:]
            )
    return (out / dt**deriv).reshape(y.shape)


def _apply(weights: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(S, n) weights times (n, N) samples, one column at a time in effect.

    An explicit sum rather than ``weights @ y``: BLAS picks different kernels
    (and roundings) for one column and for many, and a column's result must
    not depend on its neighbours.
    """
    out = np.zeros((weights.shape[0], y.shape[1]))
    for j in range(weights.shape[1]):
        out += weights[:, j : j + 1] * y[j][None, :]  # (S, N)
    return out


@functools.lru_cache(maxsize=256)
def _fit_weights(n: int, degree: int, deriv: int, start: int, stop: int) -> np.ndarray:
    """Weights (stop - start, n): derivative at samples start..stop-1 of the fit.

    The least-squares polynomial of ``degree`` through n samples at unit spacing,
    differentiated ``deriv`` times (per sample, not per second) at the samples
    ``start..stop-1`` of the window.
    """
    # Abscissae centred and scaled to [-1, 1] keep the Vandermonde matrix well
    # conditioned for wide windows; the scale returns in the chain rule below.
    half = max((n - 1) / 2.0, 1.0)
    u = (np.arange(n) - (n - 1) / 2.0) / half  # (n,)
    vander = u[:, None] ** np.arange(degree + 1)[None, :]  # (n, degree+1)
    coef = np.linalg.pinv(vander)  # (degree+1, n): samples -> coefficients
    at = u[start:stop]
    powers = np.arange(degree + 1)
    # d^k/du^k u^p = p! / (p-k)! u^(p-k), zero for p < k.
    falling = np.array(
        [math.perm(p, deriv) if p >= deriv else 0 for p in powers], dtype=np.float64
    )
    exponent = np.clip(powers - deriv, 0, None)
    basis = falling[None, :] * at[:, None] ** exponent[None, :]  # (stop-start, d+1)
    weights = basis @ coef / half**deriv
    weights.setflags(write=False)
    return weights


def fill_derivatives(
    table: TrajectoryTable,
    *,
    speed_window: float = 1.0,
    acceleration_window: float = 1.0,
    order: int = 2,
) -> TrajectoryTable:
    """Fill missing speeds from positions and missing accelerations from speeds.

    Each (run, vehicle) track is ordered by time and cut into pieces at time
    gaps (a step longer than 1.5 times the track's median step); within a piece
    each run of finite source values is differentiated on its own with
    :func:`savgol_derivative`, at the piece's mean step. Then:

    * speed: a track without any speed gets d position / dt;
    * acceleration: a track without any acceleration gets d speed / dt (the
      measured speed, or the derived one).

    A track that has some values of a column keeps its NaN cells: a hole in a
    measured series is a measurement failure, which the extraction's
    ``missing`` filter reports, not something to paper over with a derivative
    of another series. Measured values are never changed. A derived cell stays
    NaN when its source run is a single sample (no derivative can be measured
    there) or its source is NaN.
    Rows keep their order; the result does not depend on it.

    Args:
        table: the trajectories.
        speed_window: window [s] of the speed derivative.
        acceleration_window: window [s] of the acceleration derivative.
        order: degree of the local polynomial.

    Returns:
        The table with speed and acceleration filled, plus one note per derived
        column (what from what, window, order, how many vehicles).

    Raises:
        DataError: a track with two rows at the same time, or an invalid window
            or order.
    """
    for value, name in (
        (speed_window, "speed_window"),
        (acceleration_window, "acceleration_window"),
    ):
        if not (math.isfinite(value) and value >= 0):
            raise DataError(f"{name} must be finite and >= 0 [s], got {value}")
    if order < 0:
        raise DataError(f"order must be >= 0, got {order}")
    frame = table.frame.copy()
    time = frame["time"].to_numpy()
    position = frame["position"].to_numpy()
    speed = frame["speed"].to_numpy().copy()
    accel = frame["acceleration"].to_numpy().copy()
    speed_log = _Log()
    accel_log = _Log()
    groups = frame.groupby(["run", "vehicle"], sort=False).indices
    for (run, vehicle), rows in groups.items():
        rows = rows[np.argsort(time[rows], kind="stable")]
        t = time[rows]
        steps = np.diff(t)
        if steps.size and (steps <= 0).any():
            at = float(t[1:][steps <= 0][0])
            raise DataError(
                f"run '{run}' vehicle '{vehicle}' has two rows at time {at} s in "
                f"'{table.source}'"
            )
        pieces = _pieces(steps)
        missing = ~np.isfinite(speed[rows])
        if missing.all():
            derived = _derive(t, position[rows], pieces, speed_window, order)
            speed[rows[missing]] = derived[missing]
            speed_log.add(missing, derived, t)
        missing = ~np.isfinite(accel[rows])
        if missing.all():
            derived = _derive(t, speed[rows], pieces, acceleration_window, order)
            accel[rows[missing]] = derived[missing]
            accel_log.add(missing, derived, t)
    frame["speed"] = speed
    frame["acceleration"] = accel
    notes = [
        log.note(column, source, window, order)
        for log, column, source, window in (
            (speed_log, "speed", "position", speed_window),
            (accel_log, "acceleration", "speed", acceleration_window),
        )
        if log.vehicles
    ]
    return dataclasses.replace(table, frame=frame).with_notes(*notes)


def _pieces(steps: np.ndarray) -> list[slice]:
    """Slices of a track between time gaps (steps > 1.5 x the median step)."""
    if steps.size == 0:
        return [slice(0, 1)]
    cut = np.flatnonzero(steps > GAP_FACTOR * np.median(steps)) + 1
    bounds = [0, *cut.tolist(), steps.size + 1]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _derive(
    t: np.ndarray, values: np.ndarray, pieces: list[slice], window: float, order: int
) -> np.ndarray:
    """d values / dt over each run of finite values within each piece; NaN else."""
    out = np.full(values.shape, np.nan)
    for piece in pieces:
        finite = np.isfinite(values[piece])
        for start, stop in _runs(finite):
            if stop - start < 2:
                continue  # one sample: no slope to measure, leave it NaN
            a, b = piece.start + start, piece.start + stop
            # Samples are taken as uniform at the run's mean step; the pieces
            # already exclude steps far from the median.
            dt = (t[b - 1] - t[a]) / (b - a - 1)
            out[a:b] = savgol_derivative(values[a:b], dt, window=window, order=order)
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(
        zip(
            np.flatnonzero(edges == 1).tolist(),
            np.flatnonzero(edges == -1).tolist(),
            strict=True,
        )
    )


@dataclasses.dataclass
class _Log:
    """What one derived column received, for its note."""

    vehicles: int = 0
    cells: int = 0
    left: int = 0
    steps: list[float] = dataclasses.field(default_factory=list)

    def add(self, missing: np.ndarray, derived: np.ndarray, t: np.ndarray) -> None:
        filled = missing & np.isfinite(derived)
        self.vehicles += 1
        self.cells += int(filled.sum())
        self.left += int((missing & ~filled).sum())
        if t.size > 1:
            self.steps.append(float(np.median(np.diff(t))))

    def note(self, column: str, source: str, window: float, order: int) -> str:
        sampling = ""
        if self.steps:
            dt = float(np.median(self.steps))
            width = 2 * window_samples(window, dt, order) + 1
            sampling = f" ({width} samples at {dt:.3g} s)"
        left = f"; {self.left} cell(s) left NaN" if self.left else ""
        return (
            f"{column} derived from {source}: Savitzky-Golay, window {float(window)} s"
            f"{sampling}, order {order}, for {self.vehicles} vehicles "
            f"({self.cells} cells){left}"
        )
