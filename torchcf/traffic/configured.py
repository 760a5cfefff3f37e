"""The plausibility battery as a run config sets it (section ``plausibility``):
at the training pairs' settings (:func:`plausibility_battery`), and as the
calibration's screen (:func:`plausibility_screen`).

Training (:mod:`torchcf.train`: the screen of its calibration, the report on
its hybrid) and the loop's re-calibration, which trains models as the run did
and is handed its screen by the study (:mod:`torchcf.study.pipeline`), both
build them here, so that they cannot drift apart.

Units: SI throughout (m, s, m/s).
"""

from __future__ import annotations

from ..abc.screen import PlausibilityScreen
from ..config import PlausibilityConfig
from ..data import PairSet
from .battery import Battery, battery_speed, rejects


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


__all__ = ["plausibility_battery", "plausibility_screen"]
