"""Dimension letters and tensor aliases used in every docstring (no logic).

Shapes are written with fixed letters, time first:

- ``P`` particles (parameter draws),
- ``N`` leader-follower pairs,
- ``T`` time steps,
- ``K`` model parameters,
- ``B`` QP instances.

A step state is ``(P, N)`` in the *full* layout (every particle on every pair) and
``(P,)`` in the *paired* layout (particle ``j`` on pair ``pair_index[j]``).
Trajectories are time-major: ``(T, P, N)`` or ``(T, P)``.
"""

from torch import Tensor

#: Any float tensor; the shape is written in the docstring that uses it.
FloatTensor = Tensor
#: Any bool tensor.
BoolTensor = Tensor
#: Any int64 tensor.
LongTensor = Tensor

__all__ = ["FloatTensor", "BoolTensor", "LongTensor"]
