"""A pool model wrapped by effects (:mod:`torchcf.models.effects`).

:class:`AugmentedModel` is a :class:`~torchcf.models.base.CFModel` whose
parameters are the base model's, then each effect's; every step runs the
perception effects, the base's command, the command effects, and the
realisation effect's motion (or the base's). Its registry name is
``"<model>+<effect>+..."``, the effects in the canonical order of
:data:`~torchcf.models.effects.EFFECTS`.
"""

from __future__ import annotations

from collections import namedtuple

from torch import Tensor

from .base import CFModel
from .effects import EFFECTS, Effect


class AugmentedModel(CFModel):
    """A pool model wrapped by effects; parameters = the model's, then each effect's.

    Args:
        base: the wrapped model (not itself augmented).
        effects: at most one of each kind and at most one realisation effect.

    Examples:
        >>> from torchcf import get_model
        >>> model = get_model("idm+lag")
        >>> type(model).__name__, model.pool_model.name, model.effect_kinds
        ('AugmentedModel', 'idm', ('lag',))
        >>> model.param_names[-1], model.acceleration_is_state
        ('t_lag', True)
    """

    def __init__(self, base: CFModel, effects: list[Effect]) -> None:
        if isinstance(base, AugmentedModel):
            raise ValueError("wrap the pool model, not an augmented model")
        if not effects:
            raise ValueError("an augmented model needs at least one effect")
        order = list(EFFECTS)
        effects = sorted(effects, key=lambda e: order.index(e.name))
        names = [e.name for e in effects]
        if len(set(names)) != len(names):
            raise ValueError(f"effect listed twice in {base.name}+{'+'.join(names)}")
        for effect in effects:
            effect.check(base)
        self.base = base
        self.effects = tuple(effects)
        self.name = "+".join([base.name] + [e.token for e in effects])
        self.param_specs = base.param_specs + tuple(
            p for e in effects for p in e.param_specs
        )
        names = [p.name for p in self.param_specs]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: parameter names collide: {names}")
        self.Params = namedtuple(  # noqa: PYI024 - built per composition
            "AugmentedParams", names
        )
        self.acceleration_is_state = base.acceleration_is_state or any(
            e.acceleration_is_state for e in effects
        )
        self.compilable = base.compilable
        self.corrects = base.corrects
        self.chunk_cells = base.chunk_cells
        self.batch_size_invariant = base.batch_size_invariant
        self.prunable = base.prunable
        self.uses_position = base.uses_position or any(e.uses_position for e in effects)
        self._realiser = next((e for e in effects if e.stage == "realisation"), None)
        # Parameter slices: the base's first, then each effect's.
        bounds, start = [], base.n_params
        for effect in effects:
            bounds.append(slice(start, start + len(effect.param_specs)))
            start += len(effect.param_specs)
        self._slices = tuple(bounds)

    @property
    def pool_model(self) -> CFModel:
        """The wrapped pool model."""
        return self.base

    @property
    def realises_as_point_mass(self) -> bool:
        """The base's realisation, unless an effect realises the command itself."""
        return self._realiser is None and self.base.realises_as_point_mass

    def check_bounds(self, box: Tensor) -> None:
        """Raise ValueError when a prior box (K, 2) is outside what the effects run."""
        for effect, part in zip(self.effects, self._slices, strict=True):
            effect.check_bounds(box[part])

    def prepare(self, p, dt, state_shape):
        fields = tuple(p)
        base = self.base.prepare(
            self.base.Params(*fields[: self.base.n_params]), dt, state_shape
        )
        own = tuple(
            effect.prepare(fields[part], dt)
            for effect, part in zip(self.effects, self._slices, strict=True)
        )
        return _Prepared(base, own)

    def initial_memory(self, p, first):
        # Each effect's memory starts from the perception as the earlier
        # perception effects hand it on (a delay's steady past includes an
        # offset), and the base's from what it perceives at the first step.
        perceived, memories = first, []
        for effect, q in zip(self.effects, p.effects, strict=True):
            memory = effect.initial_memory(q, perceived)
            if effect.stage == "perception":
                perceived, _ = effect.perceive(q, perceived, memory)
            memories.append(memory)
        return self.base.initial_memory(p.base, perceived), tuple(memories)

    def command_with_memory(self, p, obs, memory):
        perceived, base_memory, effect_memory = self._perceive(p, obs, memory)
        u, base_memory = self.base.command_with_memory(p.base, perceived, base_memory)
        return self._act(p, obs, u, base_memory, effect_memory)

    def draft_with_memory(self, p, obs, memory):
        """A correcting base (:attr:`CFModel.corrects`): the perception effects
        and the base's draft; the true ``obs`` rides along for the command
        effects, which act after the correction."""
        perceived, base_memory, effect_memory = self._perceive(p, obs, memory)
        pending, base_memory = self.base.draft_with_memory(
            p.base, perceived, base_memory
        )
        return (pending, obs), (base_memory, effect_memory)

    def correct(self, p, pending, memory):
        base_pending, obs = pending
        base_memory, effect_memory = memory
        u, base_memory = self.base.correct(p.base, base_pending, base_memory)
        return self._act(p, obs, u, base_memory, effect_memory)

    def _split_memory(self, memory):
        """The base's memory and a tuple of the effects' (None where absent)."""
        base_memory, effect_memory = memory if memory is not None else (None, None)
        if effect_memory is None:
            effect_memory = (None,) * len(self.effects)
        return base_memory, effect_memory

    def _perceive(self, p, obs, memory):
        """The perception stage: what the base perceives, the base's memory and
        the effects' memories after it."""
        base_memory, effect_memory = self._split_memory(memory)
        perceived, next_memory = obs, []
        for effect, q, mem in zip(self.effects, p.effects, effect_memory, strict=True):
            if effect.stage == "perception":
                perceived, mem = effect.perceive(q, perceived, mem)
            next_memory.append(mem)
        return perceived, base_memory, tuple(next_memory)

    def _act(self, p, obs, u, base_memory, effect_memory):
        """The command stage on the base's command ``u``; the command and the
        memory for the next step."""
        next_memory = list(effect_memory)
        for i, (effect, q) in enumerate(zip(self.effects, p.effects, strict=True)):
            if effect.stage == "command":
                u, next_memory[i] = effect.act_with_memory(q, obs, u, next_memory[i])
        return u, (base_memory, tuple(next_memory))

    def select_particles(self, p, memory, rows):
        base_memory, effect_memory = self._split_memory(memory)
        base, base_memory = self.base.select_particles(p.base, base_memory, rows)
        own, memories = [], []
        for effect, q, mem in zip(self.effects, p.effects, effect_memory, strict=True):
            q, mem = effect.select(q, mem, rows)
            own.append(q)
            memories.append(mem)
        kept = _Prepared(base, tuple(own))
        return kept, None if memory is None else (base_memory, tuple(memories))

    def command(self, p, obs):
        """The command for ``obs`` with a steady past (a delay then sees ``obs``)."""
        return self.command_with_memory(p, obs, self.initial_memory(p, obs))[0]

    def advance(self, p, state, u, dt):
        if self._realiser is not None:
            index = self.effects.index(self._realiser)
            return self._realiser.advance(p.effects[index], state, u, dt)
        return self.base.advance(p.base, state, u, dt)

    def __repr__(self) -> str:
        return f"AugmentedModel({self.name})"


_Prepared = namedtuple("_Prepared", ["base", "effects"])
