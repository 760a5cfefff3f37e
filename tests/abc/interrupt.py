"""What the resume tests share: a training killed after its n-th simulate call
(its checkpoints stay, as after Ctrl-C), and the comparison of two runs'
buffers bit for bit."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import pytest
import torch

import torchcf.abc.rejection as rejection_module
from torchcf.posterior import Posterior


def interrupt_after(calls: int, run: Callable[[], object]) -> None:
    """Run ``run`` with the rejection engine's ``simulate`` raising
    KeyboardInterrupt at its call ``calls + 1``; the interrupt must come."""
    made = [0]
    real = rejection_module.simulate

    def interrupted(*args, **kwargs):
        made[0] += 1
        if made[0] > calls:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(rejection_module, "simulate", interrupted)
        with pytest.raises(KeyboardInterrupt):
            run()


def same_buffers(
    a: Posterior, b: Posterior, models: Iterable[str] | None = None
) -> None:
    """The buffers (score, index, theta) of ``models`` (default: all of ``a``'s)
    are equal bit for bit."""
    for name in models if models is not None else a.models:
        for key in ("score", "index", "theta"):
            assert torch.equal(a.buffers[name][key], b.buffers[name][key]), (name, key)
