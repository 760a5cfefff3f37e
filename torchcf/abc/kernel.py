"""The SMC proposal kernel: per pair a Gaussian mixture around its population.

:mod:`torchcf.abc.smc` proposes every refinement round from one
:class:`SMCKernel`, fitted to the previous round's population
(:meth:`SMCKernel.fit`); the kernel is a plain value, so it is built, drawn from
and weighed as a unit here, apart from the rounds that use it:

- **space**: the kernel steps in the logit of the prior box, ``z = logit((theta -
  low) / width)`` per parameter: every proposal lies in the box and the steps
  shrink near a bound (the module docstring of :mod:`torchcf.abc.smc` says why
  it matters);
- **fit**: per pair ``p``, the members' normalised weights ``w ~ r`` (``log r``
  is the population's last column) and ``Sigma_p = scale Cov_w(z) +
  (KERNEL_FLOOR x 4)^2 I`` (``scale = 2``: Beaumont et al.'s random-walk scale;
  4 / width is the logit's slope at the box's centre, so the floor is 1e-3 of
  the box's width there);
- **propose**: uniforms ``u`` (Q, 1 + K) pick a parent by the inverse CDF of the
  pair's weights (column 0) and a Gaussian step (columns 1..K, normal quantiles).
  A pair without a population draws from the prior instead;
- **density**: ``log r = log pi_z(z) - log q(z)``, ``q(z) = sum_i w_i N(z; z_i,
  Sigma_p)``, ``pi_z(z) = prod_k s(z_k) (1 - s(z_k))`` the uniform prior's
  density in the logit space (``s`` the logistic function): the importance
  weight of the prior with respect to the proposal (the ratio of two densities,
  the same in the box's coordinates).

Shapes: N pairs, ``pop`` members per pair, K parameters, Q proposals
(:mod:`torchcf.typing`). Everything is float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

#: Relative size (fraction of each parameter's prior width; in the logit space,
#: of the width at the box's centre, where dz = 4 dtheta / width) of the diagonal
#: added to the kernel covariance: a population collapsed onto one point keeps
#: moving.
KERNEL_FLOOR = 1e-3
#: Uniforms are kept this far from 0 and 1 before the normal quantile function.
UNIFORM_EDGE = 1e-12
#: Parameter vectors per block of the importance weights
#: (:meth:`SMCKernel.grid_log_prior_ratio`): a block's distances are
#: ``WEIGHT_ROWS x pop``.
WEIGHT_ROWS = 1 << 14


@dataclass(frozen=True)
class SMCKernel:
    """A round's proposal: per pair a Gaussian mixture around its population.

    Built by :meth:`fit`; ``theta``, ``chol`` and ``white`` are in the kernel's
    space, the logit of the box (module docstring).

    Attributes:
        bounds: (K, 2) the prior box ``[low, high]`` per parameter.
        theta: (N, pop, K) the population, in the logit space.
        log_w: (N, pop) normalised log weights (``-inf``: no member).
        cum_w: (N, pop) cumulative weights (the parent's inverse CDF).
        chol: (N, K, K) lower Cholesky factor ``L`` of ``Sigma_p``.
        whiten: (N, K, K) ``L^-1``: ``|L^-1 (a - b)|^2`` is the Mahalanobis
            distance of ``Sigma_p``.
        white: (N, pop, K) the population whitened, ``L^-1 theta_i``.
        log_norm: (N,) ``log`` of the Gaussian's normalising constant.
        empty: (N,) bool, pairs without a population (they draw from the prior).
    """

    bounds: Tensor
    theta: Tensor
    log_w: Tensor
    cum_w: Tensor
    chol: Tensor
    whiten: Tensor
    white: Tensor
    log_norm: Tensor
    empty: Tensor

    @classmethod
    def fit(
        cls, population: dict[str, Tensor], bounds: Tensor, scale: float = 2.0
    ) -> SMCKernel:
        """The proposal around ``population`` (module docstring).

        Args:
            population: ``theta`` (N, pop, K + 1), its last column ``log r``,
                and ``score`` (N, pop), ``+inf`` where a pair has no member.
            bounds: (K, 2) float64 prior box.
            scale: the covariance over the population's weighted one.
        """
        theta = cls._free(population["theta"][..., :-1], bounds)  # (N, pop, K)
        member = torch.isfinite(population["score"])  # (N, pop)
        log_r = torch.where(member, population["theta"][..., -1], -math.inf)
        log_w = log_r - torch.logsumexp(log_r, dim=1, keepdim=True)  # (N, pop)
        empty = ~member.any(dim=1)  # (N,)
        log_w = torch.where(empty[:, None], -math.inf, log_w)
        w = torch.exp(log_w)  # (N, pop), 0 for non-members
        mean = (w[..., None] * theta).sum(1, keepdim=True)  # (N, 1, K)
        centred = torch.where(member[..., None], theta - mean, 0.0)
        cov = torch.einsum("np,npk,npl->nkl", w, centred, centred)  # (N, K, K)
        width = cls._centre_width(bounds)  # (K,)
        sigma = scale * cov + torch.diag((KERNEL_FLOOR * width) ** 2)
        chol = torch.linalg.cholesky(sigma)  # (N, K, K)
        k = theta.shape[-1]
        log_det = 2.0 * torch.log(torch.diagonal(chol, dim1=1, dim2=2)).sum(1)
        log_norm = -0.5 * (k * math.log(2 * math.pi) + log_det)  # (N,)
        eye = torch.eye(k, dtype=chol.dtype).expand_as(chol)
        whiten = torch.linalg.solve_triangular(chol, eye, upper=False)  # (N, K, K)
        white = torch.einsum("nkl,npl->npk", whiten, theta)  # (N, pop, K)
        cum_w = torch.cumsum(w, dim=1)
        return cls(bounds, theta, log_w, cum_w, chol, whiten, white, log_norm, empty)

    @property
    def covariance(self) -> Tensor:
        """(N, K, K) ``Sigma_p`` per pair, in the kernel's space."""
        return self.chol @ self.chol.transpose(1, 2)

    def propose(self, u: Tensor, pair: Tensor) -> Tensor:
        """Proposals from uniforms ``u`` (Q, 1 + K) on pairs ``pair`` (Q,).

        Column 0 picks the parent (inverse CDF of the pair's weights), columns
        1..K the Gaussian step (normal quantiles). A pair without a population
        draws from the prior instead (columns 1..K as a prior draw).

        Returns:
            ``theta`` (Q, K) in the box's coordinates, every row inside the
            box. Its importance weight is :meth:`log_prior_ratio`'s, taken once
            a round ends.
        """
        rows = u.shape[0]
        # Padded to whole vector lanes: CPU kernels of a transcendental function
        # (the logit space's sigmoid) compute a tensor's last few elements with
        # a scalar routine whose bits can differ from the vector one (seen on an
        # AMD EPYC); a proposal must not depend on where its chunk ends.
        fill = -rows % LANES
        if fill:
            u = torch.cat((u, u[-1:].expand(fill, -1)))
            pair = torch.cat((pair, pair[-1:].expand(fill)))
        low, high = self.bounds[:, 0], self.bounds[:, 1]
        cum = self.cum_w[pair]  # (Q, pop)
        target = u[:, :1] * cum[:, -1:]
        parent = torch.searchsorted(cum, target).clamp_(max=cum.shape[1] - 1)[:, 0]
        z = torch.special.ndtri(u[:, 1:].clamp(UNIFORM_EDGE, 1 - UNIFORM_EDGE))
        chol = self.chol[pair]  # (Q, K, K)
        # L z as K elementwise multiply-adds, not a batched product, whose
        # kernel (and bits) can depend on Q
        step = chol[:, :, 0] * z[:, :1]  # (Q, K)
        for column in range(1, z.shape[1]):
            step = step + chol[:, :, column] * z[:, column : column + 1]
        theta = self._boxed(self.theta[pair, parent] + step, self.bounds)
        prior_draw = low + (high - low) * u[:, 1:]
        from_prior = self.empty[pair]
        theta = torch.where(from_prior[:, None], prior_draw, theta)
        return theta[:rows]

    def log_prior_ratio(self, theta: Tensor, pair: Tensor) -> Tensor:
        """``log pi(theta) - log q(theta)`` (Q,) of proposals ``theta`` (Q, K) on
        pairs ``pair`` (Q,): the importance weight of the uniform prior with
        respect to the proposal (0 where the pair drew from the prior). Both
        densities are taken in the logit space; their ratio is the same in the
        box's coordinates.

        The proposals are laid out per pair (:meth:`grid_log_prior_ratio`)."""
        n_pairs = self.theta.shape[0]
        order = torch.sort(pair, stable=True).indices
        counts = torch.bincount(pair, minlength=n_pairs)
        slot = torch.empty_like(pair)
        slot[order] = (
            torch.arange(pair.numel()) - (torch.cumsum(counts, 0) - counts)[pair[order]]
        )
        grid = theta.new_zeros(n_pairs, max(int(counts.max()), 1), theta.shape[1])
        grid[pair, slot] = theta  # (N, C, K), C the most proposals of a pair
        return self.grid_log_prior_ratio(grid)[pair, slot]

    def grid_log_prior_ratio(self, theta: Tensor) -> Tensor:
        """(N, C) ``log r`` of ``theta`` (N, C, K), ``C`` parameter vectors per
        pair (a buffer's, at the end of a round), as :meth:`log_prior_ratio`.

        Per pair the Mahalanobis distances to its population are one small
        matrix product, ``(C, K) x (K, pop)``, batched over pairs; pairs are taken
        in blocks of at most :data:`WEIGHT_ROWS` rows (memory ``WEIGHT_ROWS x
        pop``), fixed, so the result does not depend on how a round was
        chunked."""
        n_pairs, width = theta.shape[:2]
        out = theta.new_empty(n_pairs, width)
        step = max(1, WEIGHT_ROWS // max(width, 1))
        for first in range(0, n_pairs, step):
            block = slice(first, first + step)
            free = self._free(theta[block], self.bounds)  # (B, C, K)
            log_prior = self._log_prior(free.reshape(-1, free.shape[-1]), self.bounds)
            z = torch.einsum("bkl,bcl->bck", self.whiten[block], free)  # (B, C, K)
            members = self.white[block]  # (B, pop, K)
            # |z - z_i|^2 expanded: one batched product per pair, not C x pop.
            distance = (
                (z**2).sum(2, keepdim=True)
                + (members**2).sum(2)[:, None, :]
                - 2.0 * torch.bmm(z, members.transpose(1, 2))
            ).clamp(min=0.0)  # (B, C, pop)
            log_phi = self.log_norm[block, None, None] - 0.5 * distance
            log_q = torch.logsumexp(self.log_w[block, None, :] + log_phi, dim=2)
            ratio = log_prior.reshape(log_q.shape) - log_q  # (B, C)
            out[block] = torch.where(self.empty[block, None], 0.0, ratio)
        return out

    # ------------------------------------------- the kernel's space: the logit
    @staticmethod
    def _free(theta: Tensor, bounds: Tensor) -> Tensor:
        """Parameters ``theta`` (..., K) in the kernel's space: the logit of their
        place in the box (a bound itself is read 1e-12 of the width inside)."""
        low, width = bounds[:, 0], bounds[:, 1] - bounds[:, 0]
        unit = ((theta - low) / width).clamp(UNIFORM_EDGE, 1 - UNIFORM_EDGE)
        return torch.logit(unit)

    @staticmethod
    def _boxed(z: Tensor, bounds: Tensor) -> Tensor:
        """The inverse of :meth:`_free`: parameters (..., K) in the box."""
        low, width = bounds[:, 0], bounds[:, 1] - bounds[:, 0]
        return low + width * torch.sigmoid(z)

    @staticmethod
    def _log_prior(z: Tensor, bounds: Tensor) -> Tensor:
        """(Q,) log density of the uniform prior at ``z`` (Q, K) in the kernel's
        space, ``sum_k log s(z_k) (1 - s(z_k))``."""
        f = torch.nn.functional.softplus
        return -(f(z) + f(-z)).sum(1)

    @staticmethod
    def _centre_width(bounds: Tensor) -> Tensor:
        """(K,) the box's width in the kernel's space, read at its centre: 4
        (the logit's slope there is 4 / width), the scale of the floor."""
        return torch.full_like(bounds[:, 0], 4.0)


#: Rows a proposal batch is padded to a multiple of (whole vector lanes of the
#: widest CPU vectors, 64 bytes, in float32 twice over: no scalar tail).
LANES = 32


__all__ = ["KERNEL_FLOOR", "UNIFORM_EDGE", "WEIGHT_ROWS", "SMCKernel"]
