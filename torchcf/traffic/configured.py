"""The plausibility battery as a run config sets it (section ``plausibility``):
at the training pairs' settings (:func:`plausibility_battery`), as the
calibration's screen (:func:`plausibility_screen`) and as the report on a
run's hybrid (:func:`hybrid_plausibility`).

Training (:mod:`torchcf.train`: the screen of its calibration, the report on
its hybrid) and the loop's re-calibration, which trains models as the run did
and is handed its screen by the study (:mod:`torchcf.study.pipeline`), both
build them here, so that they cannot drift apart.

Units: SI throughout (m, s, m/s).
"""

from __future__ import annotations

import sys

from tqdm import tqdm

from ..abc.screen import PlausibilityScreen
from ..config import PlausibilityConfig
from ..data import PairSet
from ..models import get_model
from ..posterior import Posterior
from ..runs.summary import PlausibilitySummary
from ..system.console import bar_interval
from .battery import Battery, battery_speed, check_plausibility, rejects

#: Particles per battery call on the hybrid after training. The battery holds
#: about 350 KiB per particle at its peak (the scenarios' recorded series): its
#: own default of 16 384 took 5.6 GiB once a model held that many hybrid
#: particles (10 000 pairs x 5), 2 048 take 0.7 GiB, and run faster (IDM, 8 192
#: particles on 1 thread). The result does not depend on it.
BATTERY_CHUNK = 1 << 11


def plausibility_battery(settings: PlausibilityConfig, pairs: PairSet) -> Battery:
    """The battery of ``settings`` at the training pairs' dt (s), leader length
    (m) and (unless ``plausibility.speed`` is set) 95th-percentile leader speed
    (m/s)."""
    speed = settings.speed or battery_speed(pairs.v_lead, pairs.mask)
    return Battery(
        speed=speed,
        decelerations=tuple(settings.decelerations),
        collision_spacing=settings.collision_spacing,
        dt=pairs.dt,
        leader_length=pairs.leader_length,
    )


def plausibility_screen(
    settings: PlausibilityConfig, pairs: PairSet
) -> PlausibilityScreen | None:
    """The calibration's plausibility filter (``plausibility.filter``) on the
    battery of :func:`plausibility_battery`; None when the filter is off."""
    if not settings.filter:
        return None
    battery = plausibility_battery(settings, pairs)
    return PlausibilityScreen(rejects(battery, settings.reject_string_unstable))


def hybrid_plausibility(
    settings: PlausibilityConfig,
    pairs: PairSet,
    posterior: Posterior,
    progress: bool = False,
) -> dict[str, PlausibilitySummary]:
    """The shares per model of the hybrid's particles in the battery of
    :func:`plausibility_battery`, on the CPU in float64
    (:meth:`torchcf.traffic.Plausibility.summary`), in chunks of
    :data:`BATTERY_CHUNK` particles; ``progress``: a bar over the models on
    stderr."""
    battery = plausibility_battery(settings, pairs)
    names = [
        name for name in posterior.models
        if name in posterior.hybrid and len(posterior.hybrid[name])
    ]  # fmt: skip
    bar = tqdm(
        names, desc="plausibility battery", unit="model", file=sys.stderr,
        mininterval=bar_interval(), disable=not progress,
    )  # fmt: skip
    out = {}
    for name in bar:
        bar.set_postfix_str(f"{name}, {len(posterior.hybrid[name])} particles")
        model = get_model(name)  # the posterior's names enter here
        out[name] = check_plausibility(
            model, posterior.hybrid[name].theta, battery, chunk=BATTERY_CHUNK
        ).summary()
    return out


__all__ = [
    "BATTERY_CHUNK",
    "hybrid_plausibility",
    "plausibility_battery",
    "plausibility_screen",
]
