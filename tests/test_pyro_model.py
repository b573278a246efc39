"""The Pyro model of the DP mixture, and the sampler checked against it.

* The model's log joint (``poutine.trace``) equals the closed form the sampler is derived
  from, for states the sampler produces.
* A Geweke (2004) joint-distribution test: forward draws (θ, y) of the model against the
  successive-conditional simulator that alternates one Gibbs sweep θ | y with y | θ. Both
  sample p(θ, y) exactly when the sweep leaves p(θ | y) invariant; a broken conditional shows
  as a shift in the means of test functions g(θ, y).
"""

import itertools
import math

import pyro
import pyro.poutine as poutine
import pytest
import torch
from scipy.stats import invwishart

from dipole_torch import DPMixtureState, DPSampler, NormalInverseWishartPrior
from dipole_torch.pyro_model import (
    InverseWishart,
    canonical_state,
    dp_log_joint,
    dp_mixture_model,
    state_from_trace,
    state_sites,
)

F64 = torch.float64


def prior_2d():
    return NormalInverseWishartPrior(
        mean_loc=torch.tensor([1.0, -2.0], dtype=F64),
        mean_covariance=torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=F64),
        df=6.0,
        scale=torch.tensor([[3.0, 0.5], [0.5, 1.5]], dtype=F64),
        regularization=0.1 * torch.eye(2, dtype=F64),
    )


def test_inverse_wishart_density_and_mean():
    scale = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=F64)
    dist = InverseWishart(7.0, scale)
    draws = dist.sample((20000,), generator=torch.Generator().manual_seed(0))
    assert draws.shape == (20000, 2, 2)
    expected = invwishart(7.0, scale.numpy()).logpdf(draws[:5].numpy().transpose(1, 2, 0))
    torch.testing.assert_close(dist.log_prob(draws[:5]), torch.as_tensor(expected))
    torch.testing.assert_close(draws.mean(0), dist.mean, rtol=0.05, atol=0.01)
    torch.testing.assert_close(dist.mean, scale / (7.0 - 2 - 1))
    assert dist.expand((3,)).log_prob(draws[:3]).shape == (3,)
    with pytest.raises(ValueError, match="df must exceed"):
        InverseWishart(0.5, scale)
    # ν > D − 1 is all a Wishart needs (its mean is finite beyond D + 1 only).
    assert torch.isfinite(InverseWishart(1.5, scale).log_prob(draws[:2])).all()
    with pytest.raises(ValueError, match="df must exceed D - 1 = 1"):
        InverseWishart(1.0, scale)


def test_crp_labels_sum_to_one_over_all_partitions():
    # Every partition of 4 points, in first-appearance labelling (restricted growth strings).
    prior, n, alpha = prior_2d(), 4, 1.7
    total = 0.0
    for labels in itertools.product(range(n), repeat=n):
        if any(labels[i] > max(labels[:i], default=-1) + 1 for i in range(n)):
            continue
        sites = {f"label_{i}": torch.tensor(c) for i, c in enumerate(labels)}
        trace = poutine.trace(poutine.condition(dp_mixture_model, data=sites)).get_trace(
            prior, alpha, n
        )
        trace.compute_log_prob()
        total += math.exp(sum(float(trace.nodes[f"label_{i}"]["log_prob"]) for i in range(n)))
    assert total == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_trace_log_joint_equals_the_closed_form_for_sampler_states(seed):
    prior = prior_2d()
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(14, 2, generator=g, dtype=F64)
    y[:7] += 4.0
    sampler = DPSampler(prior, alpha=0.8, m=3, update_prior=False)
    state = sampler.fit(y, 4, generator=g, init="sequential")
    assert state.num_components >= 2
    # The sampler's numbering need not be the CRP's: reverse it to be sure.
    flipped = DPMixtureState(
        labels=state.num_components - 1 - state.labels,
        means=state.means.flip(0),
        covariances=state.covariances.flip(0),
        prior=prior,
    )
    expected = dp_log_joint(y, flipped, 0.8)
    torch.testing.assert_close(dp_log_joint(y, canonical_state(flipped), 0.8), expected)
    conditioned = poutine.condition(dp_mixture_model, data=state_sites(flipped, y))
    trace = poutine.trace(conditioned).get_trace(prior, 0.8, data=y)
    torch.testing.assert_close(trace.log_prob_sum(), expected)
    assert torch.isfinite(expected)
    # Moving one point to another component changes both the same way.
    moved = DPMixtureState(state.labels.clone(), state.means, state.covariances, prior)
    counts = state.counts
    point = int(torch.nonzero(counts[state.labels] > 1)[0])
    moved.labels[point] = (moved.labels[point] + 1) % state.num_components
    trace = poutine.trace(poutine.condition(dp_mixture_model, data=state_sites(moved, y)))
    torch.testing.assert_close(
        trace.get_trace(prior, 0.8, data=y).log_prob_sum(), dp_log_joint(y, moved, 0.8)
    )


def test_forward_draws_have_the_crp_and_prior_moments():
    prior = prior_2d()
    pyro.set_rng_seed(0)
    labels, means, covariances, y = dp_mixture_model(prior, 1.0, 3, num_draws=20000)
    assert labels.shape == (20000, 3) and y.shape == (20000, 3, 2)
    num_tables = labels.max(-1).values + 1
    # CRP with α = 1 and 3 points: P(K = 1) = 1/3, P(K = 3) = 1/6.
    assert float((num_tables == 1).double().mean()) == pytest.approx(1 / 3, abs=0.015)
    assert float((num_tables == 3).double().mean()) == pytest.approx(1 / 6, abs=0.015)
    # y_i ~ μ0 marginally, with covariance Σ0 + E[Σ] + R.
    torch.testing.assert_close(y[:, 0].mean(0), prior.mean_loc, atol=0.06, rtol=0)
    expected = prior.mean_covariance + prior.expected_covariance + prior.regularization
    torch.testing.assert_close(torch.cov(y[:, 0].T), expected, rtol=0.06, atol=0.05)
    state = state_from_trace(poutine.trace(dp_mixture_model).get_trace(prior, 1.0, 5), prior)
    assert state.labels.shape == (5,) and state.means.shape == (state.num_components, 2)


def _forward_state(n=6, seed=0):
    prior = prior_2d()
    pyro.set_rng_seed(seed)
    trace = poutine.trace(dp_mixture_model).get_trace(prior, 1.0, n)
    return trace.nodes["y"]["value"], state_from_trace(trace, prior)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_model_refuses_non_finite_data(bad):
    # With Pyro's validation off (as in production runs) NaN data gave a NaN log joint.
    data = torch.randn(5, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    data[2, 1] = bad
    with pytest.raises(
        ValueError, match=r"data contains non-finite values \(first at index \(2, 1\)\)"
    ):
        dp_mixture_model(prior_2d(), 1.0, data=data)
    batched = data.expand(3, 5, 2)
    with pytest.raises(ValueError, match="data contains non-finite"):
        dp_mixture_model(prior_2d(), 1.0, data=batched, num_draws=3)


@pytest.mark.parametrize("num_draws", [None, 1, 3, 5])
def test_model_requires_batched_data_to_match_num_draws(num_draws):
    # [B, N, D] data without num_draws (or with num_draws = 1) scored all B data sets under
    # one label set; with num_draws = 3 it failed only at log_prob_sum.
    data = torch.randn(4, 5, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"data .*num_draws=\d+"):
        dp_mixture_model(prior_2d(), 1.0, data=data, num_draws=num_draws)


def test_model_takes_batched_data_with_matching_num_draws():
    prior = prior_2d()
    data = torch.randn(4, 5, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    pyro.set_rng_seed(0)
    trace = poutine.trace(dp_mixture_model).get_trace(prior, 1.0, data=data, num_draws=4)
    labels, _, _, y = trace.nodes["_RETURN"]["value"]
    assert labels.shape == (4, 5) and y is data
    assert torch.isfinite(trace.log_prob_sum())
    # One data set for every draw is said so explicitly, by expanding it.
    with pytest.raises(ValueError, match=r"data must have shape \[4, N, 2\]"):
        dp_mixture_model(prior, 1.0, data=data[0], num_draws=4)
    labels, *_ = dp_mixture_model(prior, 1.0, data=data[0].expand(4, 5, 2), num_draws=4)
    assert labels.shape == (4, 5)
    with pytest.raises(ValueError, match=r"data must have shape \[N, 2\]"):
        dp_mixture_model(prior, 1.0, data=data[0, :, :1])


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"num_points": 2.5}, ValueError, "num_points must be a positive integer"),
        ({"num_points": 0}, ValueError, "num_points must be a positive integer"),
        ({"num_points": True}, ValueError, "num_points must be a positive integer"),
        ({"num_points": None}, ValueError, "num_points must be a positive integer"),
        ({"num_points": 3, "num_draws": 0}, ValueError, "num_draws must be a positive integer"),
        ({"num_points": 3, "num_draws": 2.5}, ValueError, "num_draws must be a positive integer"),
        ({"num_points": 3, "num_draws": -1}, ValueError, "num_draws must be a positive integer"),
        ({"num_points": 3, "alpha": math.inf}, ValueError, "alpha must be a positive finite"),
        ({"num_points": 3, "alpha": math.nan}, ValueError, "alpha must be a positive finite"),
        ({"num_points": 3, "alpha": 0.0}, ValueError, "alpha must be a positive finite"),
        ({"num_points": 3, "alpha": "1"}, ValueError, "alpha must be a real number"),
        ({"num_points": 3, "prior": "H"}, TypeError, "prior must be a NormalInverseWishartPrior"),
        ({"data": [[0.0, 1.0]]}, TypeError, "data must be a floating-point torch.Tensor"),
    ],
    ids=[
        "num_points-fraction",
        "num_points-zero",
        "num_points-bool",
        "num_points-missing",
        "num_draws-zero",
        "num_draws-fraction",
        "num_draws-negative",
        "alpha-inf",
        "alpha-nan",
        "alpha-zero",
        "alpha-string",
        "prior-not-a-prior",
        "data-a-list",
    ],
)
def test_model_refuses_bad_counts_alpha_and_arguments(kwargs, error, match):
    kwargs = {"prior": prior_2d(), "alpha": 1.0, **kwargs}
    with pytest.raises(error, match=match):
        dp_mixture_model(**kwargs)


def test_model_takes_whole_float_counts():
    labels, means, _, y = dp_mixture_model(prior_2d(), 1.0, 3.0, num_draws=2.0)
    assert labels.shape == (2, 3) and means.shape == (2, 3, 2) and y.shape == (2, 3, 2)


@pytest.mark.parametrize("alpha", [0.0, -1.0, math.inf, math.nan, "1", True, None])
def test_log_joint_refuses_a_bad_alpha(alpha):
    # alpha <= 0 gave a NaN log joint.
    y, state = _forward_state()
    with pytest.raises(ValueError, match="alpha must be a"):
        dp_log_joint(y, state, alpha)


def test_log_joint_refuses_bad_y_and_state():
    y, state = _forward_state()
    assert torch.isfinite(dp_log_joint(y, state, 1.0))
    nan_y = y.clone()
    nan_y[1, 0] = math.nan
    with pytest.raises(
        ValueError, match=r"y contains non-finite values \(first at index \(1, 0\)\)"
    ):
        dp_log_joint(nan_y, state, 1.0)  # was a NaN log joint
    # Fewer rows than labels was a cryptic gather error; more was scored on the first N.
    for rows in (y[:4], torch.cat([y, y])):
        with pytest.raises(ValueError, match=r"y must have shape \[6, 2\]"):
            dp_log_joint(rows, state, 1.0)
    with pytest.raises(ValueError, match=r"y must have shape \[6, 2\]"):
        dp_log_joint(y[:, :1], state, 1.0)
    with pytest.raises(TypeError, match="y must be a torch.Tensor"):
        dp_log_joint(y.tolist(), state, 1.0)
    with pytest.raises(TypeError, match="state must be a DPMixtureState"):
        dp_log_joint(y, (state.labels, state.means, state.covariances), 1.0)
    # A component without a point: the model has none.
    empty = DPMixtureState(
        state.labels, torch.cat([state.means, state.means[:1]]),
        torch.cat([state.covariances, state.covariances[:1]]), state.prior,
    )  # fmt: skip
    with pytest.raises(ValueError, match="state: every component of means must hold a point"):
        dp_log_joint(y, empty, 1.0)
    # A label beyond the components was torch.bincount's or gather's error.
    beyond = DPMixtureState(
        state.labels.clone().index_fill_(0, torch.tensor([0]), state.means.shape[0]),
        state.means, state.covariances, state.prior,
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"state.labels must lie in \[0, 1\)"):
        dp_log_joint(y, beyond, 1.0)
    # Σ_k = covariances_k − R not positive definite (here below R): density 0, not an error.
    below = DPMixtureState(
        state.labels, state.means, 0.5 * state.prior.regularization.expand_as(state.covariances),
        state.prior,
    )  # fmt: skip
    assert dp_log_joint(y, below, 1.0) == -math.inf


def test_model_refuses_data_of_another_number_of_points():
    y = torch.zeros(5, 2, dtype=F64)
    with pytest.raises(ValueError, match="num_points=3 but data has 5 rows"):
        dp_mixture_model(prior_2d(), 1.0, 3, data=y)


# --------------------------------------------------------------------------- Geweke test
GEWEKE_PRIOR = NormalInverseWishartPrior(
    mean_loc=torch.zeros(1, dtype=F64),
    mean_covariance=torch.eye(1, dtype=F64),
    df=5.0,  # finite variance of Σ, so that moments of y² have a standard error
    scale=3.0 * torch.eye(1, dtype=F64),  # E[Σ] = 1
    regularization=torch.eye(1, dtype=F64),  # R as large as E[Σ]: the Σ step's MH matters
)
GEWEKE_N, GEWEKE_ALPHA = 3, 1.0
Z_LIMIT = 5.0  # eight test functions, 19-dof batch-means errors: P(false alarm) < 1e-3


def _test_functions(labels, point_means, point_covariances, y):
    """``[B, 8]`` g(θ, y) for 1-D states: ``labels [B, N]``, ``point_means [B, N]`` (μ_{c_i}),
    ``point_covariances [B, N]`` (Σ_{c_i} + R), ``y [B, N]``."""
    num_tables = labels.max(-1).values + 1
    return torch.stack(
        [
            num_tables.to(F64),
            (labels[:, 0] == labels[:, 1]).to(F64),
            point_means[:, 0],
            point_means[:, 0] ** 2,
            point_covariances[:, 0].log(),
            y[:, 0],
            y[:, 0] ** 2,
            y[:, 0] * y[:, 1],
        ],
        -1,
    )


def _forward_statistics(num_draws, seed):
    pyro.set_rng_seed(seed)
    labels, means, covariances, y = dp_mixture_model(
        GEWEKE_PRIOR, GEWEKE_ALPHA, GEWEKE_N, num_draws=num_draws
    )
    point_means = means[..., 0].gather(-1, labels)
    point_covariances = covariances[..., 0, 0].gather(-1, labels)
    return _test_functions(labels, point_means, point_covariances, y[..., 0])


def _chain_statistics(num_steps, seed, sweep):
    g = torch.Generator().manual_seed(seed)
    pyro.set_rng_seed(seed)
    trace = poutine.trace(dp_mixture_model).get_trace(GEWEKE_PRIOR, GEWEKE_ALPHA, GEWEKE_N)
    y, state = trace.nodes["y"]["value"], state_from_trace(trace, GEWEKE_PRIOR)
    rows = []
    for _ in range(num_steps):
        state = sweep(y, state, g)  # θ | y
        point_means = state.means[state.labels]  # [N, 1]
        point_covariances = state.covariances[state.labels]  # [N, 1, 1]
        noise = torch.randn(GEWEKE_N, 1, generator=g, dtype=F64)
        y = point_means + noise * point_covariances[..., 0].sqrt()  # y | θ, the likelihood
        rows.append((state.labels, point_means[:, 0], point_covariances[:, 0, 0], y[:, 0]))
    labels, point_means, point_covariances, ys = (
        torch.stack(column) for column in zip(*rows, strict=True)
    )
    return _test_functions(labels, point_means, point_covariances, ys)


def _geweke_z(forward, chain, batches=20):
    """``[G]`` z-scores of the difference in means: i.i.d. errors for the forward draws,
    batch means for the chain's autocorrelated draws."""
    chain = chain[: chain.shape[0] // batches * batches]
    batch_means = chain.reshape(batches, -1, chain.shape[-1]).mean(1)
    variance = forward.var(0) / forward.shape[0] + batch_means.var(0) / batches
    return (forward.mean(0) - batch_means.mean(0)) / variance.sqrt()


def _sweep(alpha=GEWEKE_ALPHA, exact_covariance=True):
    def sweep(y, state, generator):
        sampler = DPSampler(
            state.prior, alpha, m=2, inner_steps=1, update_prior=False,
            exact_covariance=exact_covariance,
        )  # fmt: skip
        return sampler.sweep(y, state, generator)

    return sweep


@pytest.fixture(scope="module")
def forward_statistics():
    return _forward_statistics(20000, seed=0)


def test_geweke_neal8_sweep_samples_the_model(forward_statistics):
    chain = _chain_statistics(1200, seed=1, sweep=_sweep())
    z = _geweke_z(forward_statistics, chain)
    assert z.abs().max() < Z_LIMIT, f"Geweke z-scores {z.tolist()}"


@pytest.mark.parametrize(
    "broken, detected_by",
    [
        # The label step with α = 3 where the model has α = 1: eq. 5's weights are wrong.
        (_sweep(alpha=3.0), [0, 1]),
        # The Σ step without its Metropolis-Hastings correction for R (the old heuristic).
        (_sweep(exact_covariance=False), [4]),
    ],
    ids=["label-step-wrong-alpha", "covariance-step-without-mh"],
)
def test_geweke_detects_a_broken_conditional(forward_statistics, broken, detected_by):
    chain = _chain_statistics(800, seed=2, sweep=broken)
    z = _geweke_z(forward_statistics, chain)
    assert (z[detected_by].abs() > Z_LIMIT).all(), f"Geweke z-scores {z.tolist()}"
