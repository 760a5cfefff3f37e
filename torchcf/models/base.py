"""The car-following model interface shared by every family (SPEC section 3).

A model is a *pure, stateless* function. At every step the rollout hands it

- the parameters ``p`` (a NamedTuple of tensors, one field per parameter, shaped to
  broadcast against the state: ``(P, 1)`` in the full layout, ``(P,)`` in the paired
  layout),
- a :class:`Perception`: what the follower perceives at this step (spacing, own speed,
  leader speed, own realised acceleration, leader length, own road position),

and receives the acceleration command ``u`` (same shape as the state). How a command
becomes motion is a separate method, :meth:`CFModel.advance`: a point mass by default,
a first-order actuation lag for HL.

Keeping *perception*, *command* and *realisation* apart is deliberate: an effect (a
perception delay, a spacing-sensor offset, an actuation lag, acceleration limits) is a
wrapper that edits the :class:`Perception` before :meth:`CFModel.command`, edits the
command after it, or replaces :meth:`CFModel.advance`, without touching the model's
equations (:mod:`torchcf.models.effects`).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor


class ParamSpec(NamedTuple):
    """One model parameter: its name, unit and default uniform prior bounds.

    Examples:
        >>> from torchcf import get_model
        >>> spec = get_model("idm").param_specs[0]
        >>> spec.name, spec.unit, spec.lower, spec.upper
        ('a', 'm/s^2', 0.5, 2.0)
    """

    name: str
    unit: str
    lower: float
    upper: float
    description: str


class Perception(NamedTuple):
    """What the follower perceives at one step; tensors broadcast to the state shape.

    Attributes:
        spacing: front-to-front spacing ``s = x_lead - x`` [m].
        v: own speed [m/s].
        v_lead: leader speed [m/s].
        a: own realised acceleration state [m/s^2] (used by HL only).
        leader_length: leader vehicle length ``L`` [m].
        position: own front-bumper position along the road [m], in the data's
            frame (what a road-grade profile is a function of); None where the
            caller has no road frame (models must not need it).

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.models import Perception
        >>> idm = get_model("idm")
        >>> p = idm.unpack(torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]]))
        >>> obs = Perception(
        ...     spacing=torch.tensor([40.0]),  # [m]
        ...     v=torch.tensor([20.0]),  # [m/s]
        ...     v_lead=torch.tensor([20.0]),
        ...     a=torch.tensor([0.0]),  # [m/s^2]
        ...     leader_length=5.0,
        ... )
        >>> round(idm.command(p, obs).item(), 3)  # [m/s^2]
        0.664
    """

    spacing: Tensor
    v: Tensor
    v_lead: Tensor
    a: Tensor
    leader_length: float
    position: Tensor | None = None


class FollowerState(NamedTuple):
    """The simulated follower: position [m], speed [m/s], acceleration [m/s^2].

    Examples:
        >>> import torch
        >>> from torchcf.models import FollowerState, point_mass_advance
        >>> x, v = torch.zeros(2), torch.full((2,), 20.0)  # [m], [m/s]
        >>> state = FollowerState(x=x, v=v, a=torch.zeros(2))
        >>> point_mass_advance(state, torch.ones(2), dt=0.1).v  # [m/s]
        tensor([20.1000, 20.1000])
    """

    x: Tensor
    v: Tensor
    a: Tensor


def point_mass_advance(state: FollowerState, u: Tensor, dt: float) -> FollowerState:
    """Constant-acceleration step over ``dt`` (SPEC section 2, point-mass models).

    ``a(t) = u``, ``v(t+1) = v + u dt``, ``x(t+1) = x + v dt + u dt^2 / 2``.

    Examples:
        >>> import torch
        >>> from torchcf.models import FollowerState, point_mass_advance
        >>> one = torch.tensor([1.0])
        >>> state = FollowerState(x=0.0 * one, v=20.0 * one, a=0.0 * one)  # [m], [m/s]
        >>> after = point_mass_advance(state, one, dt=0.1)  # u = 1 m/s^2
        >>> round(after.x.item(), 3), round(after.v.item(), 3), after.a.item()
        (2.005, 20.1, 1.0)
    """
    return FollowerState(
        x=state.x + state.v * dt + u * (0.5 * dt * dt),
        v=state.v + u * dt,
        a=u,
    )


def first_order_lag_advance(
    state: FollowerState, u: Tensor, lag: Tensor, dt: float
) -> FollowerState:
    """Exact zero-order-hold step of a first-order actuation lag (SPEC section 2, HL).

    With ``da/dt = (u - a) / TT`` and ``e = exp(-dt / TT)``:
    ``a(t+1) = u + (a - u) e``,
    ``v(t+1) = v + u dt + (a - u) TT (1 - e)``,
    ``x(t+1) = x + v dt + u dt^2 / 2 + (a - u) TT (dt - TT (1 - e))``.

    Args:
        state: follower state at t.
        u: command held over the step [m/s^2].
        lag: time constant ``TT`` [s], broadcastable to the state.
        dt: step [s].

    Examples:
        >>> import torch
        >>> from torchcf.models import FollowerState, first_order_lag_advance
        >>> one = torch.tensor([1.0])
        >>> state = FollowerState(x=0.0 * one, v=20.0 * one, a=0.0 * one)  # [m], [m/s]
        >>> after = first_order_lag_advance(state, one, lag=0.5 * one, dt=0.1)
        >>> round(after.a.item(), 3)  # [m/s^2], lagging the 1 m/s^2 command
        0.181
    """
    decay = torch.exp(-dt / lag)
    gap_to_command = state.a - u
    one_minus_decay = 1.0 - decay
    return FollowerState(
        x=state.x
        + state.v * dt
        + u * (0.5 * dt * dt)
        + gap_to_command * lag * (dt - lag * one_minus_decay),
        v=state.v + u * dt + gap_to_command * lag * one_minus_decay,
        a=u + gap_to_command * decay,
    )


def rows_of(values: Any, rows: Tensor, dim: int = 0) -> Any:
    """A tuple (or named tuple) of tensors with the particles ``rows`` taken
    along ``dim`` (early rejection, :meth:`CFModel.select_particles`);
    0-dimensional tensors are shared and stay."""
    taken = [t.index_select(dim, rows) if t.ndim else t for t in values]
    return type(values)(*taken) if hasattr(values, "_fields") else tuple(taken)


class CFModel:
    """Base class of a car-following model (see the module docstring).

    Subclasses set :attr:`name`, :attr:`Params` (a NamedTuple whose fields are the
    parameter names, in the prior files' order), :attr:`param_specs` and implement
    :meth:`command`.

    Examples:
        >>> from torchcf import CFModel, get_model
        >>> idm = get_model("idm")
        >>> isinstance(idm, CFModel), idm.n_params, tuple(idm.prior_bounds().shape)
        (True, 6, (6, 2))
        >>> idm
        IDM(a, b, v0, T, s0, delta)
    """

    name: ClassVar[str]
    Params: ClassVar[type]
    param_specs: ClassVar[tuple[ParamSpec, ...]]
    #: True when the recorded acceleration is a state of the vehicle (HL's lag) rather
    #: than the command itself (point-mass models).
    acceleration_is_state: ClassVar[bool] = False
    #: False when the command has data-dependent control flow (MPC's QP solver):
    #: the rollout then never hands :meth:`command_with_memory` whole to
    #: ``torch.compile``.
    compilable: ClassVar[bool] = True
    #: True when the command is a compilable draft and an eager correction with
    #: data-dependent control flow (:meth:`draft_with_memory`, :meth:`correct`;
    #: MPC: the plan of the unconstrained QP, then a solver for the cells whose
    #: plan leaves the box). A compiled rollout then fuses everything of a step
    #: but the correction, which runs eagerly between two compiled calls.
    corrects: ClassVar[bool] = False
    #: True when the model reads ``Perception.position`` (a road-grade profile);
    #: the rollout computes the absolute position only for such models.
    uses_position: ClassVar[bool] = False
    #: Simulated cells (rollouts of a whole pair: a particle in the paired layout,
    #: a particle's N pairs in the full one) per chunk when the caller does not
    #: choose: per-step overhead vs. memory and cache. A chunk is also the
    #: rejection engine's round, the unit of progress and checkpoints: a budget
    #: should be seconds of simulation, a small part of a long stream (on CUDA
    #: chunks hold at least :data:`torchcf.sim.rollout.CUDA_CHUNK_CELLS`).
    chunk_cells: ClassVar[int] = 1 << 18
    #: Whether a particle's rollout rounds the same whatever the batch it is
    #: simulated in. False for the MPC, whose QP solver picks its kernels by batch
    #: size (LAPACK below a size): the engines then simulate fixed-size batches.
    batch_size_invariant: ClassVar[bool] = True
    #: Whether a rollout may drop particles midway (early rejection,
    #: :func:`torchcf.sim.rollout.simulate`'s ``ceiling``): :meth:`select_particles`
    #: knows the model's prepared parameters and memory.
    prunable: ClassVar[bool] = True

    #: The effects wrapping the pool model (:class:`~torchcf.models.augmented.
    #: AugmentedModel`); none for a pool model.
    effects: tuple[Any, ...] = ()

    @property
    def pool_model(self) -> CFModel:
        """The pool model under any effects (a pool model is its own)."""
        return self

    @property
    def effect_kinds(self) -> tuple[str, ...]:
        """The kinds (:attr:`Effect.name`) of the effects wrapping the model, in
        their canonical order (road effects last): ``idm+lag+grade(end=600)`` ->
        ``("lag", "grade")``."""
        return tuple(effect.name for effect in self.effects)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(spec.name for spec in self.param_specs)

    @property
    def n_params(self) -> int:
        return len(self.param_specs)

    def prior_bounds(self, dtype: torch.dtype = torch.float64) -> Tensor:
        """Default uniform prior box, ``(K, 2)`` of (lower, upper)."""
        return torch.tensor(
            [[spec.lower, spec.upper] for spec in self.param_specs], dtype=dtype
        )

    def unpack(self, theta: Tensor, state_ndim: int = 1) -> Any:
        """Split ``theta: (P, K)`` into the Params NamedTuple.

        Each field is ``(P,)`` followed by ``state_ndim - 1`` singleton dimensions, so
        parameters broadcast over the pair dimension of the full layout with no
        ``unsqueeze`` in the physics.
        """
        columns = theta.reshape(theta.shape + (1,) * (state_ndim - 1)).unbind(1)
        # Contiguous copies: strided columns of theta would defeat vectorised loads
        # in fused kernels; the copy is made once per chunk, not per step.
        return self.Params(*(column.contiguous() for column in columns))

    def prepare(self, p: Any, dt: float, state_shape: tuple[int, ...]) -> Any:
        """Per-particle precomputation, once per chunk of particles (default: none).

        Whatever it returns is handed to :meth:`command` and :meth:`advance` in place
        of the unpacked parameters for every step of the chunk (MPC factorises its
        QP here).
        """
        return p

    def command(self, p: Any, obs: Perception) -> Tensor:
        """The acceleration command ``u`` [m/s^2], same shape as ``obs.spacing``."""
        raise NotImplementedError

    def select_particles(self, p: Any, memory: Any, rows: Tensor) -> tuple[Any, Any]:
        """The prepared parameters and memory of the particles ``rows`` alone.

        Args:
            p: what :meth:`prepare` returned for a chunk of P particles.
            memory: the memory of the same chunk.
            rows: (P',) int64 particles kept (dimension 0 of the state).

        The default serves a model whose prepared parameters are its Params
        (fields with the particle first) and that has no memory.
        """
        if memory is not None:
            raise NotImplementedError(f"{self.name}: no particle selection of memory")
        return rows_of(p, rows), None

    def initial_memory(self, p: Any, first: Perception) -> Any:
        """What a stateful model carries between steps (default: nothing).

        Two kinds exist: memory that only makes the command cheaper (MPC
        warm-starts its solver from the previous plan; the command does not depend
        on it beyond the solver's tolerance), and memory that is part of the model
        (a perception delay's history). Either way it is a pytree of tensors whose
        shapes are fixed for a rollout, so a compiled time step sees one structure.

        Args:
            p: the prepared parameters (what :meth:`prepare` returned).
            first: the perception at the first step; its tensors have the state's
                shape.
        """
        return None

    def command_with_memory(
        self, p: Any, obs: Perception, memory: Any
    ) -> tuple[Tensor, Any]:
        """The command and the memory for the next step; see :meth:`initial_memory`."""
        return self.command(p, obs), memory

    def draft_with_memory(
        self, p: Any, obs: Perception, memory: Any
    ) -> tuple[Any, Any]:
        """The compilable part of a correcting model's command (:attr:`corrects`).

        Returns:
            pending: a tuple of tensors, what :meth:`correct` completes; its
                shapes depend on the state's only, so a compiled draft has one
                graph.
            memory: the memory as the draft leaves it.

        ``command_with_memory(p, obs, memory)`` equals
        ``correct(p, *draft_with_memory(p, obs, memory))``.
        """
        raise NotImplementedError(f"{self.name} has no draft (corrects is False)")

    def correct(self, p: Any, pending: Any, memory: Any) -> tuple[Tensor, Any]:
        """The eager end of a correcting model's command: the command (the
        state's shape) and the memory for the next step."""
        raise NotImplementedError(f"{self.name} has no correction (corrects is False)")

    def advance(
        self, p: Any, state: FollowerState, u: Tensor, dt: float
    ) -> FollowerState:
        """Realise the command over one step (point mass unless overridden)."""
        return point_mass_advance(state, u, dt)

    @property
    def realises_as_point_mass(self) -> bool:
        """Whether :meth:`advance` is the point mass, whatever the parameters (a
        simulation of several models may then move their vehicles in one call)."""
        return type(self).advance is CFModel.advance

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(self.param_names)})"


def spec(
    name: str, unit: str, lower: float, upper: float, description: str
) -> ParamSpec:
    """Shorthand used by the model families to declare a parameter."""
    if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
        raise ValueError(f"bad prior bounds for {name}: [{lower}, {upper}]")
    return ParamSpec(name, unit, float(lower), float(upper), description)
