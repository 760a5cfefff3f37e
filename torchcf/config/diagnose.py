"""The settings of the diagnosis loop (the config's ``diagnose`` section,
:mod:`torchcf.diagnose`): which effects it tries, how it tests them on held-out
pairs, and how it re-calibrates."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from torchcf.config.fields import STRICT
from torchcf.models import EFFECTS
from torchcf.models.effects import parse_effect

__all__ = ["DiagnoseConfig"]


class DiagnoseConfig(BaseModel):
    """Close the loop after training (``torchcf diagnose RUN_DIR``).

    Residual diagnosis of the run's hybrid, attribution of candidate effects by
    their out-of-sample gain in small ABC runs, re-calibration with the chosen
    effects and evaluation on the test split (:mod:`torchcf.diagnose`).

    Examples:
        >>> from torchcf.config import DiagnoseConfig
        >>> diagnose = DiagnoseConfig(models="all", min_share=0.1)
        >>> diagnose.run_after_training, diagnose.models, diagnose.min_share
        (False, 'all', 0.1)
    """

    model_config = STRICT

    run_after_training: bool = Field(
        False,
        description=(
            "Run the loop at the end of the study (torchcf train, python -m "
            "torchcf.train)."
        ),
    )
    effects: list[str] = Field(
        list(EFFECTS),
        min_length=1,
        description=(
            f"Candidate effects, from {', '.join(EFFECTS)}; options in brackets, "
            "e.g. 'grade(knots=4)' (a grade without start/end spans the training "
            "pairs' road section)."
        ),
    )
    models: Literal["active", "all"] = Field(
        "active",
        description=(
            "Pool models that get the effects: 'active' = those whose share of the "
            "run's hybrid is at least min_share, 'all' = every model of the run."
        ),
    )
    min_share: float = Field(
        0.05, ge=0, le=1, description="Share that makes a model 'active' [1]."
    )
    n_particles: int = Field(
        50_000,
        gt=0,
        description=(
            "Prior draws per pool model in the small ABC run that starts the "
            "attribution on the fit windows (its S best per pair start the local "
            "search)."
        ),
    )
    population: int = Field(
        20,
        gt=0,
        description=(
            "S: particles per pair every arm keeps and refines by local search "
            "(at least abc.top_n)."
        ),
    )
    local_copies: int = Field(
        32,
        gt=0,
        description="Perturbed copies of every kept particle per local-search round.",
    )
    rounds: int = Field(
        6,
        ge=0,
        description=(
            "Local-search rounds of the pool's fit, of every arm of a comparison "
            "and of the re-calibration."
        ),
    )
    max_rounds: int = Field(
        40,
        gt=0,
        description=(
            "Local-search rounds at most to converge the current model before "
            "each step's comparisons (it stops once two rounds in a row lower "
            "the fit by less than 0.2 %)."
        ),
    )
    fit_fraction: float = Field(
        0.6,
        gt=0.1,
        lt=0.95,
        description=(
            "The share of the data the attribution fits: of every training "
            "pair's steps (validation 'time'), or of the training pairs "
            "(validation 'pairs'); the rest is out of sample."
        ),
    )
    validation: Literal["auto", "time", "pairs", "refit", "crossfit"] = Field(
        "auto",
        description=(
            "How an arm is judged out of sample: 'time' fits the first "
            "fit_fraction of every training pair's steps and scores each pair's "
            "picks on the rest; 'pairs' fits the whole windows of fit_fraction of "
            "the training pairs (a seeded draw) and scores every other pair by "
            "the best of all the picks (the minimum distance on pairs the arms "
            "never saw); 'refit' splits as 'pairs' and refits every held-out "
            "pair by a short search of its own, with and without the effect "
            "(pinned at the value the fit pairs gave), from one start; "
            "'crossfit' fits every training pair and refits every pair as "
            "'refit' does, from the picks of the other drivers (runs) only, so "
            "every pair is held out once; 'auto': 'crossfit' with at least "
            "log2(permutations + 1) training pairs (15 at the defaults), else "
            "'time'."
        ),
    )
    refit_rounds: int = Field(
        24,
        ge=0,
        description=(
            "Local-search rounds of a held-out pair's refit (validation "
            "'refit'), of refit_slots particles and local_copies / 2 copies each: "
            "at most this many with refit_stop 'calm', exactly this many with "
            "'rounds'."
        ),
    )
    refit_effect: Literal["pinned", "free"] = Field(
        "pinned",
        description=(
            "How a refit holds a driver effect (validation 'refit', "
            "'crossfit'): 'pinned' at the value the training gave (the median "
            "of the arm's picks) for every judged pair, both sides scored on "
            "the whole pair; 'free' searched per pair within its prior from "
            "that value on the first fit_fraction of the pair's steps, both "
            "sides scored on the rest (a parameter fitted to the pair is judged "
            "out of sample in time). Shared effects are pinned either way."
        ),
    )
    refit_slots: int = Field(
        5,
        gt=0,
        description=(
            "Particles a held-out pair's refit keeps and searches from "
            "(validation 'refit'; a pair's own best with 'time'): the refit's "
            "cost per round is pairs x refit_slots x local_copies / 2 rollouts."
        ),
    )
    refit_stop: Literal["calm", "rounds"] = Field(
        "calm",
        description=(
            "When a held-out pair's refit stops: 'calm' once two rounds in a "
            "row lower the held-out pairs' summed best score by less than "
            "0.2 % (as the fit's search converges; each side of a comparison "
            "is then refitted until neither would gain from more rounds), "
            "'rounds' after exactly refit_rounds rounds."
        ),
    )
    validation_warmup: float = Field(
        0.0,
        ge=0,
        le=10,
        description=(
            "Seconds of recorded history before each validation window [s] "
            "(validation 'time'; with 'auto' it asks for it): the validation "
            "rollout starts this long before the split from the observed state, "
            "and only the steps after the split are scored, so a delay's, a "
            "clock offset's or a lag's memory enters the window filled by the "
            "recorded leader (0: the window starts at the split, its memory a "
            "steady past). Held-out pairs ('pairs', 'refit') are simulated from "
            "their first step."
        ),
    )
    alpha: float = Field(
        0.05,
        gt=0,
        lt=1,
        description=(
            "Family-wise significance level of the whole selection: step s is "
            "tested at alpha / 2^s (the last step the rest), each by the fallback "
            "procedure in the order the fit windows give."
        ),
    )
    levels: Literal["halving", "pointed", "equal"] = Field(
        "halving",
        description=(
            "How a step's level is shared among its tests, in their order: "
            "'halving' gives the i-th test 2^-i of it (the first half, whatever "
            "pointed to it); 'pointed' gives the effects a residual signature "
            "points to half of it in equal shares and the others the other half "
            "in equal shares; 'equal' gives every test the same share "
            "(Bonferroni). The fallback procedure passes a significant test's "
            "level on to the next under each."
        ),
    )
    families: Literal["signature", "none"] = Field(
        "signature",
        description=(
            "'signature' tests the effects one found residual signature points "
            "to (twins: a response lag points to delay, sync and lag) as one "
            "family at the place of the first, by the largest of their "
            "statistics under common sign flips, and chooses the member within "
            "it; 'none' tests every effect by itself, each at its own place."
        ),
    )
    min_gain: float = Field(
        0.05,
        ge=0,
        lt=1,
        description="Smallest relative out-of-sample score drop that counts [1].",
    )
    max_effects: int = Field(
        3,
        gt=0,
        description=(
            "Forward selection's steps at most: each chooses the significant "
            "effect of largest out-of-sample gain, given those chosen before."
        ),
    )
    permutations: int = Field(
        20_000, ge=1000, description="Sign-flip permutations of the gain test."
    )
    seed: int | None = Field(
        None,
        ge=0,
        description=(
            "Seed of the attribution's prior draws and local search; None = "
            "abc.seed. Another seed checks that the answer is not luck."
        ),
    )
    detectable: bool = Field(
        True,
        description=(
            "Where the loop chooses nothing (its first step), estimate per "
            "tested effect the "
            "smallest size its test would have found in these data "
            "(:mod:`torchcf.diagnose.selection.power`; one refit per size tried). Off "
            "only to save that time where the sizes are not read (a power "
            "study)."
        ),
    )
    workers: int = Field(
        0,
        ge=0,
        description=(
            "Processes that search a step's effect arms side by side, one "
            "thread each: 0 (auto) one per core where an arm's search rounds "
            "are large enough to pay for starting them, 1 none (the results are "
            "the same either way)."
        ),
    )
    method: Literal["rejection", "smc"] = Field(
        "rejection",
        description=(
            "The small ABC run that starts the attribution: 'rejection' (prior "
            "draws) or 'smc' (the refinement of abc.smc at the same budget); "
            "local search follows either."
        ),
    )

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, effects: list[str]) -> list[str]:
        # parse_effect raises ValueError naming a bad effect or option.
        names = [parse_effect(token).name for token in effects]
        if len(set(names)) != len(names):
            raise ValueError(f"an effect is listed twice: {effects}")
        return [token.strip().lower() for token in effects]

    @model_validator(mode="after")
    def _warmup_in_time(self) -> DiagnoseConfig:
        asked = "validation_warmup" in self.model_fields_set
        held = self.validation in ("pairs", "refit", "crossfit")
        if held and asked and self.validation_warmup > 0:
            raise ValueError(
                "diagnose.validation_warmup applies to validation 'time' only: a "
                f"held-out pair ('{self.validation}') is simulated from its first "
                "step"
            )
        return self
