"""From a run's ``data`` section to its pairs: the one step that reads a
:class:`~torchcf.config.DataConfig` and calls :mod:`torchcf.data` with plain
arguments (which is why it lives here, above both).

    train, test = load_split(cfg.data)
"""

from __future__ import annotations

from torchcf.data import Cleaning, DataError, PairSet
from torchcf.data.importer import extract_source
from torchcf.data.splits import split_pairs

from .schema import DataConfig

__all__ = ["load_split"]


def load_split(data: DataConfig, *, download: bool = True) -> tuple[PairSet, PairSet]:
    """Load the training and test pairs a run configuration asks for.

    A raw source is extracted and split by source group
    (:func:`torchcf.data.importer.extract_source`); a named data set or folder is
    split its own way or by seeded k-fold (:func:`torchcf.data.splits.split_pairs`).

    Args:
        data: the ``data`` section of the run configuration.
        download: allow fetching missing files of a named set into the cache.

    Returns:
        ``(train, test)`` PairSets in SI units (float64, as loaded).

    Raises:
        DataError: the data cannot be loaded, a raw source gives no test pairs,
            or the k-fold split is impossible.
    """
    if data.raw is not None:
        raw = data.raw
        extraction = extract_source(
            raw.source,
            raw.format,
            reader_options=raw.reader_options(),
            options=raw.extract_options(),
        )
        if extraction.test is None:
            raise DataError("data.raw.test_fraction is 0: a run needs test pairs")
        return extraction.train, extraction.test
    source = data.name if data.name is not None else data.path
    if source is None:
        raise DataError("data: give a dataset name or a folder path")
    return split_pairs(
        source,
        data.split,
        folds=data.folds,
        fold=data.fold,
        seed=data.split_seed,
        units=data.units,
        dt=data.dt,
        leader_length=data.leader_length,
        data_root=data.root,
        download=download,
        cleaning=Cleaning(data.drop_duplicates, data.min_spacing),
    )
