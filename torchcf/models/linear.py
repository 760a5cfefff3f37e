"""Linear feedback controllers of automated vehicles: LLCTG, LLCS and HL.

SPEC section 3 and the paper's Appendix Table 3. ``s = x_lead - x`` is the
front-to-front spacing [m] and ``dv = v_lead - v`` [m/s]; commands are in m/s^2.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from .base import CFModel, FollowerState, Perception, first_order_lag_advance, spec


class LLCTGParams(NamedTuple):
    tau: Tensor
    ks: Tensor
    kv: Tensor
    l: Tensor  # noqa: E741 - the paper's standstill distance


class LLCTG(CFModel):
    """Linear controller with a constant-time-gap spacing policy.

    ``u = ks (s - v tau - l) + kv dv``: zero at the desired spacing ``v tau + l``
    when the speeds match.
    """

    name = "llctg"
    Params = LLCTGParams
    param_specs = (
        spec("tau", "s", 0.8, 1.2, "desired time gap"),
        spec("ks", "1/s^2", 0.3, 2.3, "spacing feedback gain"),
        spec("kv", "1/s", 0.3, 2.3, "speed-difference feedback gain"),
        spec("l", "m", 1.0, 11.0, "standstill distance"),
    )

    def command(self, p: LLCTGParams, obs: Perception) -> Tensor:
        spacing_error = obs.spacing - obs.v * p.tau - p.l
        return p.ks * spacing_error + p.kv * (obs.v_lead - obs.v)


class LLCSParams(NamedTuple):
    s0: Tensor
    ks: Tensor
    kv: Tensor


class LLCS(CFModel):
    """Linear controller with a constant-spacing policy: ``u = ks (s - s0) + kv dv``."""

    name = "llcs"
    Params = LLCSParams
    param_specs = (
        spec("s0", "m", 5.0, 25.0, "desired spacing"),
        spec("ks", "1/s^2", 0.3, 2.3, "spacing feedback gain"),
        spec("kv", "1/s", 0.3, 2.3, "speed-difference feedback gain"),
    )

    def command(self, p: LLCSParams, obs: Perception) -> Tensor:
        return p.ks * (obs.spacing - p.s0) + p.kv * (obs.v_lead - obs.v)


class HLParams(NamedTuple):
    tau: Tensor
    TT: Tensor
    ks: Tensor
    kv: Tensor
    ka: Tensor
    l: Tensor  # noqa: E741 - the paper's standstill distance


class HL(CFModel):
    """Third-order linear feedback controller with a first-order actuation lag.

    ``u = ks (s - v tau - l) + kv dv + ka a``, where ``a`` is the realised acceleration
    state, which follows ``da/dt = (u - a) / TT`` (integrated exactly under a
    zero-order hold, :func:`first_order_lag_advance`). The recorded acceleration series
    is the state ``a``, not the command.
    """

    name = "hl"
    Params = HLParams
    param_specs = (
        spec("tau", "s", 0.8, 1.2, "desired time gap"),
        spec("TT", "s", 0.1, 0.5, "actuation lag"),
        spec("ks", "1/s^2", 0.1, 2.3, "spacing feedback gain"),
        spec("kv", "1/s", 0.1, 2.3, "speed-difference feedback gain"),
        spec("ka", "1", -3.0, 0.0, "acceleration feedback gain"),
        spec("l", "m", 3.0, 8.0, "standstill distance"),
    )
    acceleration_is_state = True

    def command(self, p: HLParams, obs: Perception) -> Tensor:
        spacing_error = obs.spacing - obs.v * p.tau - p.l
        return p.ks * spacing_error + p.kv * (obs.v_lead - obs.v) + p.ka * obs.a

    def advance(
        self, p: HLParams, state: FollowerState, u: Tensor, dt: float
    ) -> FollowerState:
        return first_order_lag_advance(state, u, p.TT, dt)
