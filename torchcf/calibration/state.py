"""A calibration's state, what a checkpoint of it holds: per model its
per-pair buffer, its progress and (SMC, a refinement) its population.

A buffer (:class:`~torchcf.abc.TopN`) holds ``score`` ``(N, B)`` (ascending per
pair), ``index`` ``(N, B)`` (the particle's number in its model's stream) and
``theta`` ``(N, B, K)`` (SI units; one more column, ``log r``, under SMC and an
amortised calibration's refinement), for ``N`` training pairs and ``B =
SelectionRule.buffer_size`` slots.

A state starts empty, or from saved state dicts (a resumed run:
``saved_buffers``, ``saved_smc``) which :func:`build_buffers` loads into the
buffers it makes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from ..abc.rejection import ModelProgress
from ..abc.smc import SMCSettings, SMCState, new_state
from ..abc.topn import TopN
from ..models import CFModel, require_model
from ..system.files import TorchPayload
from .budget import CalibrationError


class StateError(CalibrationError):
    """A saved state that does not fit the calibration (one-line message)."""


@dataclass
class CalibrationState:
    """Per model (by name): its progress, buffer and refinement state.

    Attributes:
        progress: how far each model's stream went.
        buffers: each model's per-pair top-B buffer.
        smc: each model's refinement state (SMC, or a refinement).
        saved_buffers: buffer state dicts read from a checkpoint, until
            :func:`build_buffers` loads them.
        saved_smc: refinement state dicts likewise.
        refinement_before: per model, its share and median best score on the
            amortised samples before the refinement (an amortised
            calibration's refinement only).

    Examples:
        >>> from torchcf import get_model
        >>> state = CalibrationState()
        >>> build_buffers([get_model("idm")], n_pairs=3, buffer_size=5, smc=None,
        ...               state=state)
        >>> state.buffers["idm"].score.shape, state.progress["idm"].next
        (torch.Size([3, 5]), 0)
    """

    progress: dict[str, ModelProgress] = field(default_factory=dict)
    buffers: dict[str, TopN] = field(default_factory=dict)
    smc: dict[str, SMCState] = field(default_factory=dict)
    saved_buffers: dict[str, TorchPayload] = field(default_factory=dict)
    saved_smc: dict[str, TorchPayload] = field(default_factory=dict)
    refinement_before: dict[str, dict[str, float | None]] | None = None

    def as_payload(self) -> TorchPayload:
        """The state's tensors and records, as a checkpoint stores them."""
        payload = {
            "progress": {k: v.as_dict() for k, v in self.progress.items()},
            "buffers": {k: b.state_dict() for k, b in self.buffers.items()},
        }
        if self.smc:
            payload["smc"] = {k: v.state_dict() for k, v in self.smc.items()}
        if self.refinement_before is not None:
            payload["refinement_before"] = {
                k: dict(v) for k, v in self.refinement_before.items()
            }
        return payload


def build_buffers(
    models: Sequence[CFModel],
    n_pairs: int,
    buffer_size: int,
    smc: SMCSettings | None,
    state: CalibrationState,
    held: Mapping[str, int] | None = None,
) -> None:
    """Every model's buffer into ``state`` (from its saved state where it has
    one), its progress and, with ``smc``, its refinement state, whose buffer
    carries one more column, ``log r``.

    Args:
        models: the calibration's models; each buffer is keyed by its name.
        n_pairs: training pairs ``N``.
        buffer_size: slots per pair ``B``.
        smc: the refinement's settings; None for rejection.
        state: the state; its saved buffers (a resumed run) are loaded.
        held: per model name, its last parameters held at one value (not
            drawn): an SMC buffer and population hold the drawn ones alone.

    Raises:
        StateError: a saved buffer or refinement state does not fit.
    """
    for model in models:
        name = require_model(model, "build_buffers").name
        n_params = len(model.param_names)
        if smc is not None:  # SMC moves the drawn parameters alone
            n_params -= (held or {}).get(name, 0)
        buffer = TopN(n_pairs, buffer_size, n_params + (smc is not None))
        refinement = None if smc is None else new_state(n_pairs, smc, n_params)
        try:
            if name in state.saved_buffers:
                buffer.load_state_dict(state.saved_buffers[name])
            if refinement is not None and name in state.saved_smc:
                refinement.load_state_dict(state.saved_smc[name])
        except (KeyError, ValueError, TypeError) as error:
            raise StateError(f"{name}: {error}") from None
        state.buffers[name] = buffer
        if refinement is not None:
            state.smc[name] = refinement
        state.progress.setdefault(name, ModelProgress())


__all__ = ["CalibrationState", "StateError", "build_buffers"]
