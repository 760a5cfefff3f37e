"""Batched convex QP solver: ADMM in the OSQP form, and exact active-set solves.

Solves, for ``B`` independent instances of the same shape,

    min 1/2 x'Px + q'x   s.t.   l <= A x <= u,

``x`` of ``n`` variables, ``m`` constraint rows, ``P`` symmetric positive
semidefinite, by the ADMM of OSQP (Stellato, Banjac, Goulart, Bemporad & Boyd 2020,
"OSQP: an operator splitting solver for quadratic programs", Algorithm 1) with its
adaptive rho, infeasibility certificates and polish. Two entry points:

- :func:`solve_qp_batch` for a general ``A: (B, m, n)``;
- :class:`BoxQP` for ``A = I``, which factorises once per ``P`` and, before ADMM,
  solves exactly on guessed active sets (on the MPC QPs that finishes nearly every
  instance).

The public API is batch-first, ``(B, n)``; internally every tensor is batch-last,
``(n, B)``, ``(n, n, B)``. Timings are in ``reports/bench_qp.md``
(``tools/bench_qp.py``).

Map of the package, lowest layer first; a module imports only modules above it in
this list, never one below:

- :mod:`~torchcf.qp.kernels`: batch-last linear algebra: matrix-vector products,
  norms, gathering and scattering instances, the layout change, Cholesky (and its
  "UL" variant), solves, the SPD inverse, triangular sweeps.
- :mod:`~torchcf.qp.problem`: :class:`QPStatus`, :class:`QPSettings`,
  :class:`QPResult`, ``INFTY``; the batch-last problem data; bounds and results
  between the two layouts; the round-off floor of the tolerances.
- :mod:`~torchcf.qp.admm`: OSQP's ADMM iterations, termination checks,
  infeasibility certificates, adaptive rho and starting iterates.
- :mod:`~torchcf.qp.polish`: exact solves on a guessed active set, their KKT
  acceptance test and active-set corrections; OSQP's polish after ADMM.
- :mod:`~torchcf.qp.leading`: box QPs whose active bounds are a leading block:
  the per-``P`` factors, exact solves and rank-one boundary steps on them, their
  acceptance test. Imports kernels and problem only.
- :mod:`~torchcf.qp.active_set`: BoxQP's leading-block stage, the active-set
  passes over :mod:`~torchcf.qp.leading`'s solves.
- :mod:`~torchcf.qp.general`: :func:`solve_qp_batch`.
- :mod:`~torchcf.qp.boxqp`: :class:`BoxQP`, its stages.

This ``__init__`` only re-exports the public names.
"""

from .boxqp import BoxQP
from .general import solve_qp_batch
from .problem import INFTY, QPResult, QPSettings, QPStatus

__all__ = ["INFTY", "BoxQP", "QPResult", "QPSettings", "QPStatus", "solve_qp_batch"]
