"""The problem, its settings and its result; the problem data in the working layout.

For ``B`` independent instances of the same shape the solver finds

    min 1/2 x'Px + q'x   s.t.   l <= A x <= u,

``x`` of ``n`` variables, ``m`` constraint rows, ``P`` symmetric positive
semidefinite. The public types (:class:`QPStatus`, :class:`QPSettings`,
:class:`QPResult`) are batch-first, ``(B, n)``; :class:`ProblemData` holds the same
problems batch-last, ``(n, B)``, as every kernel reads them (see
:mod:`torchcf.qp.kernels`).

Also here: the round-off floor that both the ADMM termination and the exact solves'
acceptance tests raise their tolerances to (:func:`roundoff_floor`).

Imports only :mod:`torchcf.qp.kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

import torch
from torch import Tensor

from .kernels import mv, rmv, swap_layout, take_instances

#: Bounds beyond +-this are infinite (OSQP's OSQP_INFTY); +-inf inputs are clamped here.
INFTY = 1e30
#: A bound whose magnitude exceeds this is treated as infinite (OSQP: INFTY * 1e-4).
INF_THRESHOLD = INFTY * 1e-4
#: Relative tolerances are raised by this many machine epsilons: residuals below a
#: hundred ulps of the quantities they difference are round-off (see
#: :func:`torchcf.qp.admm.admm_iterations` and :func:`roundoff_floor`).
ROUNDOFF_ULPS = 100


class QPStatus(IntEnum):
    """Per-instance outcome of a solve.

    Examples:
        >>> from torchcf.qp import QPStatus
        >>> QPStatus(2).name, int(QPStatus.SOLVED)  # QPResult.status holds the values
        ('PRIMAL_INFEASIBLE', 0)
    """

    SOLVED = 0
    MAX_ITER = 1
    PRIMAL_INFEASIBLE = 2
    DUAL_INFEASIBLE = 3


@dataclass(frozen=True)
class QPSettings:
    """ADMM settings; the names and defaults follow OSQP's where they exist.

    Attributes:
        rho: initial ADMM step size of an inequality row (equality rows use
            ``1e3 rho``, rows without bounds ``1e-6``).
        sigma: regularisation of the x-update (keeps a singular ``P`` invertible).
        alpha: over-relaxation, in (0, 2).
        eps_abs, eps_rel: absolute and relative tolerances of the primal residual
            ``||Ax - z||_inf`` and of the dual residual ``||Px + q + A'y||_inf``.
        eps_prim_inf, eps_dual_inf: tolerances of the infeasibility certificates.
        max_iter: iteration limit per instance.
        check_every: residuals, infeasibility and rho are checked every this many
            iterations (each check costs about two iterations and a host sync).
        adaptive_rho: rescale rho per instance from the residual ratio (OSQP's rule).
        adaptive_rho_tolerance: refactorise only when the new rho differs from the
            current one by more than this factor.
        polish: refine solved instances by an exact solve on the guessed active set.

    Examples:
        >>> import torch
        >>> from torchcf.qp import INFTY, QPStatus, solve_qp_batch
        >>> P = torch.eye(2, dtype=torch.float64)[None]  # (B, n, n), B = 1
        >>> q = torch.tensor([[-1.0, -1.0]], dtype=torch.float64)
        >>> A = torch.ones(1, 1, 2, dtype=torch.float64)  # one row: x1 + x2
        >>> from torchcf.qp import QPSettings
        >>> l, u = torch.tensor([[-1.0]]).double(), torch.tensor([[1.0]]).double()
        >>> few = QPSettings(max_iter=10, polish=False)  # too few ADMM iterations
        >>> result = solve_qp_batch(P, q, A, l, u, settings=few)
        >>> QPStatus(int(result.status[0])).name, result.n_iter.tolist()
        ('MAX_ITER', [10])
    """

    rho: float = 0.1
    sigma: float = 1e-6
    alpha: float = 1.6
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    eps_prim_inf: float = 1e-6
    eps_dual_inf: float = 1e-6
    max_iter: int = 4000
    check_every: int = 10
    adaptive_rho: bool = True
    adaptive_rho_tolerance: float = 5.0
    polish: bool = True

    def __post_init__(self) -> None:
        if not self.rho > 0 or not self.sigma > 0:
            raise ValueError("rho and sigma must be positive")
        if not 0 < self.alpha < 2:
            raise ValueError(f"alpha must be in (0, 2), got {self.alpha}")
        if self.eps_abs < 0 or self.eps_rel < 0 or self.eps_abs + self.eps_rel <= 0:
            raise ValueError("eps_abs and eps_rel must be >= 0, not both 0")
        if self.max_iter < 1 or self.check_every < 1:
            raise ValueError("max_iter and check_every must be >= 1")
        if not self.adaptive_rho_tolerance >= 1:
            raise ValueError("adaptive_rho_tolerance must be >= 1")


class QPResult(NamedTuple):
    """Solution of a batch of QPs.

    For a PRIMAL_INFEASIBLE instance ``y`` is the infeasibility certificate (the last
    ADMM step of ``y``, OSQP's ``prim_inf_cert``: ``A'y = 0``, ``u'y_+ + l'y_- < 0``);
    for a DUAL_INFEASIBLE one ``x`` is the certificate (the last step of ``x``: a
    direction of unbounded descent). Both are scaled to unit inf-norm. MAX_ITER
    instances hold the last iterate.

    Attributes:
        x: (B, n) primal solution, contiguous.
        y: (B, m) multipliers of ``l <= Ax <= u``: positive where the upper bound is
            active, negative where the lower one is (``Px + q + A'y = 0``). A
            transposed view of batch-last storage (``.contiguous()`` copies it).
        z: (B, m) ``Ax`` projected onto ``[l, u]``; a transposed view like ``y``.
        n_iter: (B,) int64 ADMM iterations (0 where BoxQP's fast path or active-set
            stage solved the instance).
        status: (B,) int64 :class:`QPStatus` values.
        polished: (B,) bool, True where the returned point is an exact solve on an
            active set (the polish after ADMM, or BoxQP's active-set stage).

    Examples:
        >>> import torch
        >>> from torchcf.qp import BoxQP
        >>> P = torch.eye(2, dtype=torch.float64).expand(3, 2, 2)  # (B, n, n)
        >>> q = torch.tensor([[-1.0, -1.0], [-3.0, 0.0], [1.0, -0.5]]).double()
        >>> l, u = torch.zeros(3, 2).double(), torch.ones(3, 2).double()  # 0 <= x <= 1
        >>> result = BoxQP(P).solve(q, l, u)
        >>> result.x.shape, result.y.shape, result.status.dtype  # (B, n), (B, m)
        (torch.Size([3, 2]), torch.Size([3, 2]), torch.int64)
        >>> result.y.tolist()  # > 0 at an active upper bound, < 0 at a lower one
        [[0.0, 0.0], [2.0, 0.0], [-1.0, 0.0]]
    """

    x: Tensor
    y: Tensor
    z: Tensor
    n_iter: Tensor
    status: Tensor
    polished: Tensor


class ProblemData(NamedTuple):
    """A working set of ``B`` QPs, batch-last. ``A is None`` means ``A = I``
    (``m = n``: a box QP)."""

    P: Tensor  # (n, n, B)
    q: Tensor  # (n, B)
    A: Tensor | None  # (m, n, B)
    l: Tensor  # (m, B), clamped to [-INFTY, INFTY]  # noqa: E741
    u: Tensor  # (m, B)

    def take(self, idx: Tensor) -> ProblemData:
        """Instances ``idx: (b,)`` of the working set."""
        return ProblemData(
            *(None if t is None else take_instances(t, idx) for t in self)
        )

    def Ax(self, x: Tensor) -> Tensor:
        """``A x``: (n, B) -> (m, B)."""
        return x if self.A is None else mv(self.A, x)

    def Aty(self, y: Tensor) -> Tensor:
        """``A' y``: (m, B) -> (n, B)."""
        return y if self.A is None else rmv(self.A, y)


def roundoff_floor(scale: Tensor, settings: QPSettings) -> Tensor:
    """(B,) the acceptance floor of a residual whose quantities are of size
    ``scale: (B,)``: ``min(100 eps (1 + scale), eps_abs + eps_rel' scale)`` with
    ``eps_rel' = eps_rel + ROUNDOFF_ULPS eps`` (``eps`` the machine epsilon), a
    hundred ulps of ``scale`` capped at the termination tolerance (see
    :func:`torchcf.qp.polish._kkt_accept`). Increasing in ``scale``."""
    ulp = torch.finfo(scale.dtype).eps
    eps_rel = settings.eps_rel + ROUNDOFF_ULPS * ulp
    return torch.minimum(100 * ulp * (1 + scale), settings.eps_abs + eps_rel * scale)


# --------------------------------------------------------------------------------------
# Between the batch-first API and the working layout.


def check_shape(name: str, t: Tensor | None, shape: tuple[int, ...]) -> None:
    """Raise ValueError unless ``t`` is None or of ``shape``."""
    if t is not None and tuple(t.shape) != shape:
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {shape}")


def batch_last_bounds(
    l: Tensor,  # noqa: E741
    u: Tensor,
    dtype: torch.dtype,
    keep_broadcast: bool = False,
) -> tuple[Tensor, Tensor, bool]:
    """Batch-last bounds ``(m, B)`` from batch-first ``l, u: (B, m)``, infinities
    replaced by +-INFTY, and whether any row is an equality (``l == u``).

    With ``keep_broadcast``, a bound given as the same value on every row (an
    expanded ``(B, 1)`` tensor, as the MPC passes its input limits) stays a
    broadcast ``(m, B)`` view of one row: every operation that reads it then reads
    ``B`` values, not ``m B``. Such views must only be read.

    Raises:
        ValueError: where a lower bound exceeds its upper bound.
    """

    def batch_last(t: Tensor) -> Tensor:
        t = t.T  # (m, B)
        if keep_broadcast and t.shape[0] > 1 and t.stride(0) == 0:
            return t[:1].to(dtype).clamp(-INFTY, INFTY).expand(t.shape)
        return t.to(dtype).clamp(-INFTY, INFTY).contiguous()

    lower, upper = batch_last(l), batch_last(u)
    # The gap on the stored rows only (one row of a broadcast bound).
    rows = 1 if lower.stride(0) == 0 and upper.stride(0) == 0 else lower.shape[0]
    gap = upper[:rows] - lower[:rows]
    least = float(gap.amin()) if gap.numel() else 1.0
    if least < 0:
        raise ValueError("every lower bound must be <= its upper bound")
    return lower, upper, least == 0


def batch_first_result(
    x: Tensor, y: Tensor, z: Tensor, n_iter: Tensor, status: Tensor, polished: Tensor
) -> QPResult:
    """Batch-first result from batch-last iterates ``x: (n, B)``, ``y, z: (m, B)``:
    ``x`` contiguous, ``y`` and ``z`` transposed views (a transposing copy costs
    about as much as a pass of the active-set stage, and most callers only read
    ``x``)."""
    return QPResult(swap_layout(x), y.T, z.T, n_iter, status, polished)
