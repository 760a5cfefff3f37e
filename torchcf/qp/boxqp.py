"""The public solver for box QPs (``A = I``): :class:`BoxQP`.

It factorises once per ``P`` and reuses the factors for every ``(q, l, u)``. A
solve runs stages, each on what the previous one left:

1. the leading-block stage (:mod:`torchcf.qp.active_set`): exact solves on guessed
   active sets, from the caller's guess (the MPC passes its last plan) or from "no
   bound active", whose solve is the unconstrained minimiser, corrected by
   primal-dual active-set steps, and kept only where the KKT conditions hold;
2. general exact solves (:func:`torchcf.qp.polish.active_set_solves`) for the
   guesses that stopped being a leading block, the instances out of passes and a
   singular ``P``;
3. ADMM and its polish (:func:`torchcf.qp.polish.admm_then_polish`) on the rest.

On the MPC QPs the first stage finishes nearly every instance, so ADMM is the
fallback.

Shapes: ``B`` instances factorised, ``b`` solved in a call (all of them, or
``index``), ``r`` left to a later stage; ``n`` variables (and rows). This is the
top layer: it may import every other module, none imports it but the package's
``__init__``.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
from torch import Tensor

from .active_set import LeadingOutcome, Unfinished, leading_active_set
from .admm import (
    Iterate,
    dual_feasible_start,
    kkt_inverse,
    osqp_starting_iterate,
    rho_vector,
    uniform_rows,
)
from .kernels import (
    cholesky,
    cholesky_solve,
    is_small_subset,
    mv,
    put_instances_,
    spd_inverse,
    swap_layout,
    take_instances,
)
from .leading import leading_data, leading_factor
from .polish import AcceptedSolutions, active_set_solves, admm_then_polish
from .problem import (
    ProblemData,
    QPResult,
    QPSettings,
    QPStatus,
    batch_first_result,
    batch_last_bounds,
    check_shape,
)

#: Exact active-set solves per instance in the leading-block and general stages.
_ACTIVE_SET_PASSES = 5


class _BoxCall(NamedTuple):
    """One call of :meth:`BoxQP.solve` in the working layout, ``b`` instances."""

    q: Tensor  # (n, b) batch-last, in P's dtype
    lower: Tensor  # (n, b) clamped to +-INFTY; possibly a broadcast view: read only
    upper: Tensor  # (n, b)
    equality: bool  # some row has l == u
    definite: Tensor  # (b,) bool, P positive definite
    index: Tensor | None  # (b,) int64 the instances of the factorised batch; None: all
    given_bounds: tuple[Tensor, Tensor]  # (b, n) each: l and u as the caller gave them


class _Solutions(NamedTuple):
    """Solutions of ``b`` instances, batch-last: :class:`QPResult`'s fields."""

    x: Tensor  # (n, b)
    y: Tensor  # (n, b)
    z: Tensor  # (n, b)
    n_iter: Tensor  # (b,) int64
    status: Tensor  # (b,) int64
    polished: Tensor  # (b,) bool

    def result(self) -> QPResult:
        """The batch-first :class:`QPResult`."""
        return batch_first_result(*self)

    def put_(self, rows: Tensor, sub: _Solutions) -> None:
        """Overwrite the instances ``rows: (r,)`` with ``sub`` (``r`` instances)."""
        put_instances_(self.x, rows, sub.x)
        put_instances_(self.y, rows, sub.y)
        put_instances_(self.z, rows, sub.z)
        self.n_iter[rows] = sub.n_iter
        self.status[rows] = sub.status
        self.polished[rows] = sub.polished


def _first_guess(
    point: Tensor | None, call: _BoxCall, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """The leading-block stage's first guess of the active bounds: lower, upper,
    (n, b) bool each.

    Without a ``point``, no bound is active, so the first pass is the
    unconstrained minimiser ``-P^{-1} q``. With a ``point: (b, n)``, the bounds it
    sits at or beyond (``<= l``, ``>= u``; lower wins where ``l == u``).
    """
    n, batch = call.q.shape
    if point is None:
        at_lower = torch.zeros(n, batch, dtype=torch.bool, device=call.q.device)
        return at_lower, torch.zeros_like(at_lower)
    # Compared batch-first, with l and u as given (clamping the infinities changes
    # no comparison), and the bool masks transposed: cheaper than transposing the
    # point.
    l, u = call.given_bounds  # noqa: E741
    point = point.to(dtype)
    below, above = point <= l.to(dtype), point >= u.to(dtype)  # (b, n)
    at_lower = swap_layout(below)
    return at_lower, swap_layout(above).logical_and_(~at_lower)


class BoxQP:
    """``min 1/2 x'Px + q'x s.t. l <= x <= u`` (A = I) for many instances.

    The instances share nothing but their shape. The factorisation depends only on
    ``P`` (and rho), so it is built once here and reused by every :meth:`solve`; this
    is what the MPC uses: ``P`` depends on the particle only, ``q`` changes every
    time step. Cached per instance: ``P^{-1}`` (for the exact fast path), the
    leading-block factors of ``P`` (:func:`~torchcf.qp.leading.leading_factor`)
    and ``(P + (sigma + rho) I)^{-1}`` (the ADMM x-update).

    Args:
        P: (B, n, n) symmetric positive semidefinite (definite for the fast path).
        settings: solver settings; default :class:`QPSettings()`.

    Attributes:
        P: (B, n, n) the Hessians as given.
        settings: the solver settings.

    Examples:
        >>> import torch
        >>> from torchcf.qp import BoxQP
        >>> P = torch.eye(2, dtype=torch.float64).expand(3, 2, 2)  # (B, n, n)
        >>> q = torch.tensor([[-1.0, -1.0], [-3.0, 0.0], [1.0, -0.5]]).double()
        >>> l, u = torch.zeros(3, 2).double(), torch.ones(3, 2).double()  # 0 <= x <= 1
        >>> result = BoxQP(P).solve(q, l, u)
        >>> result.x.tolist()  # -q clipped to the box, as P = I
        [[1.0, 1.0], [1.0, 0.0], [0.0, 0.5]]
        >>> result.status.tolist(), result.n_iter.tolist()  # solved exactly, no ADMM
        ([0, 0, 0], [0, 0, 0])
    """

    def __init__(self, P: Tensor, settings: QPSettings | None = None) -> None:
        if P.ndim != 3 or P.shape[1] != P.shape[2]:
            raise ValueError(f"P must be (B, n, n), got {tuple(P.shape)}")
        self.settings = settings or QPSettings()
        self.P = P  # (B, n, n) as given
        self._P = P.permute(1, 2, 0).contiguous()  # (n, n, B)
        self._p_inverse, self._definite = spd_inverse(self._P)
        self._leading, upper_ok = leading_factor(self._P)
        self._definite &= upper_ok
        kkt = self._P.clone()
        torch.diagonal(kkt, 0, 0, 1).add_(self.settings.sigma + self.settings.rho)
        self._kkt, _ = spd_inverse(kkt)

    @property
    def batch_size(self) -> int:
        return self._P.shape[-1]

    def take(self, index: Tensor) -> BoxQP:
        """The solver of the instances ``index`` (int64 (b,)) alone, their
        cached factors taken, not computed again."""
        kept = object.__new__(BoxQP)
        kept.settings = self.settings
        kept.P = self.P.index_select(0, index)
        kept._P = self._P.index_select(-1, index)
        kept._p_inverse = self._p_inverse.index_select(-1, index)
        kept._definite = self._definite.index_select(0, index)
        kept._leading = self._leading.take(index)
        kept._kkt = self._kkt.index_select(-1, index)
        return kept

    @property
    def n(self) -> int:
        return self._P.shape[0]

    def unconstrained(self, q: Tensor, *, index: Tensor | None = None) -> Tensor:
        """Unconstrained minimiser ``-P^{-1} q`` from the cached inverse.

        Args:
            q: (B, n), or (len(index), n) with ``index``.
            index: optional (b,) int64 rows of the batch that ``q`` belongs to.

        Returns:
            (B, n) (NaN-free garbage where ``P`` is singular).
        """
        inverse = self._p_inverse
        if index is not None:
            inverse = take_instances(inverse, index)
        return -mv(inverse, q.T.to(inverse.dtype)).T

    def solve(
        self,
        q: Tensor,
        l: Tensor,  # noqa: E741
        u: Tensor,
        *,
        x0: Tensor | None = None,
        y0: Tensor | None = None,
        index: Tensor | None = None,
        method: Literal["auto", "admm"] = "auto",
        active_guess: Tensor | None = None,
    ) -> QPResult:
        """Solve the instances ``index`` (default: all) for the given ``q, l, u``.

        ``method="auto"`` runs three stages, each on what the previous one left:

        1. exact fast path: where ``-P^{-1} q`` lies in ``[l, u]`` it is the solution
           (SOLVED, ``n_iter = 0``, ``y = 0``, not ``polished``);
        2. active set: the bounds that ``-P^{-1} q`` violates, or with a guess (see
           below) the bounds the guess sits on, are fixed and the reduced system
           solved exactly, with up to ``_ACTIVE_SET_PASSES - 1`` primal-dual
           active-set corrections (Hintermueller, Ito & Kunisch 2002); a solution is
           kept only where it satisfies the KKT conditions to round-off (SOLVED,
           ``n_iter = 0``, ``polished`` unless no bound is active). On the MPC QPs
           this finishes almost every instance;
        3. ADMM and polish (:func:`solve_qp_batch`) on the rest, started from
           ``x0, y0``; without ``y0``, from ``x0`` (or ``-P^{-1} q``) clipped to
           the box, with the multipliers ``-(Px + q)`` on its rows at a bound.

        With a guess, stage 1 is not run on its own: stage 2 starts from the guess,
        and an instance whose guess has no active bound gets the unconstrained
        minimiser in its first pass, as stage 1 would give it.

        ``method="admm"`` runs stage 3 alone, from ``x0, y0`` or zeros as OSQP does:
        the same result as ``solve_qp_batch`` with ``A = I``.

        Args:
            q: (b, n) with ``b = B`` or ``len(index)``.
            l: (b, n) lower bounds, ``-inf`` allowed.
            u: (b, n) upper bounds, ``+inf`` allowed.
            x0: (b, n) optional warm start of ADMM's primal iterate (the MPC
                passes its previous plan, shifted by one step, as ``x0`` alone);
                also stage 2's guess unless ``active_guess`` is given.
            y0: (b, n) optional warm start of ADMM's dual iterate.
            index: optional (b,) int64 rows of the batch to solve; the cached factors
                are gathered.
            method: "auto" or "admm", see above.
            active_guess: optional (b, n) point whose entries at or beyond a bound
                (``<= l``, ``>= u``) are stage 2's first guess of the active set.
                The MPC passes its previous plan unshifted: saturated inputs tend
                to stay saturated (on the states of ``tools/bench_qp.py`` its
                active set is the new one about three times as often as the
                shifted plan's). Only a guess: any point gives the same solution.

        Returns:
            :class:`QPResult` with ``b`` rows.
        """
        if method not in ("auto", "admm"):
            raise ValueError(f"method must be 'auto' or 'admm', got {method!r}")
        call = self._prepare(q, l, u, index, x0=x0, y0=y0, active_guess=active_guess)
        if method == "admm":  # stage 3 alone: its result is the output
            everything = torch.arange(call.q.shape[-1], device=q.device)
            stage = self._admm_stage(call, everything, x0, y0, osqp_start=True)
            return stage.result()
        point = x0 if active_guess is None else active_guess
        solutions, rest = self._exact_stages(call, point)
        if rest.numel():
            # Without y0 ADMM starts from a dual feasible point, not OSQP's start.
            admm = self._admm_stage(call, rest, x0, y0, osqp_start=y0 is not None)
            solutions.put_(rest, admm)
        return solutions.result()

    # ----------------------------------------------------------------------------------
    # The stages of solve().

    def _prepare(
        self,
        q: Tensor,
        l: Tensor,  # noqa: E741
        u: Tensor,
        index: Tensor | None,
        **optional: Tensor | None,
    ) -> _BoxCall:
        """Check the shapes of ``q, l, u`` and of the ``optional`` (b, n) inputs;
        the call in the working layout."""
        n = self.n
        batch = self.batch_size if index is None else index.shape[0]
        for name, t in (("q", q), ("l", l), ("u", u), *optional.items()):
            check_shape(name, t, (batch, n))
        definite = self._definite if index is None else self._definite[index]
        dtype = self._P.dtype
        lower, upper, equality = batch_last_bounds(l, u, dtype, keep_broadcast=True)
        q_t = swap_layout(q.to(dtype))
        return _BoxCall(q_t, lower, upper, equality, definite, index, (l, u))

    def _exact_stages(
        self, call: _BoxCall, point: Tensor | None
    ) -> tuple[_Solutions, Tensor]:
        """Stages 1 and 2: the leading-block stage from the guess ``point: (b, n)``
        (None: a cold start), then general exact solves on what it hands on.

        Returns:
            the solutions (exact where solved; the others are overwritten by the
            ADMM stage), and rest: (r,) int64 the instances neither stage solved.
        """
        at_lower, at_upper = _first_guess(point, call, self._P.dtype)
        # A cold start's first pass is the unconstrained minimiser: one pass more.
        passes = _ACTIVE_SET_PASSES + 1 if point is None else _ACTIVE_SET_PASSES
        leading, unfinished = self._leading_stage(call, at_lower, at_upper, passes)
        solutions = self._leading_solutions(call, leading)
        # The rest: guesses that stopped being a leading block, instances out of
        # passes, and singular P. Exact solves that refactorise.
        other = (~call.definite).nonzero().squeeze(1)
        rest = torch.cat((unfinished.rows, other))
        if not rest.numel():
            return solutions, rest
        at_lower = torch.cat((unfinished.lower, at_lower[:, other]), -1)
        at_upper = torch.cat((unfinished.upper, at_upper[:, other]), -1)
        accepted = self._general_stage(call, Unfinished(rest, at_lower, at_upper))
        done = rest[accepted.rows]
        put_instances_(solutions.x, done, accepted.x)
        put_instances_(solutions.y, done, accepted.y)
        put_instances_(solutions.z, done, accepted.z)
        solutions.polished[done] = True
        left = torch.ones(rest.numel(), dtype=torch.bool, device=rest.device)
        left[accepted.rows] = False
        return solutions, rest[left.nonzero().squeeze(1)]

    def _leading_stage(
        self, call: _BoxCall, at_lower: Tensor, at_upper: Tensor, passes: int
    ) -> tuple[LeadingOutcome, Unfinished]:
        """Stage 1 (:func:`~torchcf.qp.active_set.leading_active_set`) on every
        instance with a definite ``P``, from the guess ``at_lower, at_upper``."""
        data = leading_data(
            self._leading,
            call.q,
            call.lower,
            call.upper,
            self.settings,
            call.index,
            call.equality,
            given_bounds=call.given_bounds,
        )
        return leading_active_set(
            data, at_lower, at_upper, call.definite, self.settings, passes
        )

    @staticmethod
    def _leading_solutions(call: _BoxCall, leading: LeadingOutcome) -> _Solutions:
        """The call's solutions after stage 1: SOLVED, no ADMM iterations,
        ``polished`` where a bound is active (garbage where not ``solved``)."""
        x, y = leading.x, leading.y
        z = torch.clamp(x, call.lower, call.upper)
        n_iter = torch.zeros(x.shape[-1], dtype=torch.int64, device=x.device)
        status = torch.full_like(n_iter, int(QPStatus.SOLVED))
        return _Solutions(x, y, z, n_iter, status, leading.constrained)

    def _general_stage(
        self, call: _BoxCall, unfinished: Unfinished
    ) -> AcceptedSolutions:
        """Stage 2: exact solves, refactorising, on the ``unfinished`` instances
        from their guesses, with active-set corrections; returns the accepted ones
        (``rows`` index ``unfinished.rows``)."""
        rest = unfinished.rows
        _, data = self._working_set(rest, call)
        return active_set_solves(
            data,
            unfinished.lower,
            unfinished.upper,
            self.settings,
            _ACTIVE_SET_PASSES,
            definite=call.definite[rest],
        )

    def _admm_stage(
        self,
        call: _BoxCall,
        rest: Tensor,
        x0: Tensor | None,
        y0: Tensor | None,
        osqp_start: bool,
    ) -> _Solutions:
        """Stage 3: ADMM and polish on the instances ``rest: (r,)`` of the call.

        Started as OSQP does (``x0, y0`` or zeros) with ``osqp_start``, else from a
        dual feasible point (:func:`~torchcf.qp.admm.dual_feasible_start`).
        """
        cached, data = self._working_set(rest, call)
        rho = call.q.new_full((rest.numel(),), self.settings.rho)
        kkt = self._admm_kkt_inverse(cached, data, rho)
        definite = call.definite[rest]
        if osqp_start:
            x0_rest = None if x0 is None else x0[rest]
            y0_rest = None if y0 is None else y0[rest]
            start = osqp_starting_iterate(data, x0_rest, y0_rest, self.n, self.n)
        else:
            start = self._admm_warm_start(cached, data, definite, rest, x0)
        outcome, polished = admm_then_polish(
            data, start, rho, kkt, self.settings, definite=definite
        )
        return _Solutions(
            outcome.x, outcome.y, outcome.z, outcome.n_iter, outcome.status, polished
        )

    # ----------------------------------------------------------------------------------
    # The working sets of the stages, and ADMM's start and KKT inverse.

    def _working_set(self, rest: Tensor, call: _BoxCall) -> tuple[Tensor, ProblemData]:
        """The problems ``rest: (r,)`` (positions in the call): their instances of
        the cached factors, ``cached: (r,)``, and their batch-last data."""
        cached = rest if call.index is None else call.index[rest]
        if is_small_subset(cached, self.batch_size):  # from the batch-first P
            P = self.P.index_select(0, cached).to(self._P.dtype).permute(1, 2, 0)
            P = P.contiguous()
        else:
            P = take_instances(self._P, cached)
        data = ProblemData(
            P, call.q[:, rest], None, call.lower[:, rest], call.upper[:, rest]
        )
        return cached, data

    def _admm_kkt_inverse(
        self, cached: Tensor, data: ProblemData, rho: Tensor
    ) -> Tensor:
        """(n, n, r) ADMM's KKT inverse for the working set: factorised anew for a
        few instances (cheaper than a gather), else gathered from the cache and
        refactorised only where equality or free rows change rho_vec."""
        sigma = self.settings.sigma
        if is_small_subset(cached, self.batch_size):
            return kkt_inverse(data, rho_vector(rho, data), sigma)
        kkt = take_instances(self._kkt, cached)
        special = (~uniform_rows(data)).nonzero().squeeze(1)
        if special.numel():
            sub = data.take(special)
            sub_rho = rho_vector(rho[special], sub)
            put_instances_(kkt, special, kkt_inverse(sub, sub_rho, sigma))
        return kkt

    def _admm_warm_start(
        self,
        cached: Tensor,
        data: ProblemData,
        definite: Tensor,
        rest: Tensor,
        x0: Tensor | None,
    ) -> Iterate:
        """ADMM's start from ``x0: (b, n)``, else from ``-P^{-1} q``, clipped to the
        box with dual feasible multipliers (``definite: (r,)`` marks where
        ``-P^{-1} q`` is usable)."""
        if x0 is not None:
            usable = torch.ones_like(definite)
            point = swap_layout(x0[rest].to(self._P.dtype))
            return dual_feasible_start(data, point, usable)
        if is_small_subset(cached, self.batch_size):
            L, _ = cholesky(data.P, strict=False)
            point = cholesky_solve(L, -data.q)  # -P^{-1} q
        else:
            point = -mv(take_instances(self._p_inverse, cached), data.q)
        return dual_feasible_start(data, point, definite)
