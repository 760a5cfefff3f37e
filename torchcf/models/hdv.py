"""Human-driver models: OVM, GFM, FVDM and IDM (SPEC section 3, paper Appendix Table 2).

Notation: ``s = x_lead - x`` front-to-front spacing [m], ``L`` the leader length [m],
``dv = v_lead - v`` (leader minus follower) [m/s]. Every command is in m/s^2.
Parameter order is the order of the released prior files (``data/abc-paper/priori``).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .base import CFModel, Perception, spec

#: IDM floors the spacing at this value [m] where it divides (``s* / s``); SPEC 2.
IDM_MIN_SPACING = 0.1


def _optimal_velocity(
    gap: Tensor, v1: Tensor, v2: Tensor, c1: Tensor, c2: Tensor
) -> Tensor:
    """Bando's optimal velocity ``V(g) = v1 + v2 tanh(c1 g - c2)`` [m/s], ``g`` [m]."""
    return v1 + v2 * torch.tanh(c1 * gap - c2)


class OVMParams(NamedTuple):
    kappa: Tensor
    v1: Tensor
    v2: Tensor
    c1: Tensor
    c2: Tensor


class OVM(CFModel):
    """Optimal Velocity Model (Bando et al. 1995).

    ``u = kappa (V(s - L) - v)``, ``V(g) = v1 + v2 tanh(c1 g - c2)``.
    """

    name = "ovm"
    Params = OVMParams
    param_specs = (
        spec("kappa", "1/s", 0.5, 2.0, "sensitivity"),
        spec("v1", "m/s", 5.0, 8.0, "speed factor"),
        spec("v2", "m/s", 20.0, 25.0, "speed factor"),
        spec("c1", "1/m", 0.05, 0.2, "form factor"),
        spec("c2", "1", 1.5, 1.7, "form factor"),
    )

    def command(self, p: OVMParams, obs: Perception) -> Tensor:
        gap = obs.spacing - obs.leader_length
        return p.kappa * (_optimal_velocity(gap, p.v1, p.v2, p.c1, p.c2) - obs.v)


class GFMParams(NamedTuple):
    K: Tensor
    lam: Tensor
    v1: Tensor
    v2: Tensor
    c1: Tensor
    c2: Tensor


class GFM(CFModel):
    """Generalized Force Model (Helbing & Tilch 1998).

    ``u = K (V(s - L) - v) + lam H(-dv) dv`` with V as in OVM and ``H(z) = 1`` for
    ``z > 0``: the second term brakes only when the follower closes in (``dv < 0``).
    """

    name = "gfm"
    Params = GFMParams
    param_specs = (
        spec("K", "1/s", 0.0, 2.0, "proportionality factor"),
        spec("lam", "1/s", 0.0, 2.0, "sensitivity to closing speed"),
        spec("v1", "m/s", 0.0, 10.0, "speed factor"),
        spec("v2", "m/s", 0.0, 30.0, "speed factor"),
        spec("c1", "1/m", 0.0, 0.2, "form factor"),
        spec("c2", "1", 1.0, 2.0, "form factor"),
    )

    def command(self, p: GFMParams, obs: Perception) -> Tensor:
        gap = obs.spacing - obs.leader_length
        dv = obs.v_lead - obs.v
        # H(-dv) dv == min(dv, 0): one clamp instead of a comparison and a product.
        closing_speed = torch.clamp(dv, max=0.0)
        optimal = _optimal_velocity(gap, p.v1, p.v2, p.c1, p.c2)
        return p.K * (optimal - obs.v) + p.lam * closing_speed


class FVDMParams(NamedTuple):
    tau: Tensor
    lam: Tensor
    V1: Tensor
    V2: Tensor
    l_int: Tensor
    beta: Tensor


class FVDM(CFModel):
    """Full Velocity Difference Model (Jiang, Wu & Zhu 2001).

    ``u = (V1 + V2 tanh((s - L) / l_int - beta) - v) / tau + lam dv``.
    The lower bounds of ``tau`` and ``l_int`` are raised from 0 to 0.1 (they divide).
    """

    name = "fvdm"
    Params = FVDMParams
    param_specs = (
        spec("tau", "s", 0.1, 2.0, "relaxation time"),
        spec("lam", "1/s", 0.0, 2.0, "sensitivity to speed difference"),
        spec("V1", "m/s", 0.0, 30.0, "speed"),
        spec("V2", "m/s", 0.0, 30.0, "speed"),
        spec("l_int", "m", 0.1, 10.0, "interaction length"),
        spec("beta", "1", 0.0, 30.0, "form factor"),
    )

    def command(self, p: FVDMParams, obs: Perception) -> Tensor:
        gap = obs.spacing - obs.leader_length
        desired = p.V1 + p.V2 * torch.tanh(gap / p.l_int - p.beta)
        return (desired - obs.v) / p.tau + p.lam * (obs.v_lead - obs.v)


class IDMParams(NamedTuple):
    a: Tensor
    b: Tensor
    v0: Tensor
    T: Tensor
    s0: Tensor
    delta: Tensor


class IDM(CFModel):
    """Intelligent Driver Model (Treiber, Hennecke & Helbing 2000).

    ``u = a (1 - (v / v0)^delta - (s* / s)^2)``,
    ``s* = s0 + max(0, v T - v dv / (2 sqrt(a b)))``. The spacing ``s = x_lead - x``
    carries no leader length (paper's Table 2) and is floored at 0.1 m where it divides.
    """

    name = "idm"
    Params = IDMParams
    param_specs = (
        spec("a", "m/s^2", 0.5, 2.0, "maximum acceleration"),
        spec("b", "m/s^2", 1.0, 4.0, "comfortable deceleration"),
        spec("v0", "m/s", 20.0, 40.0, "desired speed"),
        spec("T", "s", 0.8, 2.5, "desired time gap"),
        spec("s0", "m", 0.5, 3.0, "jam distance"),
        spec("delta", "1", 2.0, 5.0, "free acceleration exponent"),
    )

    def command(self, p: IDMParams, obs: Perception) -> Tensor:
        v = obs.v
        dv = obs.v_lead - v
        dynamic_gap = v * p.T - v * dv / (2.0 * torch.sqrt(p.a * p.b))
        desired_gap = p.s0 + torch.clamp(dynamic_gap, min=0.0)
        spacing = torch.clamp(obs.spacing, min=IDM_MIN_SPACING)
        # exp(delta log(.)) rather than pow(): vectorises in fused kernels; 0 -> 0.
        free_road = torch.exp(p.delta * torch.log(v / p.v0))
        return p.a * (1.0 - free_road - (desired_gap / spacing) ** 2)
