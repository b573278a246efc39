"""r_c of eq. 6: the reward the IGMM predicts at a component's parameter mean."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import log_prob_tril

if TYPE_CHECKING:  # a Pyro distribution: Pyro is imported when a mixture is built
    from dipole_torch.dp.state import DPMixtureState
    from dipole_torch.gaussian_mixture import GaussianMixture

__all__ = ["ComponentRewards", "RewardRegression", "reward_weights"]


class RewardRegression:
    """E[w | θ] under a Gaussian mixture over y = [θ, w] (GMR), prepared once for many queries.

    The same regression as ``GaussianMixture.condition(θ_dims, θ).mean`` without building
    distribution objects: a sweep queries it for K component means and N·m auxiliary ones,
    and the objects' construction (shape broadcasting, validation) costs more than the maths.

    Args:
        weights: ``[K]`` mixing weights (any positive scale; e.g. the component sizes).
        means: ``[K, D + 1]`` component means.
        covariances: ``[K, D + 1, D + 1]`` component covariances.
    """

    def __init__(self, weights: Tensor, means: Tensor, covariances: Tensor):
        d = means.shape[-1] - 1
        self.means = means
        self.log_weights = (weights / weights.sum()).log()
        self.mean_theta, self.mean_w = means[:, :d], means[:, d]
        self.tril = torch.linalg.cholesky(covariances[:, :d, :d])  # [K, D, D]
        # gain_k = Σ_θθ⁻¹ Σ_θw: E[w | θ, k] = μ_w + gain_kᵀ (θ − μ_θ).
        cross = covariances[:, :d, d:]
        # (two triangular solves: cholesky_solve costs more than both at these sizes)
        half = torch.linalg.solve_triangular(self.tril, cross, upper=False)
        self.gain = torch.linalg.solve_triangular(self.tril.mT, half, upper=True).squeeze(-1)
        self._bounds: tuple | None = None  # reward_weights' clamp, memoised per weights

    def predict(self, theta: Tensor) -> Tensor:
        """``[...]`` E[w | θ] for ``theta: [..., D]``."""
        diff = theta.unsqueeze(-2) - self.mean_theta  # [..., K, D]
        log_resp = torch.log_softmax(self.log_weights + log_prob_tril(diff, 0.0, self.tril), dim=-1)
        conditional = self.mean_w + (self.gain * diff).sum(-1)  # [..., K]
        return (log_resp.exp() * conditional).sum(-1)


def reward_weights(
    mixture: GaussianMixture | RewardRegression,
    query_means: Tensor,
    floor: float | None = None,
    weights: Tensor | None = None,
) -> Tensor:
    """log r_c of eq. 6: the reward the mixture predicts at a component's parameter mean.

    The reward is the last coordinate of y = [θ, r]; r_c = E[r | θ = μ_c^θ] by Gaussian mixture
    regression on ``mixture`` (the IGMM). Rewards must already be positive weights (see
    ``dipole_torch.RewardScale``).

    The regression extrapolates linearly away from the data (at a mean drawn from H it can
    predict far above the best reward, or below zero), so the prediction is clamped:

    * with ``weights``, to the data's range [max(min w, 1e-12·max |w|), max w], so no component
      is favoured beyond the best observed reward and none is ruled out;
    * without, below at 1e-12 · the largest |reward mean| of the mixture's components.

    Both bounds are relative, so r_c scales with the rewards and eq. 6's label probabilities
    do not depend on their units (an absolute floor silently switches eq. 6 off for small
    rewards). ``floor``, when given, replaces the lower bound by an absolute one.

    Args:
        mixture: the IGMM over ``[θ, r]`` (event dim D + 1), or its prepared
            ``RewardRegression``.
        query_means: ``[..., D + 1]`` component means whose θ-part is queried.
        floor: optional absolute lower bound on r_c.
        weights: ``[N]`` the data's reward weights (the last column of y).

    Returns:
        ``[...]`` log r_c.
    """
    if not isinstance(mixture, RewardRegression):
        mixture = RewardRegression(mixture.weights, mixture.means, mixture.covariances)
    d = mixture.means.shape[-1] - 1
    predicted = mixture.predict(query_means[..., :d])
    low, high = _clamp_bounds(mixture, predicted, floor, weights)
    if high is None:
        return predicted.clamp_min(low).log()
    return predicted.clamp(low, high).log()


def _clamp_bounds(
    regression: RewardRegression, predicted: Tensor, floor: float | None, weights: Tensor | None
) -> tuple[Tensor, Tensor | None]:
    """The 0-d bounds of ``reward_weights``' clamp (``high`` None without ``weights``).

    They depend on the mixture and the data only, not on the queries: a sweep queries the
    same regression twice (its components, then the auxiliary draws), so they are memoised
    on ``regression`` for the same ``weights`` tensor (unmodified) and ``floor``.
    """
    # (Inference tensors have no version counter: their bounds are not memoised.)
    cacheable = weights is None or not weights.is_inference()
    key = (weights, weights._version if weights is not None and cacheable else None, floor)
    key += (predicted.dtype,)
    memo = regression._bounds
    if cacheable and memo is not None and memo[0][0] is key[0] and memo[0][1:] == key[1:]:
        return memo[1]
    reference = (weights if weights is not None else regression.means[..., -1]).to(predicted)
    # The smallest normal float only matters for all-zero rewards, where eq. 6 is void.
    low = (1e-12 * reference.abs().max()).clamp_min(torch.finfo(predicted.dtype).tiny)
    if weights is not None:
        low = torch.maximum(low, reference.min())
    if floor is not None:
        low = torch.full_like(low, floor)
    high = None if weights is None else torch.maximum(reference.max(), low)
    if cacheable:
        regression._bounds = (key, (low, high))
    return low, high


class ComponentRewards:
    """Eq. 6's log r_c during one sweep, for any component means: ``reward_weights`` of the
    sweep's starting mixture (components weighted by their sizes), clamped to the range of
    the data's reward weights.

    Args:
        state: the sweep's starting state.
        weights: ``[N]`` the data's reward weights (the last column of y).
    """

    def __init__(self, state: DPMixtureState, weights: Tensor):
        counts = torch.bincount(state.labels, minlength=state.num_components)
        self.regression = RewardRegression(counts.to(weights.dtype), state.means, state.covariances)
        self.weights = weights

    def __call__(self, means: Tensor) -> Tensor:
        """``[...]`` log r_c for ``means: [..., D + 1]``."""
        return reward_weights(self.regression, means, weights=self.weights)
