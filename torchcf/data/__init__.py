"""Observed car-following data: the PairSet container, the six-CSV reader, and
the named data sets of the ABC paper.

* :mod:`torchcf.data.pairset`: :class:`PairSet`, (T, N) SI tensors plus a prefix
  mask, validated on construction; :class:`DataError` for every data problem.
* :mod:`torchcf.data.reader`: :func:`read_six_csv`, the six-file CSV layout and
  unit conversion.
* :mod:`torchcf.data.registry`: :data:`DATASETS`, :func:`load_pairs` and
  :class:`Cleaning` (the duplicates and short spacings it drops), where the
  files come from (path, ``TORCHCF_DATA``, cache, checked download), the splits
  and the quirks of each data set.
* :mod:`torchcf.data.splits`: :func:`split_pairs` and :func:`kfold_split`, the
  training / test pairs of a data set (its own split or seeded k-fold). A run's
  configuration reaches them through :func:`torchcf.config.load_split`.
"""

from torchcf.data.pairset import DataError, PairSet
from torchcf.data.reader import read_six_csv
from torchcf.data.registry import (
    DATASETS,
    Cleaning,
    DatasetSpec,
    load_pairs,
    resolve_data_root,
)
from torchcf.data.splits import kfold_split, split_pairs

__all__ = [
    "DATASETS",
    "Cleaning",
    "DataError",
    "DatasetSpec",
    "PairSet",
    "kfold_split",
    "load_pairs",
    "read_six_csv",
    "resolve_data_root",
    "split_pairs",
]
