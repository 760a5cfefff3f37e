"""load_pairs: named sets (real data when TORCHCF_DATA is set), quirks, the checked
download into the cache (offline, through a replaced ``_fetch``), and folders."""

from __future__ import annotations

import hashlib
import json
import logging
import urllib.error
import urllib.parse
from pathlib import Path

import pandas as pd
import pytest
import torch

from torchcf.data import (
    DATASETS,
    Cleaning,
    DataError,
    PairSet,
    load_pairs,
    registry,
    resolve_data_root,
)
from torchcf.data.pairset import SERIES
from torchcf.data.reader import FILES
from torchcf.data.registry import short_note


def assert_same(a: PairSet, b: PairSet) -> None:
    for f in (*SERIES, "mask"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    assert (a.pair_ids, a.dt, a.leader_length, a.name, a.split, a.notes) == (
        b.pair_ids,
        b.dt,
        b.leader_length,
        b.name,
        b.split,
        b.notes,
    )


# ------------------------------------------------------------------ real data
# README.txt: T x N of the full set, and the split sizes before de-duplication.
REAL_SHAPES = {
    "ngsim-i80": (350, 150, 105, 45),
    "car-model-1": (541, 96, 67, 28),
    "car-model-2": (576, 64, 45, 18),
}


@pytest.mark.parametrize("name", list(REAL_SHAPES))
def test_real_shapes_and_pair_ids(real_data: Path, name: str) -> None:
    n_steps, n_full, n_train, n_test = REAL_SHAPES[name]
    load = dict(download=False, cleaning=Cleaning(drop_duplicates=False))
    full = load_pairs(name, **load)
    assert (full.n_steps, full.n_pairs) == (n_steps, n_full)
    assert full.pair_ids == tuple(range(n_full))
    assert (full.name, full.split, full.dt) == (name, None, 0.1)
    for split, n_pairs in (("train", n_train), ("test", n_test)):
        part = load_pairs(name, split, **load)
        assert (part.n_steps, part.n_pairs, part.split) == (n_steps, n_pairs, split)
        assert bool(part.mask.all()) and part.dtype == torch.float64
        # pair_ids name the full-set column each split column copies.
        ids = list(part.pair_ids)
        for f in (*SERIES, "mask"):
            assert torch.equal(getattr(full, f)[:, ids], getattr(part, f)), f
        assert len(set(part.pair_ids)) == n_pairs


def test_real_ngsim_is_converted_to_metres(real_data: Path) -> None:
    pairs = load_pairs("ngsim-i80", download=False)
    for field in ("x_lead", "v_follow", "a_follow"):
        raw = pd.read_csv(
            real_data / DATASETS["ngsim-i80"].folder / FILES[field], header=None
        ).to_numpy()
        assert torch.equal(getattr(pairs, field), torch.from_numpy(raw * 0.3048))
    assert 0.3048 * 32 < float(pairs.x_lead.min()) < 0.3048 * 1543


def test_real_ngsim_short_spacing(real_data: Path, caplog, monkeypatch) -> None:
    # A note is logged once per process: forget those an earlier test logged.
    monkeypatch.setattr("torchcf.data.registry._ANNOUNCED", set())
    short = (6, 13, 31, 61, 70, 95, 110, 117, 120)
    with caplog.at_level(logging.WARNING, logger="torchcf.data"):
        pairs = load_pairs("ngsim-i80", download=False)
    (note,) = pairs.notes
    assert note.startswith("9 pairs with a minimum front-to-front spacing under 4.572")
    assert ", ".join(map(str, short)) in note
    assert short_note(note) in caplog.text and "docs/data.md" in caplog.text
    kept = load_pairs("ngsim-i80", download=False, cleaning=Cleaning(min_spacing=4.572))
    assert kept.n_pairs == 141 and not set(short) & set(kept.pair_ids)
    assert "dropped 9 pairs with a minimum spacing under 4.572 m" in kept.notes[1]
    assert float((kept.x_lead - kept.x_follow).min()) >= 4.572


def test_real_car_model_1_column_outside_splits(real_data: Path) -> None:
    assert load_pairs("car-model-1", download=False).notes == ()
    for split in ("train", "test"):
        (note,) = load_pairs("car-model-1", split, download=False).notes
        assert note.startswith("full-set column 44 (0-based pair id) is in neither")
        assert "67 + 28 = 95 of 96" in note


def test_real_car_model_2_duplicates_and_leak(real_data: Path) -> None:
    full = load_pairs("car-model-2", download=False)
    assert full.n_pairs == 62 and not {16, 17} & set(full.pair_ids)
    assert any("pair ids 6 & 16, 7 & 17" in n for n in full.notes)

    test = load_pairs("car-model-2", "test", download=False)
    kept = load_pairs(
        "car-model-2", "test", download=False, cleaning=Cleaning(drop_duplicates=False)
    )
    assert (test.n_pairs, kept.n_pairs) == (17, 18)
    assert 16 in kept.pair_ids and 16 not in test.pair_ids
    assert any(n.startswith("Testing/ pair id 16") for n in test.notes)
    assert any("kept (drop_duplicates=False)" in n for n in kept.notes)

    train = load_pairs("car-model-2", "train", download=False)
    assert train.n_pairs == 44 and 6 in train.pair_ids  # both copies of 7/17 there


def test_real_data_root_forms(real_data: Path, monkeypatch) -> None:
    # The abc-paper folder (holding data/HDV, data/AV) works as well.
    assert resolve_data_root("car-model-1", data_root=real_data.parent) == real_data
    monkeypatch.setenv("TORCHCF_DATA", str(real_data.parent))
    assert resolve_data_root("car-model-1", "test") == real_data


# ------------------------------------------------------------------- download
@pytest.fixture
def cache(tmp_path: Path, monkeypatch) -> Path:
    """An empty cache and no TORCHCF_DATA: a named set must be downloaded."""
    monkeypatch.delenv("TORCHCF_DATA", raising=False)
    monkeypatch.setenv("TORCHCF_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache" / "abc-paper" / "data"


def serve(root: Path, calls: list[str], corrupt: str | None = None):
    """A ``_fetch`` that serves the files under ``root`` by their URL."""
    prefix = registry.SOURCE_URL + "/"

    def fetch(url: str) -> bytes:
        calls.append(url)
        assert url.startswith(prefix) and " " not in url
        rel = urllib.parse.unquote(url[len(prefix) :])
        payload = (root / rel).read_bytes()
        if corrupt is not None and rel.endswith(corrupt):
            payload = payload[:100] + bytes([payload[100] ^ 1]) + payload[101:]
        return payload

    return fetch


def test_download_into_cache(real_data: Path, cache: Path, monkeypatch) -> None:
    calls: list[str] = []
    monkeypatch.setattr(registry, "_fetch", serve(real_data, calls))
    pairs = load_pairs("car-model-2")
    assert len(calls) == 6 and all("/AV/CAR%20MODEL%20II/" in u for u in calls)
    folder = cache / "AV" / "CAR MODEL II"
    assert sorted(p.name for p in folder.iterdir()) == sorted(FILES.values())
    assert_same(pairs, load_pairs("car-model-2", data_root=real_data))

    load_pairs("car-model-2")  # a cache hit fetches nothing
    assert len(calls) == 6
    # A split also needs the two split folders (pair ids, leak), not more.
    assert_same(
        load_pairs("car-model-2", "test"),
        load_pairs("car-model-2", "test", data_root=real_data),
    )
    assert len(calls) == 18 and sum("/Testing/" in u for u in calls) == 6


def test_corrupted_download_saves_nothing(
    real_data: Path, cache: Path, monkeypatch
) -> None:
    calls: list[str] = []
    monkeypatch.setattr(registry, "_fetch", serve(real_data, calls, "Leading Acc.csv"))
    with pytest.raises(DataError, match=r"checksum mismatch for 'data/AV/CAR MODEL I/"):
        load_pairs("car-model-1")
    folder = cache / "AV" / "CAR MODEL I"
    assert not (folder / "Leading Acc.csv").exists()
    assert not list(folder.glob(".*"))  # no partial temp file either
    monkeypatch.setattr(registry, "_fetch", serve(real_data, calls))
    assert load_pairs("car-model-1").n_pairs == 96  # only the missing files again


def test_interrupted_write_leaves_no_file(cache: Path, monkeypatch) -> None:
    payload = b"1,2\n"
    rel = "AV/CAR MODEL I/Leading Acc.csv"
    monkeypatch.setattr(registry, "_checksums", lambda: {f"data/{rel}": _sha(payload)})

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(registry, "_fetch", lambda url: payload)
    monkeypatch.setattr(registry.os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        registry._download(rel, cache / rel)
    assert not list((cache / "AV" / "CAR MODEL I").iterdir())


def _sha(payload: bytes) -> str:
    return hashlib.sha256(payload).hexdigest()


def test_no_checksum_entry(cache: Path, monkeypatch) -> None:
    monkeypatch.setattr(registry, "_checksums", dict)
    monkeypatch.setattr(registry, "_fetch", lambda url: pytest.fail("fetched"))
    with pytest.raises(DataError, match="no checksum for 'data/HDV/NGSIM I_80/"):
        load_pairs("ngsim-i80")


def test_checksums_cover_every_registered_file() -> None:
    sums = registry._checksums()
    for name in DATASETS:
        for rel in registry._needed_files(name, "train"):
            assert len(sums[f"data/{rel}"]) == 64


def test_offline_without_copy(cache: Path, monkeypatch, tmp_path: Path) -> None:
    def offline(url: str) -> bytes:
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(registry, "_fetch", offline)
    with pytest.raises(
        DataError,
        match=r"dataset 'ngsim-i80' not found: looked in data_root= \(not given\), "
        r"\$TORCHCF_DATA \(not set\), the cache .*, and the download failed "
        r"\(URLError.*\)\. Set TORCHCF_DATA .*, pass data_root=, or allow the "
        r"download",
    ):
        load_pairs("ngsim-i80")

    monkeypatch.setattr(registry, "_fetch", lambda url: pytest.fail("fetched"))
    monkeypatch.setenv("TORCHCF_DATA", str(tmp_path))
    with pytest.raises(
        DataError, match=r"TORCHCF_DATA='.*' \(no 'HDV.*download is off"
    ):
        load_pairs("ngsim-i80", "test", download=False)


def test_explicit_data_root_must_hold_the_files(tmp_path: Path) -> None:
    with pytest.raises(DataError, match=r"data_root='.*' has no file 'AV/CAR MODEL I/"):
        load_pairs("car-model-1", data_root=tmp_path)


def test_cache_dir_order(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.setenv("TORCHCF_CACHE", str(tmp_path / "a"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "b"))
    assert registry.cache_dir() == tmp_path / "a"
    monkeypatch.delenv("TORCHCF_CACHE")
    assert registry.cache_dir() == tmp_path / "b" / "torchcf"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert registry.cache_dir() == tmp_path / "home" / ".cache" / "torchcf"


# -------------------------------------------- quirks on a synthetic named tree
@pytest.fixture
def tree(write_six, make_arrays) -> Path:
    """A data root whose "car-model-2" has a duplicate, a leak, an unsplit column.

    Full set: 5 pairs, column 3 copies column 1. Trajectory/ = columns (1, 0);
    Testing/ = columns (3, 2), so its first column repeats a training pair;
    column 4 is in neither split.
    """
    full = make_arrays(n_steps=4, n_pairs=5)
    for values in full.values():
        values[:, 3] = values[:, 1]
    folder = "root/" + DATASETS["car-model-2"].folder
    write_six(folder, arrays=full)
    write_six(folder + "/Trajectory", arrays={k: v[:, [1, 0]] for k, v in full.items()})
    root = write_six(
        folder + "/Testing", arrays={k: v[:, [3, 2]] for k, v in full.items()}
    )
    return root.parents[2]


def test_synthetic_quirks(tree: Path) -> None:
    full = load_pairs("car-model-2", data_root=tree)
    assert full.pair_ids == (0, 1, 2, 4)
    assert full.notes == (
        "the full set holds exact duplicates (all six series equal): pair ids 1 & 3; "
        "dropped the later copy (pair id 3), 4 of 5 pairs kept (drop_duplicates=True)",
    )
    train = load_pairs("car-model-2", "train", data_root=tree)
    assert train.pair_ids == (1, 0)
    test = load_pairs("car-model-2", "test", data_root=tree)
    assert test.pair_ids == (2,)
    assert test.notes == (
        "full-set columns 1 & 3 are identical; the split columns that copy them got "
        "distinct pair ids in order (Trajectory/: 1; Testing/: 3)",
        "full-set column 4 (0-based pair id) is in neither Trajectory/ nor Testing/: "
        "2 + 2 = 4 of 5 pairs are split",
        "Testing/ pair id 3 exactly duplicates Trajectory/ pair id 1 (a train-to-test "
        "leak); dropped "
        "from the test split, 1 of 2 pairs kept (drop_duplicates=True)",
    )
    kept = load_pairs(
        "car-model-2", "test", data_root=tree, cleaning=Cleaning(drop_duplicates=False)
    )
    assert kept.pair_ids == (3, 2)


def test_split_column_not_in_full_set(tree: Path, write_six, make_arrays) -> None:
    other = {k: v + 1000.0 for k, v in make_arrays(n_steps=4, n_pairs=1).items()}
    write_six("root/AV/CAR MODEL II/Testing", arrays=other)
    with pytest.raises(DataError, match=r"column 1 of '.*Testing' equals no column"):
        load_pairs("car-model-2", "test", data_root=tree)


# ----------------------------------------------------------- loading a folder
def test_folder_dt_and_units_from_meta(write_six, make_arrays) -> None:
    folder = write_six()
    with pytest.raises(DataError, match=r"dt missing: pass dt= or write meta.json"):
        load_pairs(folder)
    assert load_pairs(str(folder), dt=0.5).dt == 0.5
    meta = {"dt": 0.2, "units": "ft", "leader_length": 4.5}
    (folder / "meta.json").write_text(json.dumps(meta))
    pairs = load_pairs(folder)
    assert (pairs.dt, pairs.leader_length, pairs.name) == (0.2, 4.5, str(folder))
    expected = torch.from_numpy(make_arrays()["x_lead"] * 0.3048)
    assert torch.equal(pairs.x_lead, expected)
    assert load_pairs(folder, units="m", dt=0.1).dt == 0.1  # arguments win
    (folder / "meta.json").write_text(json.dumps({"dt": 0.1, "speed": "fast"}))
    with pytest.raises(DataError, match=r"meta.json' must be an object with keys"):
        load_pairs(folder)


@pytest.mark.parametrize("dt", [0.0, -0.1])
def test_folder_bad_dt(write_six, dt: float) -> None:
    with pytest.raises(DataError, match="dt must be finite and > 0"):
        load_pairs(write_six(), dt=dt)


def test_folder_errors_carry_file_row_column(write_six) -> None:
    folder = write_six(text={"x_follow": "1,2,3\n1,2,x\n"})
    with pytest.raises(
        DataError, match=r"'x' at row 2, column 3 of 'Following Position.csv'"
    ):
        load_pairs(folder, dt=0.1)


def test_bad_split_units_name(write_six) -> None:
    with pytest.raises(DataError, match=r"split must be None, 'train' or 'test'"):
        load_pairs("ngsim-i80", "validation")
    with pytest.raises(DataError, match=r"units must be one of 'm', 'ft', got 'mi'"):
        load_pairs(write_six(), units="mi", dt=0.1)
    with pytest.raises(
        DataError,
        match=r"unknown dataset 'ngsim': neither a registered name "
        r"\(ngsim-i80, car-model-1, car-model-2\) nor an existing folder",
    ):
        load_pairs("ngsim")


def test_folder_split_and_duplicates(write_six, make_arrays) -> None:
    arrays = make_arrays()
    for values in arrays.values():
        values[:, 2] = values[:, 0]
    write_six("set/Testing", arrays=arrays)
    folder = write_six("set")
    test = load_pairs(folder, "test", dt=0.1)
    assert (test.split, test.pair_ids) == ("test", (0, 1))
    assert "pair ids 0 & 2" in test.notes[0]
    kept = load_pairs(folder, "test", dt=0.1, cleaning=Cleaning(drop_duplicates=False))
    assert kept.pair_ids == (0, 1, 2) and "all kept" in kept.notes[0]
    with pytest.raises(DataError, match=r"not a folder: '.*Trajectory'"):
        load_pairs(folder, "train", dt=0.1)


def test_min_spacing_and_short_spacing_note(
    write_six, make_arrays, caplog, monkeypatch
) -> None:
    monkeypatch.setattr("torchcf.data.registry._ANNOUNCED", set())  # logged once
    arrays = make_arrays()  # spacings 20, 23 and 26 m
    folder = write_six(arrays=arrays)
    pairs = load_pairs(folder, dt=0.1, cleaning=Cleaning(min_spacing=21.0))
    assert pairs.pair_ids == (1, 2)
    assert pairs.notes == (
        "dropped 1 pair with a minimum spacing under 21.0 m (min_spacing): pair id 0; "
        "2 of 3 pairs kept",
    )
    with pytest.raises(DataError, match="drops all 3 pairs"):
        load_pairs(folder, dt=0.1, cleaning=Cleaning(min_spacing=30.0))
    with pytest.raises(DataError, match="min_spacing must be finite and >= 0"):
        load_pairs(folder, dt=0.1, cleaning=Cleaning(min_spacing=-1.0))

    arrays["x_follow"][2, 1] = arrays["x_lead"][2, 1] - 3.0
    with caplog.at_level(logging.WARNING, logger="torchcf.data"):
        pairs = load_pairs(write_six("short", arrays=arrays), dt=0.1)
    assert pairs.notes == (
        "1 pair with a minimum front-to-front spacing under 4.572 m (15 ft), likely "
        "position errors: pair id 1 (smallest 3 m, pair id 1); min_spacing= drops them",
    )
    assert "pair id 1 (smallest 3 m" in caplog.text


def test_notes_are_logged_once_short_and_say_where_explained(
    tree: Path, caplog, monkeypatch
) -> None:
    """Both splits of a set with a duplicate, a leak and an unsplit column: one
    line per load, each note in its first clause, the leak once (the test
    split's note differs from the training split's only after its ';'), and
    where the quirks are explained; the full notes stay in PairSet.notes."""
    monkeypatch.setattr("torchcf.data.registry._ANNOUNCED", set())
    with caplog.at_level(logging.INFO, logger="torchcf.data"):
        train = load_pairs("car-model-2", "train", data_root=tree)
        test = load_pairs("car-model-2", "test", data_root=tree)
        load_pairs("car-model-2", "test", data_root=tree)  # nothing new
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1, lines  # the test split adds nothing the train split said
    (line,) = lines
    assert line.startswith("car-model-2: ") and "docs/data.md" in line
    assert line.count("Testing/ pair id 3 exactly duplicates") == 1
    assert "leak:" not in line and "(a train-to-test leak)" in line
    for note in (*train.notes, *test.notes):
        assert short_note(note) in line
    assert any("; dropped from the test split" in n for n in test.notes)
    assert "; dropped from the test split" not in line
