"""Twins tested as one family (torchcf.diagnose.selection.attribution._judge with
diagnose.families "signature"; significance.max_flip_test)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.diagnose.rows import row_of
from torchcf.config import validate_config
from torchcf.diagnose.selection.attribution import _judge, families
from torchcf.diagnose.significance import max_flip_test, sign_flip_test


def _settings(families: str = "signature"):
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},
            "models": ["idm"],
            "diagnose": {"families": families, "permutations": 4000},
        }
    )
    return cfg.diagnose


def _row(token: str, drops: np.ndarray, gain: float, estimate: float = 0.8):
    before = np.exp(drops)  # log(before / after) = drops, after = 1
    return row_of(
        token,
        gain=gain,
        active=True,
        p_value=sign_flip_test(drops, 4000)[1],
        estimate={"value": estimate},
        per_pair={"before": before.tolist(), "after": [1.0] * drops.size},
    )


def test_one_member_is_the_sign_flip_test():
    drops = np.random.default_rng(1).normal(0.2, 1.0, 25)
    assert max_flip_test([drops], 5000, seed=3)[0] == sign_flip_test(drops, 5000, 3)[1]


def test_copies_of_one_member_cost_no_power():
    """The largest statistic over identical twins has the one member's
    p-value: splitting the level between them is what the family avoids."""
    drops = np.random.default_rng(2).normal(0.3, 1.0, 30)
    one, _ = max_flip_test([drops], 5000)
    three, _ = max_flip_test([drops, drops, drops], 5000)
    assert three == one


def test_the_family_keeps_its_level_under_the_null():
    """Twins with correlated drops and no effect: the family is rejected at
    5 % in about 5 % of draws (it is exact)."""
    rng = np.random.default_rng(0)
    rejected = 0
    draws = 400
    for _ in range(draws):
        common = rng.normal(size=20)
        members = [common + 0.5 * rng.normal(size=20) for _ in range(3)]
        p, _ = max_flip_test(members, 999, seed=int(rng.integers(1 << 30)))
        rejected += p <= 0.05
    assert rejected / draws == pytest.approx(0.05, abs=0.03)


def test_twins_form_one_family_at_the_place_of_the_first():
    rows = [row_of("delay"), row_of("sync"), row_of("lag"), row_of("offset")]
    pointed = {
        "delay": ["response lag"],
        "sync": ["response lag"],
        "lag": ["response lag", "command strength"],
    }
    grouped = families(rows, pointed, "signature")
    assert [[r.token for r in g] for g in grouped] == [
        ["delay", "sync", "lag"],
        ["offset"],
    ]
    alone = families(rows, pointed, "none")
    assert [len(g) for g in alone] == [1, 1, 1, 1]


def test_a_family_chooses_one_member_and_names_its_twins():
    rng = np.random.default_rng(5)
    signal = rng.normal(0.35, 0.5, 40)
    rows = [
        _row("delay", signal + 0.1 * rng.normal(size=40), gain=0.12),
        _row("sync", signal + 0.1 * rng.normal(size=40), gain=0.14),
        _row("lag", signal + 0.1 * rng.normal(size=40), gain=0.18),
        _row("offset", rng.normal(0.0, 0.5, 40), gain=0.01),
    ]
    pointed = {e: ["response lag"] for e in ("delay", "sync", "lag")}
    judged = _judge(rows, pointed, 0.025, _settings())
    by = {r.token: r for r in judged}
    assert [r.token for r in judged if r.significant] == ["lag"]
    assert by["lag"].family == ["delay", "sync", "lag"]
    assert by["lag"].family_p_value < 0.0125
    assert {by[t].level for t in ("delay", "sync", "lag")} == {by["lag"].level}
    assert by["offset"].family == [] and by["offset"].family_p_value is None
    # one by one, the twins split the level: the first of four tests gets less
    # than the first of two families
    alone = _judge(
        [_row(r.token, np.log(np.array(r.per_pair["before"])), r.gain) for r in rows],
        pointed,
        0.025,
        _settings("none"),
    )
    assert alone[0].level < judged[0].level


def test_a_recording_twin_gives_way_to_a_behavioural_one_within_its_margin():
    rng = np.random.default_rng(7)
    signal = rng.normal(0.4, 0.4, 40)
    rows = [
        _row("delay", signal, gain=0.20),
        _row("sync", signal + 0.05 * rng.normal(size=40), gain=0.22),
    ]
    pointed = {e: ["response lag"] for e in ("delay", "sync")}
    judged = _judge(rows, pointed, 0.025, _settings())
    assert [r.token for r in judged if r.significant] == ["delay"]
