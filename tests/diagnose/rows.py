"""Rows of the selection for tests that judge rows without running arms."""

from __future__ import annotations

from torchcf.diagnose.selection.tested import EffectTest
from torchcf.models.effects import parse_effect


def row_of(token: str, **verdict) -> EffectTest:
    """An effect's test with no measurement (gains 0, nothing estimated) but
    the given fields (``gain``, ``level``, ``significant``...)."""
    row = EffectTest(
        effect=parse_effect(token),
        fit_gain=0.0,
        base_fit_gain=0.0,
        gain=0.0,
        statistic=0.0,
        p_value=1.0,
        score_before=None,
        score_after=None,
        n_pairs=0,
        pairs_changed=0,
        pinned=None,
        variants=[],
        estimate={},
        per_pair={"before": [], "after": []},
    )
    for name, value in verdict.items():
        setattr(row, name, value)
    return row
