"""How each policy's exploration covariance is set: from the DP posterior (the paper), or by
the success rule of the (1+1)-CMA-ES (the default).

Both classes have one interface (as pycma's step-size adaptations do, the "off" case being a
class whose update does nothing): ``observe`` sees every told batch before its samples
are archived, ``starting_covariance`` gives a new policy its exploration from its DP
component's posterior covariance, and ``keeps_covariance`` says whether a policy's
exploration lives on from clustering to clustering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE
from dipole_torch.policy_set import PolicyField

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch
    from dipole_torch.tell_batch import TellBatch

__all__ = [
    "IGEL_TARGET_SUCCESS",
    "MAX_CONDITION",
    "MIN_RELATIVE_STD",
    "PosteriorExploration",
    "SuccessRule",
    "SuccessRuleParameters",
    "bounded_condition",
    "make_exploration",
    "start_spread",
]


class PosteriorExploration:
    """The paper's: a policy explores with the θ-block of its DP component's posterior
    covariance, set anew at every clustering ("the exploration noise of each component is
    fit to the sampled points at every DP run")."""

    keeps_covariance = False

    def register(self, search: PolicySearch) -> None:
        """Nothing to keep per policy."""

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """Nothing: the covariance changes only at clusterings."""

    def starting_covariance(self, search: PolicySearch, covariances: Tensor) -> Tensor:
        """``[..., D, D]`` the posterior covariances themselves."""
        return covariances.clone()


# Igel et al.'s target success rate p_t of the (1+1)-CMA-ES.
IGEL_TARGET_SUCCESS = 2.0 / 11.0


@dataclass(frozen=True)
class SuccessRuleParameters:
    """The constants of the success rule for D parameters (Igel, Suttorp & Hansen 2006,
    "A computational efficient covariance matrix update and a (1+1)-CMA for evolution
    strategies"), one a line as in pycma's ``CMAESParameters``.

    Args:
        dim: D.
        target_success: p_t, the success rate at which the covariance keeps its scale (the
            1/5th rule's (1+1) refinement: 2/11 in Igel et al., the default here; ``Dipole``
            gives its ``success_target`` option).
    """

    dim: int
    target_success: float = IGEL_TARGET_SUCCESS

    @property
    def smoothing(self) -> float:
        """c_p: the weight of the latest sample in the running success rate p̄: 1/12, Igel
        et al.'s p_t/(2 + p_t) at their p_t = 2/11, kept at any ``target_success`` (the
        formula at 0.25, 1/9, was measured: docs, Niching)."""
        return 1.0 / 12.0

    @property
    def damping(self) -> float:
        """d: the damping of the scale change, 1 + D/2."""
        return 1.0 + self.dim / 2.0

    @property
    def path_rate(self) -> float:
        """c_c: the learning rate of the evolution path, 2/(D + 2)."""
        return 2.0 / (self.dim + 2.0)

    @property
    def covariance_rate(self) -> float:
        """c_cov: the weight of the rank-one update along the path, 2/(D² + 6)."""
        return 2.0 / (self.dim * self.dim + 6.0)


class SuccessRule:
    """Exploration that follows each policy's own samples, as in the (1+1)-CMA-ES.

    A sample succeeds when it beats its policy's best kept one. A success moves the policy's
    evolution path p towards the step x − μ, (1 − c_c) p + √(c_c (2 − c_c)) (x − μ), and adds
    the rank-one term: Σ ← (1 − c_cov) Σ + c_cov p pᵀ. After every sample the running
    success rate p̄ ← (1 − c_p) p̄ + c_p·[success] scales the covariance by
    exp((p̄ − p_t) / (d (1 − p_t)))², never beyond Σ_start (a policy that keeps failing while
    it grows would otherwise turn into random search) nor below ``MIN_RELATIVE_STD`` of it
    (a policy that never retires would shrink it to zero; not in Igel et al.). Exploration
    then shrinks geometrically near an optimum and grows on a slope, and the covariance
    learns the optimum's shape. The covariance is kept from clustering to clustering. Its
    condition number is held near ``MAX_CONDITION`` (``bounded_condition``; not in Igel et
    al.).

    Σ here is Igel et al.'s σ²C in one matrix, so p is their σ·p_c: it is scaled with the
    covariance's scale at every sample. (Left in absolute units, a path from steps of
    1e-9 added its rank-one term to a covariance shrunk to 1e-11 at the next success, and
    the exploration stalled there: a policy refined over many decades never got closer.)

    Per-policy fields: ``success`` (p̄, starting at p_t) and ``paths`` (p, starting at 0).

    The target p_t is Igel et al.'s 2/11 here; ``Dipole`` uses its ``success_target`` option,
    0.25 by default (not in Igel et al.). A (1+1)-ES moves its parent to every success; a
    DIPOLE policy's mean is eq. 7's weighted average of its M best samples, and a success is
    judged against the best of them. With the higher target the exploration shrinks sooner
    around a mean that climbs more slowly than a (1+1) parent: the policies converge in fewer
    trials, and more optima were found on the multi-optima landscapes and the CEC 2013
    functions (docs: Multi-optima, History).

    Args:
        dim: D.
        target_success: p_t, in (0, 1).
    """

    keeps_covariance = True

    def __init__(self, dim: int, target_success: float = IGEL_TARGET_SUCCESS):
        self.parameters = SuccessRuleParameters(dim, float(target_success))

    def register(self, search: PolicySearch) -> None:
        search.policy_set.register("success", PolicyField(default=self.parameters.target_success))
        search.policy_set.register("paths", PolicyField(shape=(search.dim,)))

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """The success rule on the batch's policy samples (before they are archived, so a
        success is judged against the policy's kept samples)."""
        if not search.started or batch.policy_rows == 0:
            return
        policies = search.policy_set
        n = batch.policy_rows
        # Usually every policy drew one sample, in order: the policies' rows as they stand,
        # written back whole; otherwise the sampled rows, gathered and scattered.
        every = batch.every_policy(len(policies))
        policy = batch.owner[:n]

        def rows(tensor: Tensor) -> Tensor:
            return tensor if every else tensor[policy]

        succeeded = batch.rewards[:n] > rows(search.policy_best_rewards)
        constants = self.parameters
        c_c, c_cov = constants.path_rate, constants.covariance_rate
        paths, covs = rows(policies.paths), rows(policies.covariances)
        if True in succeeded.tolist():  # (most samples fail: paths and Σ then stand)
            step = batch.theta[:n] - rows(policies.means)
            paths = torch.where(
                succeeded[:, None], (1 - c_c) * paths + math.sqrt(c_c * (2 - c_c)) * step, paths
            )
            rank_one = (1 - c_cov) * covs + c_cov * paths[:, :, None] * paths[:, None, :]
            covs = torch.where(succeeded[:, None, None], bounded_condition(search, rank_one), covs)
        c = constants.smoothing
        success = (1 - c) * rows(policies.success) + c * succeeded.to(DTYPE)
        p_t = constants.target_success
        factor = torch.exp((success - p_t) / (constants.damping * (1 - p_t)))
        # Never beyond Σ_start, and never below MIN_RELATIVE_STD of it: without retirement
        # (retire_std=0) a converged policy fails on and on, and its covariance shrank
        # geometrically until it underflowed to zero and the next ask failed.
        relative = search.relative_std(covs).clamp_min(1e-300)
        factor = torch.clamp(factor, MIN_RELATIVE_STD / relative, 1.0 / relative)
        paths = paths * factor[:, None]  # in the scale's units, as Σ
        covs = covs * factor[:, None, None] ** 2
        if every:
            policies.paths, policies.success, policies.covariances = paths, success, covs
        else:
            policies.paths = policies.paths.index_put((policy,), paths)
            policies.success = policies.success.index_put((policy,), success)
            policies.covariances = policies.covariances.index_put((policy,), covs)

    def starting_covariance(self, search: PolicySearch, covariances: Tensor) -> Tensor:
        """``[..., D, D]`` Σ_start's shape at the spread of the posterior ``covariances``:
        tr(Σ_start⁻¹ Σ_c)/D · Σ_start, at most Σ_start.

        A component of a few points in D dimensions has a badly conditioned posterior
        covariance; the rank-one update needs hundreds of samples to unlearn it, which
        slowed the policies' convergence. Never below ``MIN_RELATIVE_STD``² of Σ_start, the
        success rule's own floor: a component of samples equal to rounding has a spread that
        underflows to zero, and a policy started at zero never explores."""
        spread = start_spread(search, covariances).clamp(MIN_RELATIVE_STD**2, 1.0)
        return spread[..., None, None] * search.sigma_start


def start_spread(search: PolicySearch, covariances: Tensor) -> Tensor:
    """``[...]`` the spread of ``covariances [..., D, D]`` on Σ_start's scale,
    tr(Σ_start⁻¹ Σ)/D (1 for Σ_start itself)."""
    whitened = torch.linalg.solve(search.sigma_start, covariances)
    return whitened.diagonal(dim1=-2, dim2=-1).mean(-1)


# The smallest exploration std the success rule keeps, relative to Σ_start's (its largest
# ratio over the axes): a few float64 ulps of θ at Σ_start's scale, below which samples
# round to the mean; far below the finest threshold a wake refines to (1e-12).
MIN_RELATIVE_STD = 1e-15

# The largest condition number a policy's exploration covariance may reach, in Σ_start's
# per-axis units (pycma stops a run at 1e14; float64 rounding makes a covariance singular
# near 1e16).
MAX_CONDITION = 1e12


def bounded_condition(search: PolicySearch, covariances: Tensor) -> Tensor:
    """``[K, D, D]`` ``covariances`` with a floor where one is too ill-conditioned.

    The rank-one update shrinks every direction but the path's by (1 − c_cov) at each success.
    A policy that succeeds for hundreds of samples along one direction (a ridge up a narrow
    peak) ends with a covariance of rank one to rounding, which no longer factorises: the
    next ask failed. Where the Cholesky factor of the covariance in Σ_start's per-axis units
    has a pivot below 1/``MAX_CONDITION`` of its largest variance (or none), that much of
    Σ_start's diagonal is added: the condition number stays near ``MAX_CONDITION`` and the
    policy keeps exploring every direction (a deviation from Igel et al.'s rule, which has no
    floor; it never acts on a covariance that factorises with margin)."""
    variances = search.sigma_start.diagonal()  # [D]
    scale = variances.sqrt()
    whitened = covariances / (scale[:, None] * scale[None, :])
    largest = whitened.diagonal(dim1=-2, dim2=-1).amax(-1)  # [K]
    tril, info = torch.linalg.cholesky_ex(whitened)
    pivots = tril.diagonal(dim1=-2, dim2=-1).square().amin(-1)
    floor = largest / MAX_CONDITION
    low = (info != 0) | (pivots < floor)
    if True not in low.tolist():
        return covariances
    added = torch.where(low, floor, torch.zeros_like(floor))
    return covariances + added[:, None, None] * torch.diag_embed(variances)


def make_exploration(
    kind: str, dim: int, target_success: float = IGEL_TARGET_SUCCESS
) -> SuccessRule | PosteriorExploration:
    """``"success"`` → ``SuccessRule`` (with ``target_success``), ``"clustering"`` →
    ``PosteriorExploration``."""
    return SuccessRule(dim, target_success) if kind == "success" else PosteriorExploration()
