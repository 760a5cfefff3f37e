"""Parameters whose calibrated particles pile up at a bound of their prior.

A uniform prior puts :data:`EDGE_BAND` of its mass within that fraction of its
width from each bound; where a model's hybrid particles put more than
:data:`EDGE_SHARE` there, the data may prefer a value the prior cuts off, or the
parameter trades off against another at its bound. The shares are computed with
the parameter tables (:func:`torchcf.posterior.tables.piled_at_bounds`); this
module holds the finding and how parameters.md and the study's closing lines
say it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

#: The band at each prior bound, as a fraction of the prior's width, and the
#: share of a model's hybrid particles in it above which the posterior is said
#: to pile up at the bound (a uniform spread puts EDGE_BAND in each band).
EDGE_BAND = 0.05
EDGE_SHARE = 0.25


@dataclass(frozen=True)
class PiledAtBound:
    """A parameter whose hybrid particles pile up at a bound of its prior.

    Attributes:
        model, parameter: which.
        bound: the bound's value (SI units); ``side``: "lower" or "upper".
        share: the share of the model's hybrid particles within
            :data:`EDGE_BAND` of the prior's width from it, in [0, 1].
    """

    model: str
    parameter: str
    side: str
    bound: float
    share: float

    def sentence(self) -> str:
        return (
            f"{self.model.upper()} `{self.parameter}`: {self.share:.0%} of its "
            f"particles within {EDGE_BAND:.0%} of the prior's width from its "
            f"{self.side} bound {self.bound:.4g}"
        )


def bounds_markdown(piled: Sequence[PiledAtBound]) -> list[str]:
    """The note under the parameter tables: what piles up where, and what to
    do (nothing when nothing does)."""
    if not piled:
        return []
    return [
        "**At a prior bound.** "
        + "; ".join(p.sentence() for p in piled)
        + f" (a uniform spread would put {EDGE_BAND:.0%} there). The data may "
        "prefer a value beyond the prior, or the parameter trades off against "
        'another one there: widen that prior (`models: [{"name": ..., '
        '"prior": {...}}]` in the run config) and train again to see which; '
        "until then, read the median as a bound, not an estimate.",
        "",
    ]


__all__ = ["EDGE_BAND", "EDGE_SHARE", "PiledAtBound", "bounds_markdown"]
