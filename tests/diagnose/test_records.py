"""The loop's results as records: each one's ``to_json`` is the object
``loop.json`` (or the attribution's ledger) holds, key order included, and its
``from_json`` reads that object back to the same record; a row kept by a ledger
written before the records reads back as well."""

from __future__ import annotations

import json

import pytest

from torchcf.diagnose.arms.absorption import (
    Absorption,
    Profile,
    ProfileAbsorption,
    SteadyShift,
    absorbed_from_json,
)
from torchcf.diagnose.arms.identifiability import Partner
from torchcf.diagnose.report.outcome import (
    ChangeOnTest,
    EffectPosterior,
    ParamSpread,
    SearchBudget,
    Unexplained,
)
from torchcf.diagnose.selection.tested import Detectable, EffectTest, Rung, SharedValue
from torchcf.diagnose.signatures.families import SignatureRow
from torchcf.diagnose.signatures.series import ResidualRow
from torchcf.diagnose.significance import PairedChange
from torchcf.runs.directory import RunDir
from torchcf.system.files import RunFileError

from .rows import row_of

DRIVER = Absorption(
    parameter="s0",
    model="llcs",
    effect_parameter="d_offset",
    correlation=0.93,
    slope=1.02,
    n_pairs=6,
    shift=None,
    absorbed=True,
)
PROFILED = ProfileAbsorption(
    parameter="s0",
    model="idm",
    effect_parameter="t_sync",
    correlation=-0.8,
    slope=-0.5,
    shift=0.25,
    n_pairs=12,
    absorbed=True,
    profile=Profile((-1.0, 0.0, 1.0), (1.2, 1.0, 1.1)),
    steady=SteadyShift(
        speed=12.5,
        gap_slope=-1.0,
        gap_r=-0.99,
        time_gap_slope=None,
        time_gap_r=None,
        n_pairs=12,
    ),
)
DETECTABLE = Detectable(
    unit="s",
    level=0.0125,
    at_level={"below": None, "above": 0.4},
    first_level=0.0125,
    if_first={"below": None, "above": 0.4},
    tried={"above": (Rung(0.2, 0.01, 0.3), Rung(0.4, 0.08, 0.004))},
)


def _through_a_file(raw):
    """``raw`` as a JSON file gives it back."""
    return json.loads(json.dumps(raw))


def _round_trip(record, read=None):
    """``record``'s JSON read back: the same record, the same object."""
    read = type(record).from_json if read is None else read
    raw = record.to_json()
    back = read(_through_a_file(raw))
    assert back.to_json() == _through_a_file(raw)
    assert list(back.to_json()) == list(raw)  # key order included
    return back


@pytest.mark.parametrize(
    "record",
    [
        DRIVER,
        PairedChange(pairs=17, better=11, change=-0.12, p_value=0.03),
        Partner(partner="s0", r=0.91, traded_off=True, n_pairs=24),
        SignatureRow(
            signature="response lag",
            unit="s",
            mean=0.4,
            median=0.35,
            n_pairs=20,
            p_value=0.001,
            found=True,
            points_to=("delay", "sync", "lag"),
            family=None,
        ),
        ResidualRow(
            channel="spacing",
            test="own speed",
            statistic=12.0,
            p_value=None,
            effect={"v": 0.1, "v2": None},
            n=4000,
            n_pairs=20,
        ),
        Unexplained(
            signature="drift",
            mean=0.01,
            unit="m/s",
            p_value=0.002,
            tested_not_chosen=(),
            family="parameters that drift within a window",
        ),
        SearchBudget(
            population=20,
            local_copies=4,
            rounds=8,
            refit_rounds=4,
            validation_warmup=0.0,
            n_particles=5000,
            run_particles=20000,
            n_train=40,
        ),
        ParamSpread(n=30, median=0.8, q05=0.5, q95=1.1, mean=0.81),
        EffectPosterior(
            share=0.7, params={"t_delay": ParamSpread(n=30, median=0.8, mean=0.8)}
        ),
        ChangeOnTest(run=PairedChange(17, 11, -0.12, 0.03), reference=None),
        SharedValue(
            value={"t_sync": 0.3},
            prior={"t_sync": (-1.0, 1.0)},
            interval={"t_sync": [0.2, 0.4]},
        ),
        DETECTABLE,
    ],
    ids=lambda record: type(record).__name__,
)
def test_a_record_reads_back_from_its_json(record):
    assert _round_trip(record) == record


def test_absorptions_keep_their_files_key_order():
    assert list(DRIVER.to_json()) == [
        "parameter",
        "model",
        "effect_parameter",
        "correlation",
        "slope",
        "n_pairs",
        "shift",
        "absorbed",
    ]
    raw = PROFILED.to_json()
    assert list(raw) == [
        "parameter",
        "model",
        "effect_parameter",
        "correlation",
        "slope",
        "shift",
        "n_pairs",
        "absorbed",
        "profile",
        "steady",
    ]
    assert raw["profile"] == {
        "values": [-1.0, 0.0, 1.0],
        "relative_fit": [1.2, 1.0, 1.1],
    }
    back = _round_trip(PROFILED, absorbed_from_json)
    assert isinstance(back, ProfileAbsorption) and back.steady == PROFILED.steady
    assert isinstance(absorbed_from_json(DRIVER.to_json()), Absorption)


def test_an_effect_without_particles_is_written_as_its_count_alone():
    assert ParamSpread(n=0).to_json() == {"n": 0}
    assert ParamSpread.from_json({"n": 0}) == ParamSpread(n=0)


def test_a_row_reads_back_with_its_parts_as_records():
    row = row_of("sync", gain=0.2, level=0.0125, significant=True)
    row.shared = SharedValue({"t_sync": 0.3}, {"t_sync": (-1.0, 1.0)}, None)
    row.absorbed_by = PROFILED
    row.detectable = DETECTABLE
    raw = row.to_json()
    back = EffectTest.from_json(_through_a_file(raw))
    assert back.shared == row.shared and back.detectable == DETECTABLE
    assert back.absorbed_by == PROFILED
    assert list(back.to_json()) == list(raw)
    unsized = row_of("asymmetry")  # no sizes asked: no key at all
    assert "detectable" not in unsized.to_json()
    assert EffectTest.from_json(unsized.to_json()).to_json() == unsized.to_json()


def test_a_row_kept_by_an_earlier_ledger_reads_back():
    """A ledger written before the records kept each row as a plain dict (a
    shared effect's box a tuple, the absorption and the sizes dicts)."""
    kept = row_of("offset").to_json() | {
        "shared": {
            "value": {"d_offset": 0.5},
            "prior": {"d_offset": (-2.0, 2.0)},
            "interval": None,
        },
        "absorbed_by": DRIVER.to_json(),
        "detectable": DETECTABLE.to_json(),
    }
    row = EffectTest.from_json(kept)
    assert row.shared.prior == {"d_offset": (-2.0, 2.0)}
    assert row.absorbed_by == DRIVER and row.detectable == DETECTABLE
    assert _through_a_file(row.to_json()) == _through_a_file(kept)


def test_the_loop_reads_a_runs_metrics_as_its_evaluation(tmp_path):
    """An evaluation this release does not read stops the loop with one line
    that says what to do."""
    (tmp_path / "metrics.json").write_text('{"hybrid": {"ws": 1.0}}')
    with pytest.raises(RunFileError, match="evaluate the run again"):
        RunDir(tmp_path).read_metrics()
