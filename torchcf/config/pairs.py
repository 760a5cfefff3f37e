"""From a run's ``data`` section to its pairs: the one step that reads a
:class:`~torchcf.config.DataConfig` and calls :mod:`torchcf.data` with plain
arguments (which is why it lives here, above both).

    train, test = load_split(cfg.data)
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from torchcf.data import Cleaning, DataError, PairSet
from torchcf.data.importer import extract_source
from torchcf.data.splits import split_pairs

from .schema import DataConfig

__all__ = ["load_index", "load_split"]


def load_index(data: DataConfig, split: str = "train") -> pd.DataFrame | None:
    """Where the pairs of one side of the split came from, one row per pair
    id (``run``, ``follower``, ...): a raw source's whole index, whose row is
    a pair's id in the full set; a folder's ``index.csv`` rows of ``split``,
    in the order of its files, which is a pair's id there. None where the
    data keep no index (a named data set, a folder without ``index.csv``) or
    it cannot be read.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.config import DataConfig, load_index
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     rows = "run,follower,split\\n1,7,train\\n1,8,test\\n2,9,train\\n"
        ...     _ = (Path(folder) / "index.csv").write_text(rows)
        ...     index = load_index(DataConfig(path=folder))
        >>> index["follower"].tolist(), load_index(DataConfig(name="car-model-1"))
        ([7, 9], None)
    """
    if data.raw is not None:
        raw = data.raw
        index = extract_source(
            raw.source,
            raw.format,
            reader_options=raw.reader_options(),
            options=raw.extract_options(),
        ).index
        return index.reset_index(drop=True)
    if data.name is None and data.path is not None:
        path = Path(data.path) / "index.csv"
        if not path.is_file():
            return None
        try:
            index = pd.read_csv(path)
        except (OSError, ValueError):
            return None
    else:
        return None
    if "split" not in index.columns:
        return None
    return index[index["split"] == split].reset_index(drop=True)


def load_split(
    data: DataConfig, *, download: bool = True, require_test: bool = True
) -> tuple[PairSet, PairSet | None]:
    """Load the training and test pairs a run configuration asks for.

    A raw source is extracted and split by source group
    (:func:`torchcf.data.importer.extract_source`); a named data set or folder is
    split its own way or by seeded k-fold (:func:`torchcf.data.splits.split_pairs`).

    Args:
        data: the ``data`` section of the run configuration.
        download: allow fetching missing files of a named set into the cache.
        require_test: data without a test split (a raw source with
            ``test_fraction`` 0, a folder extracted so: no ``Testing/``) are an
            error, as evaluating needs test pairs; False gives None as the test
            pairs instead (training needs none).

    Returns:
        ``(train, test)`` PairSets in SI units (float64, as loaded); ``test`` is
        None only with ``require_test=False``.

    Raises:
        DataError: the data cannot be loaded, test pairs are required and there
            are none, or the k-fold split is impossible.

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.config import DataConfig, load_split
        >>> from torchcf.data.writer import write_six_csv
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(synthetic_pairs(get_model("idm"), idm, 4, 60), folder)
        ...     data = DataConfig(path=folder, dt=0.1, split="kfold", folds=2)
        ...     train, test = load_split(data)
        >>> train.n_pairs, test.n_pairs
        (2, 2)
    """
    if data.raw is not None:
        raw = data.raw
        extraction = extract_source(
            raw.source,
            raw.format,
            reader_options=raw.reader_options(),
            options=raw.extract_options(),
        )
        if extraction.test is None and require_test:
            raise DataError(
                "no test split: data.raw.test_fraction is 0, and evaluating a run "
                "needs test pairs (set data.raw.test_fraction > 0)"
            )
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
        require_test=require_test,
    )
