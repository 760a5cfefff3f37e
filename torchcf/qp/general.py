"""The public solver for a general constraint matrix: :func:`solve_qp_batch`.

Imports every lower layer it needs (:mod:`~torchcf.qp.problem`,
:mod:`~torchcf.qp.admm`, :mod:`~torchcf.qp.polish`); nothing imports it but the
package's ``__init__``.
"""

from __future__ import annotations

from torch import Tensor

from .admm import kkt_inverse, osqp_starting_iterate, rho_vector
from .polish import admm_then_polish
from .problem import (
    ProblemData,
    QPResult,
    QPSettings,
    batch_first_result,
    batch_last_bounds,
    check_shape,
)


def solve_qp_batch(
    P: Tensor,
    q: Tensor,
    A: Tensor,
    l: Tensor,  # noqa: E741
    u: Tensor,
    *,
    settings: QPSettings | None = None,
    x0: Tensor | None = None,
    y0: Tensor | None = None,
) -> QPResult:
    """Solve ``min 1/2 x'Px + q'x s.t. l <= Ax <= u`` for a batch of instances.

    OSQP's ADMM (Stellato et al. 2020, Algorithm 1) per instance, with per-instance
    termination, adaptive rho, infeasibility detection and polishing; see
    :mod:`torchcf.qp`. Bounds may be ``-inf`` / ``+inf``; rows with ``l == u`` are
    equalities.

    Args:
        P: (B, n, n) symmetric positive semidefinite.
        q: (B, n).
        A: (B, m, n).
        l: (B, m) lower bounds, ``l <= u``.
        u: (B, m) upper bounds.
        settings: solver settings; default :class:`QPSettings()`.
        x0: (B, n) optional warm start of the primal iterate.
        y0: (B, m) optional warm start of the dual iterate.

    Returns:
        :class:`QPResult` in the dtype and on the device of ``q``.

    Examples:
        >>> import torch
        >>> from torchcf.qp import INFTY, QPStatus, solve_qp_batch
        >>> P = torch.eye(2, dtype=torch.float64)[None]  # (B, n, n), B = 1
        >>> q = torch.tensor([[-1.0, -1.0]], dtype=torch.float64)
        >>> A = torch.ones(1, 1, 2, dtype=torch.float64)  # one row: x1 + x2
        >>> l, u = torch.tensor([[-1.0]]).double(), torch.tensor([[1.0]]).double()
        >>> result = solve_qp_batch(P, q, A, l, u)  # x1 + x2 <= 1
        >>> [round(x, 3) for x in result.x[0].tolist()]
        [0.5, 0.5]
        >>> QPStatus(int(result.status[0])).name
        'SOLVED'
        >>> A2 = torch.ones(1, 2, 2, dtype=torch.float64)  # x1 + x2 >= 2 and <= 1
        >>> l2 = torch.tensor([[2.0, -INFTY]]).double()
        >>> u2 = torch.tensor([[INFTY, 1.0]]).double()
        >>> QPStatus(int(solve_qp_batch(P, q, A2, l2, u2).status[0])).name
        'PRIMAL_INFEASIBLE'
    """
    settings = settings or QPSettings()
    batch, n = q.shape
    m = A.shape[1]
    check_shape("P", P, (batch, n, n))
    check_shape("A", A, (batch, m, n))
    check_shape("l", l, (batch, m))
    check_shape("u", u, (batch, m))
    check_shape("x0", x0, (batch, n))
    check_shape("y0", y0, (batch, m))
    dtype = q.dtype
    lower, upper, _ = batch_last_bounds(l, u, dtype)
    data = ProblemData(
        P=P.to(dtype).permute(1, 2, 0).contiguous(),
        q=q.T.contiguous(),
        A=A.to(dtype).permute(1, 2, 0).contiguous(),
        l=lower,
        u=upper,
    )
    rho = q.new_full((batch,), settings.rho)
    inverse = kkt_inverse(data, rho_vector(rho, data), settings.sigma)
    start = osqp_starting_iterate(data, x0, y0, n, m)
    outcome, polished = admm_then_polish(data, start, rho, inverse, settings)
    return batch_first_result(
        outcome.x, outcome.y, outcome.z, outcome.n_iter, outcome.status, polished
    )
