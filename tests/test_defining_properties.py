"""The defining property of each piece of DIPOLE's mathematics, tested directly: the
(1+1)-CMA-ES success rule, the paper's global importance set, the hyperprior update of H,
what a sweep hands to it, the posterior point estimate, draws given a precision, the
sequential Chinese-restaurant start and the reward regression of eq. 6.

Each test checks the formula itself (exact values on hand-built inputs, or moments over many
draws from a fixed seed with a margin of about four standard errors), so that a changed
constant, a dropped factor or another degree of freedom makes it fail.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from torch.distributions import MultivariateNormal

from dipole_torch import Dipole, DipoleOptions
from dipole_torch.dp.conditionals import draw_mean, posterior_point_estimate
from dipole_torch.dp.neal8 import neal8_sweep
from dipole_torch.dp.reward_weights import RewardRegression
from dipole_torch.dp.sampler import DPSampler
from dipole_torch.dp.state import DPMixtureState, sequential_labels
from dipole_torch.gaussian_mixture import GaussianMixture
from dipole_torch.prior import NormalInverseWishartPrior

F64 = torch.float64


def spd(rows: list[list[float]]) -> torch.Tensor:
    return torch.tensor(rows, dtype=F64)


# ---------------------------------------------------------------------- a. the success rule
def bimodal(theta: torch.Tensor) -> torch.Tensor:
    return -((theta - 1.0).pow(2).sum(-1)) * ((theta + 1.0).pow(2).sum(-1))


# The success rule's target rate: the library's default, and Igel et al.'s 2/11.
TARGETS = (DipoleOptions().success_target, 2.0 / 11.0)


def success_rule_dipole(sigma_start: torch.Tensor, target: float, **changes) -> Dipole:
    """A default Dipole (success-rule exploration, target rate ``target``) with no scouts,
    probes, retirement or merging, after its first tell: one row per policy at the next asks,
    and nothing but the success rule changes a covariance before the next clustering.
    ``changes``: other options instead of these (scouts, ``max_sampled``)."""
    options = dict(explore=0.0, hill_valley=False, retire_std=0.0, merge_radius=0.0,
                   max_sampled=None, max_policies=None)  # fmt: skip
    opt = Dipole(
        torch.zeros(2, dtype=F64),
        sigma_start,
        generator=torch.Generator().manual_seed(0),
        success_target=target,
        **(options | changes),
    )
    theta = opt.ask()
    opt.tell(theta, bimodal(theta))
    return opt


def success_rule_by_hand(opt: Dipole, theta, rewards, owner):
    """The success rule of Igel, Suttorp & Hansen (2006), one told row at a time in Python
    scalars: ``(paths, success, covariances, capped, successes)`` after the tell. Σ is their
    σ²C in one matrix, so the path is their σ·p_c: it scales with σ's factor. The target
    rate p_t is the optimizer's ``success_target`` (Igel et al.'s is 2/11)."""
    dim = opt.dim
    c_p, p_t = 1.0 / 12.0, opt.options.success_target
    c_c, c_cov, damping = 2.0 / (dim + 2.0), 2.0 / (dim * dim + 6.0), 1.0 + dim / 2.0
    paths = opt.policy_set.paths.clone()
    success = opt.policy_set.success.clone()
    covs = opt.policy_covariances.clone()
    best = opt.policy_best_rewards.clone()
    start_var = opt.sigma_start.diagonal()
    capped, successes = [], []
    for row, k in enumerate(owner.tolist()):
        succeeded = bool(rewards[row] > best[k])
        successes.append(succeeded)
        path, cov = paths[k].clone(), covs[k].clone()
        if succeeded:
            step = theta[row] - opt.policy_means[k]
            path = (1 - c_c) * path + math.sqrt(c_c * (2 - c_c)) * step
            cov = (1 - c_cov) * cov + c_cov * torch.outer(path, path)
        rate = (1 - c_p) * float(success[k]) + c_p * float(succeeded)
        factor = math.exp((rate - p_t) / (damping * (1 - p_t)))
        limit = 1.0 / math.sqrt(float((cov.diagonal() / start_var).max()))
        capped.append(factor > limit)
        factor = min(factor, limit)
        paths[k], success[k], covs[k] = path * factor, rate, cov * factor**2
    return paths, success, covs, capped, successes


def tell_and_check_the_rule(opt: Dipole, theta, rewards, owner):
    """Tell ``rewards`` and check p̄, the paths and Σ against ``success_rule_by_hand``;
    returns its ``(capped, successes)``."""
    paths, success, covs, capped, successes = success_rule_by_hand(
        opt, theta.clone(), rewards, owner
    )
    opt.tell(theta, rewards)
    torch.testing.assert_close(opt.policy_set.success, success, rtol=1e-13, atol=0)
    torch.testing.assert_close(opt.policy_set.paths, paths, rtol=1e-11, atol=1e-14)
    torch.testing.assert_close(opt.policy_covariances, covs, rtol=1e-11, atol=1e-14)
    return capped, successes


@pytest.mark.parametrize("target", TARGETS)
def test_a_tie_with_the_best_kept_return_is_no_success(target):
    opt = success_rule_dipole(torch.eye(2, dtype=F64), target)
    assert torch.equal(opt.policy_set.success, torch.full_like(opt.policy_set.success, target))
    theta = opt.ask()
    owner = opt.asked_owner.clone()
    best = opt.policy_best_rewards[owner]
    before = opt.policy_covariances.clone()
    opt.tell(theta, best)  # every sample ties its policy's best kept return
    p_t = target
    expected_rate = torch.full_like(opt.policy_set.success, (1 - 1 / 12) * p_t)
    torch.testing.assert_close(opt.policy_set.success, expected_rate, rtol=1e-14, atol=0)
    assert torch.equal(opt.policy_set.paths, torch.zeros_like(opt.policy_set.paths))
    # No rank-one term: every covariance only shrinks by the same scalar factor.
    factor = math.exp((expected_rate[0] - p_t) / ((1 + opt.dim / 2) * (1 - p_t))) ** 2
    assert factor < 1 - 1e-3
    torch.testing.assert_close(opt.policy_covariances, before * factor, rtol=1e-12, atol=0)


@pytest.mark.parametrize("target", TARGETS)
def test_the_success_rule_exact_values_tell_by_tell(target):
    # Σ_start with unequal axes, so that the cap acts per axis.
    sigma_start = torch.diag(torch.tensor([1.0, 0.36], dtype=F64))
    opt = success_rule_dipole(sigma_start, target)
    assert opt.num_policies >= 3
    capped_any, uncapped_success = False, False
    # Iterations 1-4 precede the next clustering (every M = 5 iterations).
    for t in range(4):
        theta = opt.ask()
        owner = opt.asked_owner.clone()
        assert torch.equal(owner, torch.arange(opt.num_policies))
        best = opt.policy_best_rewards[owner]
        # Alternately a success (better than the best kept) and a tie (no success).
        succeed = (owner + t) % 2 == 0
        rewards = torch.where(succeed, best + 0.5 * best.abs() + 1.0, best)
        capped, successes = tell_and_check_the_rule(opt, theta, rewards, owner)
        assert successes == succeed.tolist()
        capped_any |= any(capped)
        uncapped_success |= any(s and not c for s, c in zip(successes, capped, strict=True))
        # The cap: no exploration std beyond Σ_start's on any axis.
        assert bool((opt.relative_std() <= 1.0 + 1e-12).all())
    # Both branches of the cap were exercised.
    assert capped_any and uncapped_success


@pytest.mark.parametrize("target", TARGETS)
def test_the_success_rule_exact_values_when_a_batch_samples_some_policies(target):
    # A batch cut to fewer rows than policies (as train.py cuts the last one): the sampled
    # policies' p̄, path and Σ are updated by the rule (the gathered and scattered rows),
    # the others' stand.
    sigma_start = torch.diag(torch.tensor([1.0, 0.36], dtype=F64))
    opt = success_rule_dipole(sigma_start, target)
    k = opt.num_policies
    assert k >= 3
    for t in range(3):
        theta = opt.ask(max_rows=k - 1)
        owner = opt.asked_owner[: theta.shape[0]].clone()  # (the rows told)
        assert len(set(owner.tolist())) == owner.numel() == k - 1  # some policies, once each
        best = opt.policy_best_rewards[owner]
        succeed = (torch.arange(k - 1) + t) % 2 == 0
        rewards = torch.where(succeed, best + 0.5 * best.abs() + 1.0, best)
        _, successes = tell_and_check_the_rule(opt, theta, rewards, owner)
        assert successes == succeed.tolist()


@pytest.mark.parametrize("target", TARGETS)
def test_the_success_rule_exact_values_with_max_sampled_and_scouts(target):
    # The default's batch: max_sampled of the policies, then the scouts' rows (no policy's).
    # The rule updates the sampled policies from their rows alone; the others' stand.
    sigma_start = torch.diag(torch.tensor([1.0, 0.36], dtype=F64))
    opt = success_rule_dipole(sigma_start, target, explore=0.5, max_sampled=2)
    assert opt.num_policies >= 3
    for t in range(3):
        theta = opt.ask()
        rows = int((opt.asked_owner >= 0).sum())
        owner = opt.asked_owner[:rows].clone()
        assert rows == 2 and theta.shape[0] > rows  # two policies, then scouts
        best = opt.policy_best_rewards[owner]
        succeed = (torch.arange(rows) + t) % 2 == 0
        rewards = torch.where(succeed, best + 0.5 * best.abs() + 1.0, best)
        rewards = torch.cat((rewards, torch.full((theta.shape[0] - rows,), -1e3, dtype=F64)))
        tell_and_check_the_rule(opt, theta, rewards, owner)


# ---------------------------------------------------------------------- b. global importance
def paper_with_archive(m: int, means, thetas, rewards, owner) -> Dipole:
    opt = Dipole.paper(torch.zeros(2, dtype=F64), 1.0, M=m, generator=torch.Generator())
    opt.policy_set.reset(means.clone(), torch.eye(2, dtype=F64).repeat(means.shape[0], 1, 1))
    opt.archive.replace(thetas.clone(), rewards.clone(), owner.clone())
    return opt


def test_global_importance_keeps_the_best_k_times_m_overall_before_eq7():
    # K = 2 policies, M = 2. Policy 0 owns the three best samples overall; policy 1 the
    # fourth best and worse ones. The best K·M = 4 overall are {10, 9, 8, 7}; within them
    # each policy averages its own best M: policy 0 {10, 9}, policy 1 {7}.
    thetas = torch.arange(16, dtype=F64).reshape(8, 2) / 4.0
    rewards = torch.tensor([10.0, 7.0, 9.0, 6.0, 8.0, 1.0, 0.5, 3.0], dtype=F64)
    owner = torch.tensor([0, 1, 0, 1, 0, 1, 1, 1])
    means = torch.tensor([[0.0, 0.0], [5.0, -5.0]], dtype=F64)
    opt = paper_with_archive(2, means, thetas, rewards, owner)
    opt.importance.power_step(opt)
    assert sorted(opt.archive.rewards.tolist()) == [7.0, 9.0, 10.0]
    # Eq. 7 with the returns as weights ("positive", the paper's variant).
    expected0 = (10.0 * thetas[0] + 9.0 * thetas[2]) / 19.0
    torch.testing.assert_close(opt.policy_means[0], expected0, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(opt.policy_means[1], thetas[1], rtol=1e-14, atol=1e-14)


def test_global_importance_keeps_every_sample_when_fewer_than_k_times_m():
    thetas = torch.tensor([[1.0, 2.0], [3.0, 1.0], [-1.0, 0.5]], dtype=F64)
    rewards = torch.tensor([2.0, 1.0, 4.0], dtype=F64)
    owner = torch.tensor([0, 0, 1])
    means = torch.zeros(2, 2, dtype=F64)
    opt = paper_with_archive(2, means, thetas, rewards, owner)
    opt.importance.power_step(opt)
    assert sorted(opt.archive.rewards.tolist()) == [1.0, 2.0, 4.0]
    torch.testing.assert_close(opt.policy_means[0], (2.0 * thetas[0] + thetas[1]) / 3.0)
    torch.testing.assert_close(opt.policy_means[1], thetas[2])


# ---------------------------------------------------------------------- c. H's update
D_C, K_C, DRAWS_C = 2, 4, 8000


@pytest.fixture(scope="module")
def hyperprior_draws():
    """``DRAWS_C`` updates of H from fixed components, with the current H's Σ0 and ν0 unlike
    the initial one's (so the test tells which prior each term comes from)."""
    initial = NormalInverseWishartPrior(
        mean_loc=torch.tensor([0.5, -1.0], dtype=F64),
        mean_covariance=spd([[2.0, 0.6], [0.6, 1.0]]),
        df=6.0,
        scale=spd([[1.5, -0.4], [-0.4, 0.8]]),
        regularization=0.05 * torch.eye(2, dtype=F64),
    )
    current = NormalInverseWishartPrior(
        mean_loc=torch.tensor([1.0, 1.0], dtype=F64),
        mean_covariance=spd([[0.7, -0.2], [-0.2, 1.4]]),
        df=5.5,
        scale=spd([[1.0, 0.3], [0.3, 2.0]]),
        regularization=0.05 * torch.eye(2, dtype=F64),
    )
    means = torch.tensor([[3.0, 1.0], [2.0, -2.0], [4.0, 0.5], [-1.0, 3.0]], dtype=F64)
    a = torch.tensor([[[0.6, 0.2], [0.0, 0.4]]], dtype=F64) * torch.arange(
        1, K_C + 1, dtype=F64
    ).reshape(-1, 1, 1)
    covariances = a @ a.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=F64)
    g = torch.Generator().manual_seed(1234)
    loc, mean_cov, scale = [], [], []
    for _ in range(DRAWS_C):
        drawn = current.updated(means, covariances, initial, g)
        loc.append(drawn.mean_loc)
        mean_cov.append(drawn.mean_covariance)
        scale.append(drawn.scale)
    return {
        "initial": initial,
        "current": current,
        "means": means,
        "covariances": covariances,
        "loc": torch.stack(loc),
        "mean_covariance": torch.stack(mean_cov),
        "scale": torch.stack(scale),
    }


def within_four_standard_errors(draws: torch.Tensor, expected: torch.Tensor) -> None:
    mean = draws.mean(0)
    error = draws.std(0) / math.sqrt(draws.shape[0])
    z = ((mean - expected) / error).abs()
    assert bool((z < 4.0).all()), f"means {mean} vs {expected}: z = {z}"


def test_hyperprior_mean_loc_has_its_conditional_posterior_mean(hyperprior_draws):
    h = hyperprior_draws
    inv = torch.linalg.inv
    hyper = inv(h["initial"].mean_covariance)
    spread = inv(h["current"].mean_covariance)
    precision = hyper + K_C * spread
    expected = inv(precision) @ (hyper @ h["initial"].mean_loc + spread @ h["means"].sum(0))
    within_four_standard_errors(h["loc"], expected)
    # ...and its conditional posterior covariance P⁻¹ (within 5 % on every entry's scale).
    empirical = torch.cov(h["loc"].T)
    scale = inv(precision).diagonal().sqrt()
    gap = (empirical - inv(precision)).abs() / torch.outer(scale, scale)
    assert bool((gap < 0.05).all())


def test_hyperprior_scale_has_its_conditional_posterior_mean(hyperprior_draws):
    # Ψ0 | {Σ_k} ~ Wishart(ν_h + K ν0, (V⁻¹ + Σ_k Σ_k⁻¹)⁻¹), ν_h = D + 1, V = Ψ0_init / ν_h.
    h = hyperprior_draws
    nu_h = D_C + 1.0
    v = h["initial"].scale / nu_h
    posterior = torch.linalg.inv(torch.linalg.inv(v) + torch.linalg.inv(h["covariances"]).sum(0))
    expected = (nu_h + K_C * h["current"].df) * posterior
    within_four_standard_errors(h["scale"], expected)


def test_hyperprior_mean_covariance_has_its_conditional_mean_given_the_drawn_loc(
    hyperprior_draws,
):
    # Σ0 | μ0, {μ_k} ~ IW(ν_s + K, 2 Σ0_init + Σ_k (μ_k − μ0)(μ_k − μ0)ᵀ), ν_s = D + 3: its
    # mean given each drawn μ0 is that scale over ν_s + K − D − 1 = K + 2.
    h = hyperprior_draws
    centred = h["means"][None] - h["loc"][:, None, :]  # [draws, K, D]
    scatter = centred.transpose(-1, -2) @ centred
    conditional = (2.0 * h["initial"].mean_covariance + scatter) / (K_C + 2.0)
    within_four_standard_errors(h["mean_covariance"] - conditional, torch.zeros(2, 2, dtype=F64))


# ---------------------------------------------------------------------- d. what a sweep hands H
def test_neal8_sweep_hands_the_unregularised_covariances_to_the_prior_update(monkeypatch):
    regularization = 0.2 * torch.eye(3, dtype=F64)
    prior = NormalInverseWishartPrior(
        mean_loc=torch.zeros(3, dtype=F64),
        mean_covariance=4.0 * torch.eye(3, dtype=F64),
        df=7.0,
        scale=3.0 * torch.eye(3, dtype=F64),
        regularization=regularization,
    )
    g = torch.Generator().manual_seed(5)
    y = torch.randn(30, 3, generator=g, dtype=F64)
    y[:15] += 3.0
    sampler = DPSampler(prior, update_prior=True)
    seen = []
    original = NormalInverseWishartPrior.updated

    def spy(self, means, covariances, initial, generator=None):
        seen.append((means.clone(), covariances.clone(), initial))
        return original(self, means, covariances, initial, generator)

    monkeypatch.setattr(NormalInverseWishartPrior, "updated", spy)
    state = DPMixtureState.single_component(y, prior)
    for _ in range(3):
        state = neal8_sweep(y, state, sampler, g)
        means, covariances, initial = seen[-1]
        assert initial is prior
        torch.testing.assert_close(means, state.means, rtol=0, atol=0)
        # The components' Σ (the state holds Σ + R), as IW(ν0, Ψ0) draws them.
        torch.testing.assert_close(covariances, state.covariances - regularization)
    assert len(seen) == 3


# ---------------------------------------------------------------------- e. the point estimate
def test_posterior_point_estimate_is_the_conditional_means():
    p = 3
    prior = NormalInverseWishartPrior(
        mean_loc=torch.tensor([0.5, -0.5, 1.0], dtype=F64),
        mean_covariance=spd([[2.0, 0.3, 0.0], [0.3, 1.0, -0.2], [0.0, -0.2, 1.5]]),
        df=7.5,
        scale=spd([[1.2, 0.1, 0.2], [0.1, 0.9, 0.0], [0.2, 0.0, 1.1]]),
        regularization=torch.diag(torch.tensor([0.01, 0.02, 0.03], dtype=F64)),
    )
    y = torch.tensor(
        [
            [0.0, 0.1, 1.0],
            [0.4, -0.3, 1.2],
            [-0.2, 0.0, 0.7],
            [3.0, 2.0, -1.0],
            [3.5, 2.2, -0.4],
            [-2.0, 1.0, 0.0],
            [-2.4, 0.6, 0.3],
        ],
        dtype=F64,
    )
    labels = torch.tensor([0, 0, 0, 1, 1, 2, 2])
    # Means that are not the data's: the scatter is taken about them.
    means = torch.tensor([[0.1, 0.0, 1.0], [3.0, 2.5, -0.5], [-2.0, 0.5, 0.5]], dtype=F64)
    state = DPMixtureState(labels, means, torch.eye(p, dtype=F64).repeat(3, 1, 1), prior)
    estimate = posterior_point_estimate(y, state)
    inv = torch.linalg.inv
    for k in range(3):
        points = y[labels == k]
        n = points.shape[0]
        scatter = sum(torch.outer(row - means[k], row - means[k]) for row in points)
        cov = (prior.scale + scatter) / (prior.df + n - p - 1) + prior.regularization
        torch.testing.assert_close(estimate.covariances[k], cov, rtol=1e-13, atol=0)
        # E[μ | Σ, y] with the likelihood's covariance Σ (+ R, as estimated).
        precision = inv(prior.mean_covariance) + n * inv(cov)
        rhs = inv(prior.mean_covariance) @ prior.mean_loc + inv(cov) @ points.sum(0)
        torch.testing.assert_close(estimate.means[k], inv(precision) @ rhs, rtol=1e-10, atol=0)
    assert torch.equal(estimate.labels, labels)


# ---------------------------------------------------------------------- f. draws given P
def test_draw_mean_has_the_inverse_precision_as_covariance():
    # The μ step's draw (``draw_mean``): μ0 + L⁻ᵀ (half + z) with P = L Lᵀ; half = 0 here.
    precision = spd([[4.0, 3.0], [3.0, 2.5]])
    covariance = torch.linalg.inv(precision)  # [[2.5, -3], [-3, 4]]
    tril = torch.linalg.cholesky(precision)
    # L⁻¹ z would have covariance (Lᵀ L)⁻¹ = [[0.25, -0.75], [-0.75, 6.25]]: far from P⁻¹.
    assert (torch.linalg.inv(tril.T @ tril) - covariance).abs().max() > 2.0
    n = 100_000
    loc = torch.tensor([1.0, -2.0], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    prior = NormalInverseWishartPrior(loc, eye, 5.0, eye, 0.0 * eye)
    normals = torch.randn(n, 2, generator=torch.Generator().manual_seed(3), dtype=F64)
    draws = draw_mean(prior, torch.zeros(n, 2, 1, dtype=F64), tril.expand(n, 2, 2), normals)
    within_four_standard_errors(draws, loc)
    empirical = torch.cov(draws.T)
    # Var of a sample covariance entry ≈ (s_ij² + s_ii s_jj) / n.
    error = (covariance.square() + torch.outer(covariance.diagonal(), covariance.diagonal())) / n
    assert bool(((empirical - covariance).abs() < 4.0 * error.sqrt()).all())


# ---------------------------------------------------------------------- g. the sequential start
def sequential_partition_probabilities(y, mean_loc, mean_cov, cov, alpha):
    """Every partition's probability under the sequential Chinese-restaurant pass, by
    enumeration over the uniformly random orders and every choice: a point joins cluster c
    ∝ n_c N(y; ȳ_c, (1 + 1/n_c) C), a new one ∝ α N(y; μ0, Σ0 + C)."""
    n = len(y)
    out: dict[frozenset, float] = {}

    def visit(order, pos, clusters, prob):
        if pos == n:
            key = frozenset(frozenset(c) for c in clusters)
            out[key] = out.get(key, 0.0) + prob
            return
        i = order[pos]
        logits = []
        for c in clusters:
            nc = len(c)
            centre = sum(y[j] for j in c) / nc
            logits.append(
                math.log(nc) + float(MultivariateNormal(centre, (1 + 1 / nc) * cov).log_prob(y[i]))
            )
        new = MultivariateNormal(mean_loc, mean_cov + cov).log_prob(y[i])
        logits.append(math.log(alpha) + float(new))
        top = max(logits)
        weights = [math.exp(v - top) for v in logits]
        total = sum(weights)
        for choice, weight in enumerate(weights):
            grown = [list(c) for c in clusters]
            if choice < len(clusters):
                grown[choice].append(i)
            else:
                grown.append([i])
            visit(order, pos + 1, grown, prob * weight / total)

    orders = list(itertools.permutations(range(n)))
    for order in orders:
        visit(order, 0, [], 1.0 / len(orders))
    return out


def test_sequential_labels_follow_the_sequential_crp_probabilities():
    prior = NormalInverseWishartPrior(
        mean_loc=torch.tensor([0.5, 0.0], dtype=F64),
        mean_covariance=spd([[2.0, 0.5], [0.5, 1.0]]),
        df=6.0,
        scale=spd([[1.2, 0.3], [0.3, 0.6]]),  # E_H[Σ] = Ψ0 / (ν0 − D − 1) = Ψ0 / 3
        regularization=spd([[0.1, 0.0], [0.0, 0.1]]),
    )
    alpha = 1.3
    y = torch.tensor([[0.0, 0.0], [0.5, 0.2], [1.5, -1.0]], dtype=F64)
    # The components' covariance in the model is Σ + R; Σ at its prior mean.
    cov = prior.expected_covariance + prior.regularization
    expected = sequential_partition_probabilities(
        list(y), prior.mean_loc, prior.mean_covariance, cov, alpha
    )
    runs = 6000
    counts: dict[frozenset, int] = {}
    for seed in range(runs):
        labels = sequential_labels(y, prior, alpha, torch.Generator().manual_seed(seed)).tolist()
        key = frozenset(
            frozenset(i for i, c in enumerate(labels) if c == label) for label in set(labels)
        )
        counts[key] = counts.get(key, 0) + 1
    assert set(counts) <= set(expected)
    for key, p in expected.items():
        frequency = counts.get(key, 0) / runs
        error = math.sqrt(p * (1 - p) / runs)
        assert abs(frequency - p) < 4 * error, (sorted(map(sorted, key)), frequency, p)


# ---------------------------------------------------------------------- h. the reward regression
def test_reward_regression_is_gaussian_mixture_regression():
    g = torch.Generator().manual_seed(11)
    k, d = 3, 2
    a = torch.randn(k, d + 1, d + 1, generator=g, dtype=F64)
    covariances = a @ a.transpose(-1, -2) + 0.2 * torch.eye(d + 1, dtype=F64)
    # Correlated θ-w blocks: the gain Σ_θθ⁻¹ Σ_θw differs from Σ_θw itself.
    gain = torch.linalg.solve(covariances[:, :d, :d], covariances[:, :d, d:]).squeeze(-1)
    assert (gain - covariances[:, :d, d]).abs().max() > 0.1
    means = torch.randn(k, d + 1, generator=g, dtype=F64)
    weights = torch.tensor([1.0, 2.5, 0.7], dtype=F64)
    theta = torch.randn(6, d, generator=g, dtype=F64)
    predicted = RewardRegression(weights, means, covariances).predict(theta)
    mixture = GaussianMixture(weights, means, covariances)
    torch.testing.assert_close(
        predicted, mixture.condition(range(d), theta).mean[..., 0], rtol=1e-10, atol=1e-12
    )
    # And by hand: Σ_k h_k(θ) (μ_w + Σ_wθ Σ_θθ⁻¹ (θ − μ_θ)), h_k ∝ π_k N(θ; μ_θ, Σ_θθ).
    for row in theta:
        log_h = torch.stack(
            [
                weights[j].log()
                + MultivariateNormal(means[j, :d], covariances[j, :d, :d]).log_prob(row)
                for j in range(k)
            ]
        )
        h = torch.softmax(log_h, 0)
        conditional = torch.stack(
            [
                means[j, d]
                + covariances[j, d, :d]
                @ torch.linalg.inv(covariances[j, :d, :d])
                @ (row - means[j, :d])
                for j in range(k)
            ]
        )
        expected = (h * conditional).sum()
        torch.testing.assert_close(
            RewardRegression(weights, means, covariances).predict(row), expected
        )
