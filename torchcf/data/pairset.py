"""The validated container for observed leader-follower pairs.

A :class:`PairSet` holds N leader-follower pairs sampled every ``dt`` seconds over T
steps, time-major: every series is a ``(T, N)`` tensor, column j of all six series
belongs to pair j. Everything is SI: positions [m] (front bumpers, along the road),
speeds [m/s], accelerations [m/s^2]; unit conversion happens in the reader.

Pairs of different durations are padded to a common T and carry a boolean ``mask``:
each column is a prefix (True on its valid steps, then False). Padding repeats the
last valid value, so it is always finite and never NaN; everything downstream
reduces over ``mask`` only.

Every PairSet is checked when it is built, and a problem raises :class:`DataError`
with a one-line message that names it and where it is (1-based row and column,
as a spreadsheet shows them, plus the pair id).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchcf.system.errors import TorchcfError

__all__ = ["DataError", "PairSet", "SERIES"]

#: Field names of the six observed series, in the canonical order.
SERIES: tuple[str, ...] = (
    "x_lead",
    "v_lead",
    "a_lead",
    "x_follow",
    "v_follow",
    "a_follow",
)

_SPLITS = (None, "train", "test")


class DataError(TorchcfError, ValueError):
    """Observed data is missing, malformed or physically impossible."""


@dataclass(frozen=True, eq=False)
class PairSet:
    """N observed leader-follower pairs over T steps, in SI units.

    Build one with :meth:`from_arrays` (converts, pads, validates) or through
    ``torchcf.data.load_pairs``; the constructor validates but converts nothing.

    Examples:
        >>> import torch
        >>> from torchcf import PairSet
        >>> t = torch.arange(50, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> x_lead, v = 35.0 + 20.0 * t, torch.full_like(t, 20.0)  # 20 m/s
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 35.0, v, a], dt=0.1)
        >>> pairs.n_steps, pairs.n_pairs
        (50, 1)

    Attributes:
        x_lead: (T, N) leader front-bumper position [m].
        v_lead: (T, N) leader speed [m/s].
        a_lead: (T, N) leader acceleration [m/s^2].
        x_follow: (T, N) follower front-bumper position [m].
        v_follow: (T, N) follower speed [m/s].
        a_follow: (T, N) follower acceleration [m/s^2].
        mask: (T, N) bool, True on valid steps; each column is a prefix.
        dt: sampling interval [s], > 0.
        leader_length: leader vehicle length [m], > 0.
        pair_ids: (N,) ids of the pairs: for a named dataset the 0-based column in
            the full set's files, for a folder the 0-based column in the files
            read. Left empty, it becomes ``0 .. N-1``.
        name: dataset name or folder.
        split: None (the full set), "train" or "test".
        notes: human-readable reports of quirks found or handled while loading.
        road_frame: True when the positions of all pairs are positions on one
            road (road effects such as a grade profile are then shared by the
            pairs), False when each pair has its own frame, None when the data
            do not say (``meta.json``'s ``"road_frame"``; the diagnosis then
            decides, :func:`torchcf.diagnose.signatures.road.shares_road_frame`).
        road_period: the lap length [m] when that road is a closed track
            (positions are then odometers round it and a road profile is
            periodic, :class:`torchcf.models.effects.RoadProfile`); None for
            an open road (``meta.json``'s ``"road_period"``).
    """

    x_lead: Tensor
    v_lead: Tensor
    a_lead: Tensor
    x_follow: Tensor
    v_follow: Tensor
    a_follow: Tensor
    mask: Tensor
    dt: float
    leader_length: float = 5.0
    pair_ids: tuple[int, ...] = ()
    name: str = ""
    split: str | None = None
    notes: tuple[str, ...] = ()
    road_frame: bool | None = None
    road_period: float | None = None

    def __post_init__(self) -> None:
        n_pairs = self._check_tensors()
        self._set("dt", positive_float(self.dt, "dt", "s"))
        self._set(
            "leader_length",
            positive_float(self.leader_length, "leader_length", "m"),
        )
        ids = tuple(int(i) for i in self.pair_ids) or tuple(range(n_pairs))
        if len(ids) != n_pairs:
            raise DataError(f"{len(ids)} pair_ids given for {n_pairs} pairs")
        self._set("pair_ids", ids)
        if self.split not in _SPLITS:
            raise DataError(
                f"split must be None, 'train' or 'test', got {self.split!r}"
            )
        self._set("name", str(self.name))
        self._set("notes", tuple(str(n) for n in self.notes))
        if self.road_frame not in (None, True, False):
            raise DataError(
                f"road_frame must be true, false or null, got {self.road_frame!r}"
            )
        if self.road_period is not None:
            self._set(
                "road_period", positive_float(self.road_period, "road_period", "m")
            )
            if self.road_frame is not True:
                raise DataError(
                    "road_period (a closed track's lap length) needs road_frame true"
                )
        arrays, mask = self._host()
        self._check_mask(mask)
        self._check_values(arrays, mask)

    # ------------------------------------------------------------------ building
    @classmethod
    def from_arrays(
        cls,
        series: Mapping[str, Any] | Sequence[Any],
        *,
        dt: float | None,
        mask: Any = None,
        leader_length: float = 5.0,
        pair_ids: Sequence[int] | None = None,
        name: str = "",
        split: str | None = None,
        notes: Sequence[str] = (),
    ) -> PairSet:
        """Build a validated PairSet from array-likes.

        Tensors keep their floating dtype (integer tensors become float64); any
        other array-like becomes float64. The six series are promoted to one
        common dtype. Masked steps are overwritten with the last valid value of
        their column, so padding is finite whatever the input held there.

        Args:
            series: the six (T, N) series, in :data:`SERIES` order (leader
                position [m], speed [m/s], acceleration [m/s^2], then the
                follower's), or by those names (:meth:`series` gives them so).
            dt: sampling interval [s].
            mask: (T, N) bool prefix mask of valid steps; None means all valid.
            leader_length: leader vehicle length [m].
            pair_ids: (N,) pair ids; None means ``0 .. N-1``.
            name: dataset name or folder.
            split: None, "train" or "test".
            notes: quirk reports to carry along.

        Returns:
            The PairSet, on the device of ``x_lead``.

        Raises:
            DataError: the arrays are not a valid pair set (see the class doc).
        """
        if dt is None:
            raise DataError("dt missing: pass the sampling interval dt [s]")
        raw = _six_series(series)
        series = [_as_float_tensor(a, f) for a, f in zip(raw, SERIES, strict=True)]
        shapes = {tuple(s.shape) for s in series}
        if len(shapes) > 1 or series[0].ndim != 2:
            raise DataError(
                f"series must share one (T, N) shape, got {_shapes(series)}"
            )
        dtype = series[0].dtype
        for s in series[1:]:
            dtype = torch.promote_types(dtype, s.dtype)
        device = series[0].device
        series = [s.to(device=device, dtype=dtype) for s in series]
        if mask is None:
            mask_t = torch.ones(series[0].shape, dtype=torch.bool, device=device)
        else:
            mask_t = torch.as_tensor(mask, device=device).to(torch.bool)
            # Padding only where something is masked: the common all-valid case
            # stays a zero-copy view of the input.
            if mask_t.shape == series[0].shape and not _numpy(mask_t).all():
                series = [edge_pad(s, mask_t) for s in series]
        return cls(
            *series,
            mask=mask_t,
            dt=dt,
            leader_length=leader_length,
            pair_ids=tuple(pair_ids) if pair_ids is not None else (),
            name=name,
            split=split,
            notes=tuple(notes),
        )

    # ---------------------------------------------------------------- properties
    @property
    def n_steps(self) -> int:
        """T, the number of time steps (the longest pair)."""
        return self.mask.shape[0]

    @property
    def n_pairs(self) -> int:
        """N, the number of pairs."""
        return self.mask.shape[1]

    def __len__(self) -> int:
        return self.n_pairs

    @property
    def lengths(self) -> Tensor:
        """(N,) long number of valid steps of each pair."""
        return self.mask.sum(dim=0)

    @property
    def dtype(self) -> torch.dtype:
        """The floating dtype of the six series."""
        return self.x_lead.dtype

    @property
    def device(self) -> torch.device:
        """The device all tensors live on."""
        return self.x_lead.device

    def series(self) -> dict[str, Tensor]:
        """The six (T, N) series by field name, in :data:`SERIES` order."""
        return {f: getattr(self, f) for f in SERIES}

    # ------------------------------------------------------------- derivations
    def to(
        self,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> PairSet:
        """Move to ``device`` and/or cast the six series to floating ``dtype``.

        The mask stays bool.

        Raises:
            TypeError: ``dtype`` is not a floating dtype.
        """
        if dtype is not None and not dtype.is_floating_point:
            raise TypeError(f"PairSet.to: dtype must be floating, got {dtype}")
        moved = {f: t.to(device=device, dtype=dtype) for f, t in self.series().items()}
        return dataclasses.replace(self, **moved, mask=self.mask.to(device=device))

    def steps(self, start: int, stop: int | None = None) -> PairSet:
        """Every pair's steps ``start`` to ``stop`` (exclusive; None: the
        end): the same pairs, a follower then starting from its recorded state
        at ``start``."""
        rows = slice(start, stop)
        return dataclasses.replace(
            self,
            **{field: t[rows] for field, t in self.series().items()},
            mask=self.mask[rows],
        )

    def subset(self, index: Sequence[int] | Tensor) -> PairSet:
        """The pairs at positions ``index`` (0-based positions in this set).

        Args:
            index: (N',) positions (ints or a LongTensor; negatives count from the
                end), or an (N,) bool tensor selecting N' pairs.

        Returns:
            A PairSet of N' pairs with the same T; ``pair_ids`` follow the pairs.

        Raises:
            IndexError: a position is out of range.
        """
        if isinstance(index, Tensor):
            idx = index
        else:
            array = np.asarray(index)
            # np.asarray([]) is float64; an empty selection is still an index.
            idx = torch.from_numpy(array if array.dtype == bool else array.astype(int))
        if idx.dtype == torch.bool:
            if idx.shape != (self.n_pairs,):
                raise IndexError(
                    f"bool index of shape {tuple(idx.shape)} for {self.n_pairs} pairs"
                )
            idx = idx.nonzero().flatten()
        idx = idx.to(device="cpu", dtype=torch.long).flatten()
        bad = (idx < -self.n_pairs) | (idx >= self.n_pairs)
        if bad.any():
            raise IndexError(
                f"pair position {int(idx[bad][0])} out of range for "
                f"{self.n_pairs} pairs"
            )
        idx = idx % max(self.n_pairs, 1)
        picked = {
            f: t.index_select(1, idx.to(t.device)) for f, t in self.series().items()
        }
        return dataclasses.replace(
            self,
            **picked,
            mask=self.mask.index_select(1, idx.to(self.mask.device)),
            pair_ids=tuple(self.pair_ids[i] for i in idx.tolist()),
        )

    def __repr__(self) -> str:
        split = f", split={self.split!r}" if self.split else ""
        return (
            f"PairSet(name={self.name!r}{split}, n_steps={self.n_steps}, "
            f"n_pairs={self.n_pairs}, dt={self.dt}, "
            f"leader_length={self.leader_length}, dtype={self.dtype}, "
            f"device={self.device}, notes={len(self.notes)})"
        )

    # -------------------------------------------------------------- validation
    def _set(self, field: str, value: object) -> None:
        # The dataclass is frozen; normalising fields happens once, here.
        object.__setattr__(self, field, value)

    def _check_tensors(self) -> int:
        series = [getattr(self, f) for f in SERIES]
        for f, t in zip(SERIES, series, strict=True):
            if not isinstance(t, Tensor):
                raise DataError(f"{f} must be a torch.Tensor, got {type(t).__name__}")
        if not isinstance(self.mask, Tensor):
            raise DataError(
                f"mask must be a torch.Tensor, got {type(self.mask).__name__}"
            )
        shape = tuple(self.x_lead.shape)
        if len(shape) != 2 or any(tuple(t.shape) != shape for t in series):
            raise DataError(
                f"series must share one (T, N) shape, got {_shapes(series)}"
            )
        if tuple(self.mask.shape) != shape:
            raise DataError(
                f"mask has shape {tuple(self.mask.shape)} but the series have {shape}"
            )
        if self.mask.dtype != torch.bool:
            raise DataError(f"mask must be bool, got {self.mask.dtype}")
        dtypes = {t.dtype for t in series}
        if len(dtypes) > 1 or not self.x_lead.dtype.is_floating_point:
            raise DataError(
                "series must share one floating dtype, got "
                + ", ".join(
                    f"{f}={t.dtype}" for f, t in zip(SERIES, series, strict=True)
                )
            )
        devices = {t.device for t in (*series, self.mask)}
        if len(devices) > 1:
            raise DataError(
                f"tensors live on several devices: {sorted(map(str, devices))}"
            )
        return shape[1]

    def _where(self, row: int, col: int) -> str:
        """Location text, 1-based as a spreadsheet shows it, plus the pair id."""
        row, col = int(row), int(col)
        return f"at row {row + 1}, column {col + 1} (pair id {self.pair_ids[col]})"

    def _host(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        # Checks run on one host copy in NumPy: a handful of tiny reductions per
        # series would otherwise each cost a device sync (GPU) or a thread-pool
        # dispatch (CPU), which dominates loading time.
        arrays = {f: _numpy(getattr(self, f)) for f in SERIES}
        return arrays, _numpy(self.mask)

    def _check_mask(self, mask: np.ndarray) -> None:
        # A prefix mask never turns back on: False at t and True at t + 1 is a gap.
        gap = ~mask[:-1] & mask[1:]
        if gap.any():
            row, col = np.argwhere(gap)[0]
            raise DataError(
                f"mask is not a prefix: False {self._where(row, col)} "
                f"but True again at row {row + 2}"
            )
        empty = ~mask.any(axis=0)
        if empty.any():
            col = int(np.flatnonzero(empty)[0])
            raise DataError(
                f"pair has no valid step: column {col + 1} "
                f"(pair id {self.pair_ids[col]}) is masked everywhere"
            )

    def _check_values(self, arrays: dict[str, np.ndarray], mask: np.ndarray) -> None:
        for f, values in arrays.items():
            bad = ~np.isfinite(values)
            if bad.any():
                row, col = np.argwhere(bad)[0]
                where = "" if mask[row, col] else " (a padding step)"
                raise DataError(
                    f"non-finite {f} = {values[row, col]} "
                    f"{self._where(row, col)}{where}"
                )
        spacing = arrays["x_lead"] - arrays["x_follow"]  # (T, N)
        bad = (spacing <= 0) & mask
        if bad.any():
            row, col = np.argwhere(bad)[0]
            count = int(bad.sum())
            more = f"; {count} such steps in all" if count > 1 else ""
            raise DataError(
                "non-positive spacing x_lead - x_follow = "
                f"{spacing[row, col]:.6g} m {self._where(row, col)}{more}"
            )


def edge_pad(values: Tensor, mask: Tensor) -> Tensor:
    """Overwrite masked steps with the last valid value of their column.

    Args:
        values: (T, N) series.
        mask: (T, N) bool prefix mask.

    Returns:
        (T, N) series, equal to ``values`` where ``mask`` is True.
    """
    n_steps = values.shape[0]
    last = (mask.sum(dim=0) - 1).clamp_min(0)  # (N,)
    rows = torch.arange(n_steps, device=values.device)[:, None]  # (T, 1)
    src = torch.minimum(rows, last[None, :])  # (T, N)
    return torch.where(mask, values, values.gather(0, src))


def _numpy(tensor: Tensor) -> np.ndarray:
    host = tensor.detach().cpu()
    if host.dtype in (torch.bfloat16, torch.float8_e4m3fn, torch.float8_e5m2):
        host = host.to(torch.float32)  # NumPy has no such dtype; checks only
    return host.numpy()


def _six_series(series: Mapping[str, Any] | Sequence[Any]) -> tuple[Any, ...]:
    """The six series in :data:`SERIES` order, from a mapping by those names
    or a sequence of six (DataError otherwise)."""
    if isinstance(series, Mapping):
        names = set(series)
        if names != set(SERIES):
            missing, extra = set(SERIES) - names, names - set(SERIES)
            raise DataError(
                "series must name the six series "
                f"({', '.join(SERIES)}); missing {sorted(missing)}, "
                f"unknown {sorted(map(str, extra))}"
            )
        return tuple(series[f] for f in SERIES)
    if isinstance(series, Tensor | np.ndarray) or len(series) != 6:
        raise DataError(
            f"series must be the six series ({', '.join(SERIES)}), "
            "as a sequence of six or by name"
        )
    return tuple(series)


def _as_float_tensor(array: Any, field: str) -> Tensor:
    if isinstance(array, Tensor):
        return array if array.dtype.is_floating_point else array.to(torch.float64)
    try:
        return torch.from_numpy(np.array(array, dtype=np.float64))
    except (TypeError, ValueError) as err:
        raise DataError(f"{field} is not numeric: {err}") from None


def _shapes(series: Sequence[Tensor]) -> str:
    return ", ".join(
        f"{f}={tuple(t.shape)}" for f, t in zip(SERIES, series, strict=True)
    )


def positive_float(value: Any, field: str, unit: str) -> float:
    """``value`` as a finite float > 0, else a DataError naming ``field [unit]``."""
    if value is None:
        raise DataError(f"{field} missing: pass {field} [{unit}]")
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{field} must be a number [{unit}], got {value!r}") from None
    if not math.isfinite(out) or out <= 0:
        raise DataError(f"{field} must be finite and > 0 [{unit}], got {out}")
    return out
