"""The learned hybrid model as a PyTorch module, for traffic simulations.

:class:`HybridSampler` holds ``Theta_hybrid`` (SPEC section 5: the particles that
ABC kept, every model's, in the proportions of the shares) and drives a batch of
vehicles with it:

- :meth:`HybridSampler.sample` gives every vehicle one particle, drawn uniformly from
  the learned set, so a model's frequency among the vehicles follows its share
  ``beta_m``; optionally every vehicle redraws every ``resample_every`` seconds
  (intra-driver variability);
- :meth:`HybridSampler.forward` maps what the vehicles perceive to their
  acceleration commands, all models in one call: the vehicles are grouped by model
  when they are assigned, and every step runs each model's own batched code
  (:meth:`CFModel.command_with_memory`, the code the calibration rollout runs) on
  its group's gathered tensors and scatters the commands back. The loop is over the
  (few) models, never over vehicles;
- :meth:`HybridSampler.advance` realises the commands (SPEC section 2 through
  :func:`torchcf.sim.rollout.realise`: a point mass, or HL's / the ``lag``
  effect's exact first-order lag, then no reversing).

The learned particles and the assignment are buffers: they move with ``.to()``,
change dtype with ``.double()`` and round-trip through ``state_dict``. What a
model carries between steps — MPC's previous plan (a warm start only), a
perception delay's history (part of the model) — is **sampler state**: ``forward``
reads and replaces :attr:`HybridSampler.memory`. It starts from a steady past at the
first ``forward`` after :meth:`sample`, :meth:`assign`, a redraw, ``load_state_dict``
or :meth:`reset_memory`; it moves with ``.to()`` but is not in the ``state_dict``
(nor is the generator kept for redraws: after loading, pass one to
:meth:`resample` or :meth:`sample` for a reproducible stream).

Shapes: ``V`` is the number of vehicles; the vehicles may be laid out in any shape
(``vehicle_shape``, e.g. ``(S, n)`` scenarios x vehicles), and every per-vehicle
tensor has that shape. Internally the vehicles are flattened to ``(V,)``.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn
from torch.utils import _pytree as pytree

from ..data import DATASETS, DataError
from ..data.registry import read_meta
from ..models import CFModel, FollowerState, Perception, get_model, require_model
from ..posterior import Posterior
from ..runs.directory import RunDir
from ..runs.summary import RunSummary
from ..sim.rollout import check_theta, realise
from ..system.files import RunFileError, TorchPayload

#: The base class realises a command as a point mass (it ignores its parameters):
#: :meth:`HybridSampler.advance` moves every vehicle with it at once, then
#: overwrites the groups whose model has its own realisation.
_POINT_MASS = CFModel()


def _command(
    model: CFModel, prepared: Any, obs: Perception, memory: Any
) -> tuple[Tensor, Any]:
    return model.command_with_memory(prepared, obs, memory)


@functools.cache
def _command_eager() -> Any:
    """:func:`_command` for models with data-dependent control flow (MPC's QP
    solver): they run eagerly inside a compiled forward, dynamo leaving this call
    out of the graph instead of failing. Made on first use: ``disable`` imports
    dynamo, a second of every torchcf process's start-up otherwise."""
    return torch.compiler.disable(_command)


class _Group(NamedTuple):
    """The vehicles driven by one model, ready to step."""

    model_id: int
    model: CFModel
    index: Tensor  # (V_g,) int64 flat vehicle indices, increasing
    prepared: Any  # model.prepare(...) over the V_g vehicles
    covers_all: bool  # V_g == V: no gather or scatter needed


class HybridSampler(nn.Module):
    """The learned hybrid car-following model for PyTorch traffic models.

    Build it with :meth:`from_file` from a ``posterior.pt``, then::

        sampler.sample(n_vehicles, generator=g)           # a particle per vehicle
        u = sampler(spacing, v, v_leader, a)              # commands [m/s^2]
        x, v, a = sampler.advance(x, v, a, u)             # one step of dt
        sampler.tick()                                    # clock, redraws

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample(3, generator=torch.Generator().manual_seed(0))
        >>> spacing, v = torch.full((3,), 40.0), torch.full((3,), 20.0)
        >>> u = sampler(spacing, v, v, torch.zeros(3))  # commands [m/s^2]
        >>> x, v, a = sampler.advance(torch.zeros(3), v, torch.zeros(3), u)
        >>> u.shape, bool((x > 0).all())
        (torch.Size([3]), True)

    Args:
        models: the model objects (``torchcf.get_model("idm+delay")``), one per
            entry of ``particles``; a name raises :class:`TypeError`.
        particles: per model, ``(P_m, K_m)`` parameters in the model's order (SI);
            ``P_m`` may be 0 (a model with no share).
        dt: step [s]. The step the particles were learned at: MPC's prediction
            model and a delay's interpolation depend on it.
        leader_length: the leader length ``L`` [m] the models perceive.
        dtype: float32 or float64; the dtype every input must have.

    Attributes:
        models: the models, in ``particles`` order.
        model_names: their names.
        dt, leader_length: as given.
        vehicle_shape: the layout of the vehicles of the current assignment.
        resample_every: seconds between redraws (None: never).
        vehicle_particle: buffer ``(V,)`` int64, the particle of each vehicle (an
            index into the concatenation of every model's particles).
    """

    vehicle_particle: Tensor
    particle_model: Tensor
    particle_row: Tensor

    def __init__(
        self,
        models: Sequence[CFModel],
        particles: Sequence[Tensor],
        *,
        dt: float,
        leader_length: float = 5.0,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(
                f"dtype must be torch.float32 or torch.float64, got {dtype}"
            )
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        if not (math.isfinite(leader_length) and leader_length >= 0):
            raise ValueError(f"leader_length must be >= 0 [m], got {leader_length}")
        if len(models) != len(particles):
            raise ValueError(
                f"{len(models)} models but {len(particles)} particle tensors"
            )
        if not models:
            raise ValueError("a hybrid sampler needs at least one model")
        self.models = tuple(require_model(m, "HybridSampler") for m in models)
        self.model_names = tuple(m.name for m in self.models)
        if len(set(self.model_names)) != len(self.model_names):
            raise ValueError(f"a model is listed twice: {list(self.model_names)}")
        self.dt = float(dt)
        self.leader_length = float(leader_length)

        model_ids, rows = [], []
        for m, (model, theta) in enumerate(zip(self.models, particles, strict=True)):
            theta = torch.as_tensor(theta)
            check_theta(model, theta, what="particles")
            self.register_buffer(f"theta_{m}", theta.to(dtype).clone())
            model_ids.append(torch.full((theta.shape[0],), m, dtype=torch.long))
            rows.append(torch.arange(theta.shape[0]))
        n_particles = sum(len(r) for r in rows)
        if n_particles == 0:
            raise ValueError("the learned set holds no particle")
        # Particle i of the learned set is row particle_row[i] of model
        # particle_model[i]; derived from the particles, so not saved.
        self.register_buffer("particle_model", torch.cat(model_ids), persistent=False)
        self.register_buffer("particle_row", torch.cat(rows), persistent=False)
        self.register_buffer("vehicle_particle", torch.zeros(0, dtype=torch.long))
        self.vehicle_shape: tuple[int, ...] = (0,)
        self.resample_every: float | None = None
        self._generator: torch.Generator | None = None
        self._clock = 0  # steps since the last draw
        self._groups: list[_Group] = []
        self._memory: list[Any] | None = None
        self._acceleration_is_state = torch.zeros(0, dtype=torch.bool)

    # ------------------------------------------------------------- construction
    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike[str],
        *,
        dt: float | None = None,
        leader_length: float | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> HybridSampler:
        """The sampler of a trained run's ``posterior.pt``.

        Args:
            path: the ``posterior.pt`` (or the run directory holding it).
            dt: the time step [s]; default: the run's (its ``summary.json``,
                else the registry's for a named data set, else the
                ``config.json``'s data beside the file).
            leader_length: the leader's length [m]; default as ``dt``.
            dtype: float32 or float64.

        Raises:
            ValueError: no such file, not a posterior, or no ``dt`` or leader
                length to be found.
        """
        path = Path(path)
        if path.is_dir():
            path = RunDir(path).posterior_pt
        if not path.is_file():
            raise ValueError(f"{path}: no such posterior file")
        posterior = Posterior.load(path)
        if dt is None or leader_length is None:
            known_dt, known_length = _data_constants(posterior.dataset, path.parent)
            dt = known_dt if dt is None else dt
            leader_length = known_length if leader_length is None else leader_length
        for value, name, unit in (
            (dt, "dt", "s"),
            (leader_length, "leader_length", "m"),
        ):
            if value is None:
                raise ValueError(
                    f"{path}: the data set {posterior.dataset!r} is not a named one "
                    f"and neither the run's summary.json nor its config gives its "
                    f"{name}; pass {name}= [{unit}]"
                )
        return cls.from_posterior(
            posterior, dt=dt, leader_length=leader_length, dtype=dtype
        )

    @classmethod
    def from_posterior(
        cls,
        posterior: Posterior,
        *,
        dt: float,
        leader_length: float = 5.0,
        dtype: torch.dtype = torch.float32,
    ) -> HybridSampler:
        """The sampler of a :class:`~torchcf.posterior.Posterior` (its hybrid set)."""
        names = [name for name in posterior.models if name in posterior.hybrid]
        models = [get_model(name) for name in names]  # the file's names enter here
        for name, model in zip(names, models, strict=True):
            stored = tuple(posterior.hybrid[name].param_names)
            if stored != model.param_names:
                raise ValueError(
                    f"{name}: the posterior's parameters {list(stored)} are not the "
                    f"model's {list(model.param_names)}"
                )
        return cls(
            models,
            [posterior.hybrid[name].theta for name in names],
            dt=dt,
            leader_length=leader_length,
            dtype=dtype,
        )

    # ------------------------------------------------------------ the learned set
    @property
    def dtype(self) -> torch.dtype:
        return self.theta_0.dtype

    @property
    def device(self) -> torch.device:
        return self.theta_0.device

    @property
    def n_particles(self) -> int:
        return self.particle_model.shape[0]

    @property
    def n_vehicles(self) -> int:
        return self.vehicle_particle.shape[0]

    @property
    def shares(self) -> dict[str, float]:
        """Each model's fraction of the learned set (SPEC section 5's ``beta_m``)."""
        counts = torch.bincount(self.particle_model, minlength=len(self.models))
        return {
            name: float(count) / self.n_particles
            for name, count in zip(self.model_names, counts.tolist(), strict=True)
        }

    def particles(self, model: str) -> Tensor:
        """``(P_m, K_m)`` the learned particles of ``model``."""
        return self.get_buffer(f"theta_{self._model_id(model)}")

    def particle_ids(
        self, model: str, rows: Tensor | Sequence[int] | None = None
    ) -> Tensor:
        """Learned-set indices of rows of ``model``'s particles (for :meth:`assign`).

        Args:
            model: a model name of the sampler.
            rows: rows of :meth:`particles` (default: all), any shape.

        Returns:
            int64 tensor of ``rows``' shape.
        """
        m = self._model_id(model)
        first = int((self.particle_model < m).sum())
        count = int(self.get_buffer(f"theta_{m}").shape[0])
        if rows is None:
            rows = torch.arange(count, device=self.device)
        rows = torch.as_tensor(rows, device=self.device)
        if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= count):
            raise ValueError(f"{model} has {count} particles; rows out of range")
        return rows.long() + first

    def _model_id(self, model: str) -> int:
        name = get_model(model).name  # a caller's name, in its canonical spelling
        if name not in self.model_names:
            raise ValueError(
                f"{model!r} is not in the learned set ({', '.join(self.model_names)})"
            )
        return self.model_names.index(name)

    # ------------------------------------------------------------------ drawing
    def sample(
        self,
        n: int | Sequence[int],
        generator: torch.Generator | None = None,
        *,
        resample_every: float | None = None,
    ) -> Tensor:
        """Give every vehicle a particle drawn uniformly from the learned set.

        Uniform over particles, so model ``m`` drives a vehicle with probability
        ``beta_m`` (its share) and, within a model, each kept particle is equally
        likely (the particles are the posterior sample; SPEC section 5).

        Args:
            n: the number of vehicles, or their layout (e.g. ``(S, n)``).
            generator: random stream of the draws (and of later redraws: the
                sampler keeps it); default: torch's global one.
            resample_every: redraw every vehicle's particle every this many
                seconds of simulated time (counted by :meth:`tick`); None: never.

        Returns:
            ``vehicle_shape`` int64: the index in :attr:`model_names` of each
            vehicle's model.
        """
        shape = (int(n),) if isinstance(n, int) else tuple(int(k) for k in n)
        if not shape or any(k < 1 for k in shape):
            raise ValueError(f"n must be a positive count or shape, got {n!r}")
        if resample_every is not None and not (
            math.isfinite(resample_every) and resample_every > 0
        ):
            raise ValueError(
                f"resample_every must be a positive number of seconds, "
                f"got {resample_every}"
            )
        self._generator = generator
        self.resample_every = None if resample_every is None else float(resample_every)
        self.assign(self._draw(shape))
        return self.vehicle_model

    def assign(self, particle: Tensor) -> None:
        """Give the vehicles these particles (learned-set indices, any shape).

        Resets the clock and the memory. See :meth:`particle_ids`.
        """
        particle = torch.as_tensor(particle)
        if particle.is_floating_point() or particle.is_complex():
            raise ValueError("particle indices must be integers")
        if particle.numel() == 0:
            raise ValueError("assign at least one vehicle")
        if int(particle.min()) < 0 or int(particle.max()) >= self.n_particles:
            raise ValueError(
                f"particle indices must lie in [0, {self.n_particles}), "
                f"got [{int(particle.min())}, {int(particle.max())}]"
            )
        self.vehicle_shape = tuple(particle.shape)
        self.vehicle_particle = particle.reshape(-1).to(self.device, torch.long)
        self._clock = 0
        self._rebuild()

    def resample(self, generator: torch.Generator | None = None) -> None:
        """Redraw every vehicle's particle (the generator given to :meth:`sample`
        unless another is given); the memory restarts from a steady past."""
        if self.n_vehicles == 0:
            raise ValueError("no vehicles: call sample() first")
        if generator is not None:
            self._generator = generator
        self.assign(self._draw(self.vehicle_shape))

    def tick(self) -> bool:
        """Count one step of ``dt``; redraw when ``resample_every`` has elapsed.

        Returns:
            True if the vehicles were redrawn.
        """
        self._clock += 1
        if self.resample_every is None:
            return False
        if self._clock * self.dt < self.resample_every - 1e-9 * self.dt:
            return False
        self.resample()
        return True

    def _draw(self, shape: tuple[int, ...]) -> Tensor:
        generator = self._generator
        where = generator.device if generator is not None else self.device
        drawn = torch.randint(
            0, self.n_particles, shape, generator=generator, device=where
        )
        return drawn.to(self.device)

    @property
    def vehicle_model(self) -> Tensor:
        """``vehicle_shape`` int64: the index in :attr:`model_names` of each
        vehicle's model."""
        return self.particle_model[self.vehicle_particle].reshape(self.vehicle_shape)

    @property
    def acceleration_is_state(self) -> Tensor:
        """``vehicle_shape`` bool: True where the recorded acceleration is a state
        of the vehicle (HL, ``+lag``), False where it is the command."""
        return self._acceleration_is_state.reshape(self.vehicle_shape)

    def _rebuild(self) -> None:
        """Group the vehicles by model and prepare each group's parameters.

        Runs when the assignment, the device or the dtype change, never per step;
        MPC factorises its vehicles' QPs here.
        """
        flat = self.vehicle_particle
        vehicle_model = self.particle_model[flat]  # (V,)
        groups = []
        state_flags = torch.zeros(flat.shape, dtype=torch.bool, device=self.device)
        for m, model in enumerate(self.models):
            index = (vehicle_model == m).nonzero().squeeze(1)  # (V_g,)
            if index.numel() == 0:
                continue
            theta = self.get_buffer(f"theta_{m}")[self.particle_row[flat[index]]]
            prepared = model.prepare(
                model.unpack(theta, state_ndim=1), self.dt, (index.numel(),)
            )
            groups.append(
                _Group(m, model, index, prepared, index.numel() == flat.numel())
            )
            if model.acceleration_is_state:
                state_flags[index] = True
        self._groups = groups
        self._acceleration_is_state = state_flags
        self._memory = None

    # --------------------------------------------------------------- stepping
    @property
    def memory(self) -> list[Any] | None:
        """What the models carry between steps, one pytree per model group (None
        before the first ``forward`` of an assignment). Assignable, e.g. to
        branch a simulation from a saved point."""
        return self._memory

    @memory.setter
    def memory(self, value: list[Any] | None) -> None:
        self._memory = value

    def reset_memory(self) -> None:
        """Forget the memory: the next ``forward`` starts from a steady past."""
        self._memory = None

    def forward(
        self,
        spacing: Tensor,
        v: Tensor,
        v_leader: Tensor,
        a: Tensor,
        position: Tensor | None = None,
    ) -> Tensor:
        """The acceleration command of every vehicle, each by its own particle.

        For the vehicles of model ``m`` with parameters ``theta``:
        ``u = m.command(theta, Perception(spacing, v, v_leader, a, L, position))``
        (SPEC section 3; effects included), with the model's memory carried from
        the previous call (see the module docstring).

        Args:
            spacing: ``vehicle_shape`` front-to-front spacing ``x_leader - x`` [m].
            v: own speed [m/s].
            v_leader: the leader's speed [m/s].
            a: own realised acceleration [m/s^2] (HL and ``+lag`` read it).
            position: own road position [m]; needed only by models that read it
                (the ``grade`` effect).

        Returns:
            ``vehicle_shape`` command ``u`` [m/s^2], the sampler's dtype.
        """
        self._check(spacing=spacing, v=v, v_leader=v_leader, a=a, position=position)
        command, self._memory = self._commands(
            (spacing, v, v_leader, a), position, self._memory
        )
        return command.reshape(spacing.shape)

    def _commands(
        self,
        inputs: tuple[Tensor, Tensor, Tensor, Tensor],
        position: Tensor | None,
        memory: list[Any] | None,
    ) -> tuple[Tensor, list[Any]]:
        """Group by group: gather, the model's command, scatter. ``(V,)`` out."""
        flat = [t.reshape(-1) for t in inputs]  # each (V,)
        flat_position = position.reshape(-1) if position is not None else None
        command = None
        next_memory = []
        for k, group in enumerate(self._groups):
            # Only models that read their road position get it (others must not
            # need it; this saves a gather per group).
            here = flat_position if group.model.uses_position else None
            if group.covers_all:
                spacing, v, v_leader, a = flat
            else:
                spacing, v, v_leader, a = (t.index_select(0, group.index) for t in flat)
                if here is not None:
                    here = here.index_select(0, group.index)  # (V_g,)
            obs = Perception(spacing, v, v_leader, a, self.leader_length, here)
            state = (
                group.model.initial_memory(group.prepared, obs)
                if memory is None
                else memory[k]
            )
            step = _command if group.model.compilable else _command_eager()
            u, state = step(group.model, group.prepared, obs, state)
            next_memory.append(state)
            if group.covers_all:
                command = u
            else:
                if command is None:
                    command = torch.empty_like(flat[0])
                # In place into the fresh buffer: one pass over V per step, not
                # one per group.
                command.index_copy_(0, group.index, u)
        return command, next_memory

    def advance(self, x: Tensor, v: Tensor, a: Tensor, u: Tensor) -> FollowerState:
        """Realise the commands over one step ``dt`` (SPEC section 2).

        Each vehicle moves by its model's realisation (a point mass, or the exact
        first-order lag of HL and ``+lag``), then ``v >= 0`` and ``x`` never
        decreases: :func:`torchcf.sim.rollout.realise`, the rollout's own update.

        Args:
            x: ``vehicle_shape`` position [m] (any frame: the update only adds to
                it; pass zeros to get each vehicle's displacement).
            v: speed [m/s].
            a: realised acceleration [m/s^2].
            u: the commands of :meth:`forward` [m/s^2].

        Returns:
            FollowerState ``(x, v, a)`` at t + dt, each ``vehicle_shape``.
        """
        self._check(x=x, v=v, a=a, u=u)
        shape = x.shape
        state = FollowerState(*(t.reshape(-1) for t in (x, v, a)))  # (V,) each
        u = u.reshape(-1)
        moved = None
        if any(g.model.realises_as_point_mass for g in self._groups):
            # Every vehicle as a point mass in one pass; lag groups overwrite below.
            moved = realise(_POINT_MASS, None, state, u, self.dt)
        for group in self._groups:
            if group.model.realises_as_point_mass:
                continue
            if group.covers_all:
                moved = realise(group.model, group.prepared, state, u, self.dt)
                continue
            index = group.index
            # Out of place: the point-mass pass's acceleration is the caller's u.
            own = realise(
                group.model,
                group.prepared,
                FollowerState(*(t.index_select(0, index) for t in state)),
                u.index_select(0, index),
                self.dt,
            )  # (V_g,) each
            moved = FollowerState(
                *(
                    whole.index_copy(0, index, part)
                    for whole, part in zip(moved, own, strict=True)
                )
            )
        return FollowerState(*(t.reshape(shape) for t in moved))

    def equilibrium_speed(
        self,
        spacing: float | Tensor,
        *,
        v_max: float = 40.0,
        iterations: int = 40,
        position: Tensor | None = None,
    ) -> Tensor:
        """Each vehicle's steady speed at a spacing: ``u(s, v, v_leader=v, a=0) = 0``.

        Bisection on ``[0, v_max]`` (the command falls as the speed grows) with
        the models' commands from a steady past; the memory is left alone. 0 where
        even standing still the command is negative, ``v_max`` where it stays
        positive (LLCS's constant-spacing policy has no equilibrium speed: it gets
        one of the two).

        Args:
            spacing: front-to-front spacing [m], a number or ``vehicle_shape``.
            v_max: upper end of the search [m/s].
            iterations: bisection steps (error ``v_max / 2^iterations``).
            position: road position [m] for models that read it (default 0).

        Returns:
            ``vehicle_shape`` speed [m/s].
        """
        spacing = self._steady_tensor(spacing)
        return increasing_root(
            lambda v: -self._steady_command(spacing, v, position),
            torch.zeros_like(spacing),
            torch.full_like(spacing, v_max),
            iterations,
        )

    def equilibrium_spacing(
        self,
        v: float | Tensor,
        *,
        s_min: float = 0.0,
        s_max: float | Tensor = 1000.0,
        iterations: int = 50,
        position: Tensor | None = None,
    ) -> Tensor:
        """Each vehicle's steady spacing at a speed: ``u(s, v, v_leader=v, a=0) = 0``.

        Bisection on ``[s_min, s_max]`` (the command grows with the spacing) with
        the models' commands from a steady past; the memory is left alone.
        ``s_max`` where the command stays negative (the speed is above what the
        model reaches at any spacing up to ``s_max``), ``s_min`` where it stays
        positive (a model that still accelerates at ``s_min``: OVM, GFM or FVDM
        with ``V(s_min - L) > v``).

        Args:
            v: speed [m/s], a number or ``vehicle_shape``.
            s_min: lower end of the search [m].
            s_max: upper end of the search [m], a number or broadcastable to
                ``vehicle_shape``.
            iterations: bisection steps (error ``s_max / 2^iterations``).
            position: road position [m] for models that read it (default 0).

        Returns:
            ``vehicle_shape`` spacing [m].
        """
        v = self._steady_tensor(v)
        high = torch.zeros_like(v) + torch.as_tensor(
            s_max, dtype=v.dtype, device=v.device
        )
        return increasing_root(
            lambda spacing: self._steady_command(spacing, v, position),
            torch.full_like(v, s_min),
            high,
            iterations,
        )

    def _steady_tensor(self, value: float | Tensor) -> Tensor:
        if self.n_vehicles == 0:
            raise ValueError("no vehicles: call sample() first")
        zero = torch.zeros(self.vehicle_shape, dtype=self.dtype, device=self.device)
        return zero + torch.as_tensor(value, dtype=self.dtype, device=self.device)

    def _steady_command(
        self, spacing: Tensor, v: Tensor, position: Tensor | None
    ) -> Tensor:
        """``u(s, v, v_leader = v, a = 0)`` from a steady past, ``vehicle_shape``."""
        if position is None and any(g.model.uses_position for g in self._groups):
            position = torch.zeros_like(v)
        zero = torch.zeros_like(v)
        command, _ = self._commands((spacing, v, v, zero), position, None)
        return command.reshape(self.vehicle_shape)

    def _check(self, **tensors: Tensor | None) -> None:
        """One-line errors for inputs that do not fit the assignment."""
        if self.n_vehicles == 0:
            raise ValueError("no vehicles: call sample() or assign() first")
        for name, t in tensors.items():
            if t is None:
                if name == "position" and any(
                    g.model.uses_position for g in self._groups
                ):
                    raise ValueError("a model of the sampler reads position: pass it")
                continue
            if tuple(t.shape) != self.vehicle_shape:
                raise ValueError(
                    f"{name} must have the vehicles' shape {self.vehicle_shape}, "
                    f"got {tuple(t.shape)}"
                )
            if t.dtype != self.dtype:
                raise ValueError(
                    f"{name} is {t.dtype} but the sampler is {self.dtype} "
                    "(convert one of them, e.g. sampler.double())"
                )
            if t.device != self.device:
                raise ValueError(
                    f"{name} is on {t.device} but the sampler is on {self.device}"
                )

    # ------------------------------------------------- nn.Module integration
    def _apply(self, fn, recurse=True):  # type: ignore[override]
        super()._apply(fn, recurse)
        memory = self._memory
        # The prepared parameters derive from the buffers: prepare them again on
        # the new device / in the new dtype; the memory's tensors follow as they are.
        self._rebuild()
        if memory is not None:
            self._memory = pytree.tree_map(
                lambda t: fn(t) if isinstance(t, Tensor) else t, memory
            )
        return self

    def get_extra_state(self) -> TorchPayload:
        return {
            "models": list(self.model_names),
            "dt": self.dt,
            "leader_length": self.leader_length,
            "vehicle_shape": list(self.vehicle_shape),
            "resample_every": self.resample_every,
        }

    def set_extra_state(self, state: TorchPayload) -> None:
        mine = self.get_extra_state()
        for key in ("models", "dt", "leader_length"):
            if state[key] != mine[key]:
                raise ValueError(
                    f"state_dict of another sampler: {key} {state[key]!r}, "
                    f"this one {mine[key]!r}"
                )
        self.vehicle_shape = tuple(state["vehicle_shape"])
        self.resample_every = state["resample_every"]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        # The assignment's size is the saved one, whatever this sampler holds.
        key = prefix + "vehicle_particle"
        if key in state_dict:
            self.vehicle_particle = torch.empty_like(
                state_dict[key], device=self.device, dtype=torch.long
            )
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        if math.prod(self.vehicle_shape) != self.n_vehicles:
            self.vehicle_shape = (self.n_vehicles,)
        self._clock = 0
        self._rebuild()

    def extra_repr(self) -> str:
        shares = ", ".join(f"{k} {v:.3f}" for k, v in self.shares.items() if v > 0)
        return (
            f"{self.n_particles} particles ({shares}), dt={self.dt:g} s, "
            f"vehicles={self.vehicle_shape}, {self.dtype}"
        )


def increasing_root(
    f, low: Tensor, high: Tensor, iterations: int, *, bracket: bool = False
) -> Tensor | tuple[Tensor, Tensor]:
    """Elementwise bisection for ``f(x) = 0`` with ``f`` increasing on ``[low, high]``.

    Where ``f`` keeps one sign the result tends to the end it points to (``low``
    if ``f(low) >= 0``, ``high`` if ``f(high) <= 0``); NaN counts as negative.

    Returns:
        the midpoint of the final bracket, or with ``bracket`` the bracket
        ``(low, high)`` itself (``f(low) <= 0 < f(high)`` where ``f`` changes
        sign).
    """
    for _ in range(iterations):
        middle = 0.5 * (low + high)
        above = f(middle) > 0
        low, high = torch.where(above, low, middle), torch.where(above, middle, high)
    return (low, high) if bracket else 0.5 * (low + high)


def _data_constants(dataset: str, run_dir: Path) -> tuple[float | None, float | None]:
    """``(dt, leader_length)`` of a posterior's data set, where they can be
    known: the run's ``summary.json`` (which records its training pairs'), the
    registry's for a named set, else the config's ``data`` section and, for a
    folder, its ``meta.json`` (the leader length its loader took: 5.0 m where
    the folder states none)."""
    run = RunDir(run_dir)
    try:
        summary = run.read_summary()
    except RunFileError:
        summary = None
    # a training's summary (a re-calibration's records neither)
    if (
        isinstance(summary, RunSummary)
        and summary.dt is not None
        and summary.leader_length is not None
    ):
        return summary.dt, summary.leader_length
    if dataset in DATASETS:
        spec = DATASETS[dataset]
        return spec.dt, spec.leader_length
    try:
        data = run.read_config_json()["data"]
        dt, length = data.get("dt"), data.get("leader_length")
        if data.get("path") and (dt is None or length is None):
            meta = read_meta(Path(data["path"]))
            dt = meta.get("dt") if dt is None else dt
            length = meta.get("leader_length", 5.0) if length is None else length
        return dt, length
    except (RunFileError, DataError, OSError, KeyError, TypeError, AttributeError):
        return None, None


__all__ = ["HybridSampler", "increasing_root"]
