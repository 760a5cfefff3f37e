"""loop.md's account of how an effect is tested: the design that judged the
arms out of sample, the test and why its p-value holds, and the guard over
the step's tests (:func:`method_text`, a section of
:func:`torchcf.diagnose.report.markdown.loop_markdown`)."""

from __future__ import annotations

from ...system.files import JSON


def method_text(result: JSON) -> list[str]:
    """How an effect is compared with its base, and why the p-value is valid."""
    search = result.get("search", {})
    levels = ", ".join(f"{level:.3g}" for level in result.get("levels", []))
    kind = result.get("validation", "time")
    held_out = (
        "The training pairs are split in two by a seeded draw: "
        f"{result.get('fit_pairs', '?')} ({result['fit_fraction']:.0%}) are "
        "the *fit pairs*, whole windows, the other "
        f"{result.get('validation_units', '?')} the *held-out pairs*, which "
        "no arm sees. The current model (at first the pool) is fitted on "
        f"the fit pairs ({search.get('population', '?')} particles per pair)"
    )
    if kind == "crossfit":
        split = (
            "Every training pair is held out once (*cross-fitting*). The "
            "current model (at first the pool) is fitted on the whole windows "
            "of all the training pairs "
            f"({search.get('population', '?')} particles per pair)"
        )
        judged = (
            "Every training pair is then refitted as a held-out pair by a "
            f"short local search of its own ({_refit_rounds(search)}), started "
            "only from the best particles of the *other* drivers (the pairs "
            "of another follower or run: none of its own windows), once from "
            "the placebo's without the effect and once from the effect arm's "
            "with the effect pinned at one value for all pairs (a driver "
            "effect: the median over the arm's picks; a recording or road "
            "effect: its one value), the model's own parameters free on both "
            "sides and the same random numbers: the model class with the "
            "effect against the class without it, each driver judged by "
            "particles that never saw it. *Gain* is the relative drop of the "
            "summed refitted score, the p-value a one-sided sign-flip test of "
            "the per-pair log score ratios over all the training pairs"
        )
    elif kind == "refit":
        split = held_out
        judged = (
            "Every held-out pair is then refitted by a short local search of "
            f"its own ({_refit_rounds(search)}), once from the "
            "placebo's best particles without the effect and once from the "
            "effect arm's with the effect pinned at the value the fit pairs "
            "gave it (a driver effect: the median over the arm's picks; a "
            "recording or road effect: its one value), the model's own "
            "parameters free on both sides and the same random numbers: the "
            "model class with the effect against the class without it, on "
            "drivers no arm saw, whose own parameters are found for them. "
            "*Gain* is the relative drop of the summed refitted score, the "
            "p-value a one-sided sign-flip test of the per-pair log score "
            "ratios. The held-out pairs are independent of one another and of "
            "the fit given the fit pairs, and the effect's value was not chosen "
            "on them"
        )
    elif kind == "pairs":
        split = held_out
        judged = (
            "Every held-out pair is scored by the best of the arm's best "
            "particles (the hybrid's picks), pooled over the fit pairs: the "
            "minimum distance of the test split, on pairs the arm never saw; "
            "*gain* is the relative drop of the summed held-out score, the "
            "p-value a one-sided sign-flip test of the per-pair log score "
            "ratios. The held-out pairs are independent of one another and of "
            "the fit given the fit pairs"
        )
    else:
        fallback = (
            " (validation 'auto': held out, too few pairs would deny the test "
            "levels the windows reach)"
            if result.get("validation_asked") == "auto"
            else ""
        )
        split = (
            f"Every training pair is split in time{fallback}: the "
            f"first {result['fit_fraction']:.0%} of its steps are the *fit "
            "window*, the rest the *validation window*. The current model (at "
            "first the pool) is fitted on the fit windows "
            f"({search.get('population', '?')} particles per pair)"
        )
        warmup = search.get("validation_warmup") or 0.0
        begun = (
            f" (its rollout begun {warmup:g} s early from the recorded state, "
            "the early steps unscored, so that a delay's or a lag's memory "
            "enters it with the recorded history)"
            if warmup > 0
            else ""
        )
        judged = (
            "Per pair, the arm's best particles (the hybrid's picks) "
            f"are scored on the validation window{begun}, out of sample; *gain* "
            "is the relative drop of the summed validation score, the p-value a "
            "one-sided sign-flip test of the per-pair log score ratios. The "
            "pairs are independent and the arms saw only the fit windows"
        )
    return [
        f"**How an effect is tested.** {split} until its local search "
        "converges. Every candidate effect is "
        "then compared from that one fit: the **base arm** searches "
        f"{search.get('rounds', '?')} more rounds by itself; the **effect arm** "
        "lifts the same particles to the variants with the effect (at its neutral "
        "value they are the model itself), refits them at design points over the "
        "effect's prior (a chain from the neutral value, its first step halved, "
        "each later refit started also from the secant of the two before it, so "
        "that a parameter that takes the effect up follows it along the ridge; "
        "a one-parameter recording effect: its "
        "profile, and its best value for every pair; a road profile: one value "
        "searched jointly over the pairs), searches them and keeps the base arm's "
        "particles too: an effect cannot lose in sample.",
        "",
        "**The test.** An effect arm is judged against the **placebo arm**: the "
        "base arm merged with the same search of the current model alone (a chain "
        "of refits with the design points' budgets, then the same rounds), with "
        "*common random numbers*. Both hold the base arm and one more search of "
        "equal budget, so the difference is the effect, not a second search "
        "(which alone lowers the error of a model short of its optimum). "
        f"{judged}{_exactness(kind)} *In-sample "
        "gain*: the same drop on the fit windows against the placebo (against "
        "the base arm, which the effect arm holds, it is never negative).",
        "",
        "**The guard.** The effects of a step are tested in an order fixed by the "
        "fit windows: those a residual signature points to first, then by "
        "in-sample gain. The *fallback procedure* (Wiens 2003) gives the i-th "
        "effect of the order the level 2^-i of the step's (normalised), plus the "
        "level of the effect before it when that one was significant: a closed "
        "test of weighted Bonferroni tests, so the family-wise error of a step "
        "stays within its level under any dependence, half of it goes where the "
        "residual points, and a first effect that fails does not stop the "
        "others (as a fixed sequence would; Holm would ignore the order). Step s "
        f"is tested at alpha / 2^s (the last the rest: {levels}; they sum to "
        f"alpha = {result['alpha']}), so any chosen effect is a false one with "
        f"probability at most alpha. An effect must also gain at least "
        f"{result['min_gain']:.0%} and its estimate must leave its neutral value "
        "(by 5 % of its prior's width: an arm whose best particles keep the "
        "effect neutral owes its gain to the search). The significant effect of "
        "largest gain is chosen (a recording effect, a claim that the data are "
        "faulty, only when it gains more than "
        f"{result['min_gain']:.0%} beyond the best behavioural one), becomes "
        "part of the current model, and the others are tested again. *Twins* "
        "(the effects one found signature points to: a response lag points to "
        "a delay, a clock offset and an actuation lag) are tested as one "
        "*family* at the place of the first, by the largest of their "
        "statistics under common sign flips (exact for the family); where the "
        "family passes, the member chosen within it is significant and its "
        "twins are named.",
        "",
    ]


def _exactness(kind: str) -> str:
    """Why the p-value is valid: exact where the judged units took no part in
    the fit, measured where cross-fitting learns the pinned value and the
    order on every pair."""
    if kind == "crossfit":
        return (
            ". No pair's own particles start its refit, but the pinned value "
            "and the order of the tests are learned on all the pairs, each "
            "pair one of them: the test is not exact by construction, and its "
            "false-choice rate on data without effects is measured (docs/loop.md, "
            "*Power on small sets*)."
        )
    return (
        ", so under 'the effect does not improve the out-of-sample fit' every "
        "pair's ratio is as likely to fall as to rise: the test is exact, "
        "whatever decided the particles and the order of the tests on the fit "
        "windows."
    )


def _refit_rounds(search: JSON) -> str:
    """How long a held-out pair's refit ran, as ``loop.json`` records it (a
    record from before ``refit_stop`` ran its rounds in full)."""
    rounds = search.get("refit_rounds", "?")
    slots = search.get("refit_slots")
    width = "" if slots is None else f"{slots} particles, "
    if search.get("refit_stop") == "calm":
        return (
            f"{width}until two rounds in a row gain less than 0.2 %, "
            f"at most {rounds} rounds"
        )
    return f"{width}{rounds} rounds"


__all__ = ["method_text"]
