import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from dipole_torch import GaussianMixture


def random_mixture(batch=(), k=3, d=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    weights = torch.rand(*batch, k, generator=g, dtype=torch.float64) + 0.1
    means = 2 * torch.randn(*batch, k, d, generator=g, dtype=torch.float64)
    a = torch.randn(*batch, k, d, d, generator=g, dtype=torch.float64)
    covs = a @ a.transpose(-1, -2) + 0.5 * torch.eye(d, dtype=torch.float64)
    return GaussianMixture(weights, means, covs)


def scipy_log_prob(gm, x):
    w = gm.weights.numpy()
    dens = sum(
        w[k] * multivariate_normal(gm.means[k].numpy(), gm.covariances[k].numpy()).pdf(x)
        for k in range(gm.num_components)
    )
    return np.log(dens)


def test_log_prob_matches_scipy_and_torch_mixture():
    gm = random_mixture()
    x = torch.randn(7, 3, dtype=torch.float64)
    expected = scipy_log_prob(gm, x.numpy())
    np.testing.assert_allclose(gm.log_prob(x).numpy(), expected, rtol=1e-10)
    np.testing.assert_allclose(gm.to_distribution().log_prob(x).numpy(), expected, rtol=1e-10)


def test_batch_shapes_follow_torch_distributions():
    gm = random_mixture(batch=(4, 2))
    assert gm.batch_shape == (4, 2) and gm.event_shape == (3,)
    assert gm.log_prob(torch.zeros(5, 4, 2, 3, dtype=torch.float64)).shape == (5, 4, 2)
    sample = gm.sample((6,), generator=torch.Generator().manual_seed(0))
    assert sample.shape == (6, 4, 2, 3)
    assert gm.to_distribution().batch_shape == (4, 2)
    # Broadcasting batch shapes of the parameters, like torch.distributions.
    broad = GaussianMixture(gm.weights[0, 0], gm.means, gm.covariances[0, 0])
    assert broad.batch_shape == (4, 2)


def test_sample_is_reproducible_and_has_the_right_moments():
    gm = random_mixture(seed=3)
    a = gm.sample(20000, generator=torch.Generator().manual_seed(1))
    b = gm.sample(20000, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    torch.testing.assert_close(a.mean(0), gm.mean, atol=0.08, rtol=0)
    torch.testing.assert_close(torch.cov(a.T), gm.covariance_matrix, atol=0.3, rtol=0.05)


def test_condition_matches_hand_derived_gmr():
    # Two 2-D components; condition on x0 = 1 and predict x1 by hand.
    weights = torch.tensor([0.3, 0.7], dtype=torch.float64)
    means = torch.tensor([[0.0, 1.0], [2.0, -1.0]], dtype=torch.float64)
    covs = torch.tensor([[[1.0, 0.5], [0.5, 2.0]], [[2.0, -0.4], [-0.4, 1.0]]], dtype=torch.float64)
    gm = GaussianMixture(weights, means, covs)
    x0 = 1.0
    lik = [multivariate_normal(means[k, 0].item(), covs[k, 0, 0].item()).pdf(x0) for k in range(2)]
    h = np.array([0.3 * lik[0], 0.7 * lik[1]])
    h /= h.sum()
    mu = [1.0 + 0.5 / 1.0 * (x0 - 0.0), -1.0 + (-0.4) / 2.0 * (x0 - 2.0)]
    var = [2.0 - 0.5**2 / 1.0, 1.0 - 0.4**2 / 2.0]
    cond = gm.condition([0], torch.tensor([x0], dtype=torch.float64))
    np.testing.assert_allclose(cond.weights.numpy(), h, rtol=1e-10)
    np.testing.assert_allclose(cond.means[:, 0].numpy(), mu, rtol=1e-10)
    np.testing.assert_allclose(cond.covariances[:, 0, 0].numpy(), var, rtol=1e-10)
    np.testing.assert_allclose(cond.mean.item(), float(h @ np.array(mu)), rtol=1e-10)


def test_condition_equals_joint_over_marginal():
    # p(x_b | x_a) = p(x_a, x_b) / p(x_a) for any mixture.
    gm = random_mixture(k=4, d=4, seed=5)
    y = torch.randn(9, 4, dtype=torch.float64)
    dims = [1, 3]
    cond = gm.condition(dims, y[:, dims])
    lhs = cond.log_prob(y[:, [0, 2]])
    rhs = gm.log_prob(y) - gm.marginal(dims).log_prob(y[:, dims])
    torch.testing.assert_close(lhs, rhs)
    assert cond.batch_shape == (9,)


def test_state_dict_round_trip():
    gm = random_mixture(seed=2)
    restored = GaussianMixture.from_state_dict(gm.state_dict())
    x = torch.randn(5, 3, dtype=torch.float64)
    assert torch.equal(restored.log_prob(x), gm.log_prob(x))
    other = random_mixture(seed=9)
    other.load_state_dict(gm.state_dict())
    assert torch.equal(other.log_prob(x), gm.log_prob(x))


@pytest.mark.parametrize(
    "weights, means, covs, message",
    [
        (torch.ones(2), torch.zeros(3, 2), torch.eye(2).expand(2, 2, 2), "means must have shape"),
        (torch.ones(2), torch.zeros(2, 2), torch.eye(3).expand(2, 3, 3), "covariances must"),
        (-torch.ones(2), torch.zeros(2, 2), torch.eye(2).expand(2, 2, 2), "non-negative"),
        (torch.ones(2), torch.zeros(2, 2), -torch.eye(2).expand(2, 2, 2), "positive definite"),
        (
            torch.ones(2),
            torch.full((2, 2), float("nan")),
            torch.eye(2).expand(2, 2, 2),
            "non-finite",
        ),
    ],
)
def test_bad_parameters_are_rejected(weights, means, covs, message):
    with pytest.raises(ValueError, match=message):
        GaussianMixture(weights, means, covs)


def test_bad_condition_arguments_are_rejected():
    gm = random_mixture()
    with pytest.raises(ValueError, match="distinct integers"):
        gm.condition([0, 0], torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="len\\(dims\\)"):
        gm.condition([0], torch.zeros(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="every dimension"):
        gm.condition([0, 1, 2], torch.zeros(3, dtype=torch.float64))


# --------------------------------------------------------------------------- as a Distribution
def test_is_a_torch_distribution_with_constraints_and_shapes():
    gm = random_mixture(batch=(2,), k=3, d=2)
    assert isinstance(gm, torch.distributions.Distribution)
    assert gm.support is torch.distributions.constraints.real_vector
    for name, constraint in gm.arg_constraints.items():
        assert bool(constraint.check(getattr(gm, name)).all()), name
    assert gm.batch_shape == (2,) and gm.event_shape == (2,)
    batch, event = GaussianMixture.infer_shapes(
        weights=(5, 3), means=(1, 3, 2), covariances=(3, 2, 2)
    )
    assert batch == (5,) and event == (2,)
    assert not gm.has_rsample
    with pytest.raises(NotImplementedError):
        gm.rsample()


def test_expand_broadcasts_without_changing_the_density():
    gm = random_mixture(k=2, d=3, seed=4)
    _ = gm.scale_tril  # a cached factor must be expanded too
    big = gm.expand((4, 5))
    assert big.batch_shape == (4, 5) and big.event_shape == (3,)
    x = torch.randn(4, 5, 3, dtype=torch.float64)
    torch.testing.assert_close(big.log_prob(x), gm.log_prob(x))
    assert big.sample((2,), generator=torch.Generator().manual_seed(0)).shape == (2, 4, 5, 3)
    torch.testing.assert_close(big.mean, gm.mean.expand(4, 5, 3))


def test_variance_is_the_diagonal_of_the_mixture_covariance():
    gm = random_mixture(k=3, d=2, seed=6)
    x = gm.sample((40000,), generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(gm.variance, gm.covariance_matrix.diagonal(), rtol=0, atol=0)
    torch.testing.assert_close(x.var(0), gm.variance, rtol=0.05, atol=0)
    torch.testing.assert_close(gm.stddev, gm.variance.sqrt())


def test_dtype_follows_the_parameters():
    gm32 = random_mixture(seed=1).to(torch.float32)
    assert gm32.dtype == torch.float32
    assert gm32.sample((3,), generator=torch.Generator().manual_seed(0)).dtype == torch.float32
    assert gm32.log_prob(torch.zeros(3, dtype=torch.float32)).dtype == torch.float32
    assert gm32.condition([0], torch.zeros(1)).dtype == torch.float32
    # Mixed parameters promote, as torch.distributions' broadcast_all does.
    mixed = GaussianMixture(
        torch.ones(2, dtype=torch.float64), torch.zeros(2, 1), torch.ones(2, 1, 1)
    )
    assert mixed.dtype == mixed.weights.dtype == mixed.covariances.dtype == torch.float64
    counts = GaussianMixture(torch.tensor([1, 3]), torch.zeros(2, 1), torch.ones(2, 1, 1))
    assert counts.dtype == torch.float32 and counts.weights.tolist() == [0.25, 0.75]


def test_value_validation_follows_validate_args():
    gm = random_mixture(batch=(2,), d=3)
    with pytest.raises(ValueError, match="event dim 3"):
        gm.log_prob(torch.zeros(2, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="broadcastable"):
        gm.log_prob(torch.zeros(3, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="support"):
        gm.log_prob(torch.full((2, 3), float("nan"), dtype=torch.float64))
    lax = GaussianMixture(gm.weights, gm.means, gm.covariances, validate_args=False)
    assert torch.isnan(lax.log_prob(torch.full((2, 3), float("nan"), dtype=torch.float64))).all()
    # Derived mixtures keep the parent's setting.
    assert not lax.marginal([0])._validate_args and gm.marginal([0])._validate_args
    # None follows torch.distributions' global default.
    torch.distributions.Distribution.set_default_validate_args(False)
    try:
        quiet = GaussianMixture(torch.ones(1), torch.zeros(1, 1), -torch.ones(1, 1, 1))
        assert not quiet._validate_args
    finally:
        torch.distributions.Distribution.set_default_validate_args(True)


def test_usable_in_pyro_sample_and_under_a_plate():
    import pyro
    import pyro.poutine as poutine

    gm = random_mixture(k=3, d=2, seed=7)
    observed = torch.randn(6, 2, dtype=torch.float64)

    def model():
        theta = pyro.sample("theta", gm)
        with pyro.plate("data", 6):
            pyro.sample("x", gm, obs=observed)
        return theta

    pyro.set_rng_seed(0)
    trace = poutine.trace(model).get_trace()
    theta = trace.nodes["theta"]["value"]
    assert theta.shape == (2,) and theta.dtype == torch.float64
    assert trace.nodes["x"]["fn"].batch_shape == (6,)  # expanded by the plate
    expected = gm.log_prob(theta) + gm.log_prob(observed).sum()
    torch.testing.assert_close(trace.log_prob_sum(), expected)
    pyro.set_rng_seed(0)
    assert torch.equal(poutine.trace(model).get_trace().nodes["theta"]["value"], theta)


def test_kl_divergence_is_registered_for_single_components():
    from torch.distributions import MultivariateNormal, kl_divergence

    p = random_mixture(batch=(3,), k=1, d=2, seed=1)
    q = random_mixture(k=1, d=2, seed=2)
    p_normal = MultivariateNormal(p.means[:, 0], p.covariances[:, 0])
    q_normal = MultivariateNormal(q.means[0], q.covariances[0])
    expected = kl_divergence(p_normal, q_normal)
    assert expected.shape == (3,) and (expected > 0).all()
    torch.testing.assert_close(kl_divergence(p, q), expected)
    torch.testing.assert_close(kl_divergence(p, q_normal), expected)
    torch.testing.assert_close(kl_divergence(p_normal, q), expected)
    assert torch.allclose(kl_divergence(q, q), torch.zeros((), dtype=q.dtype), atol=1e-12)
    with pytest.raises(NotImplementedError, match="no closed form"):
        kl_divergence(random_mixture(k=2, d=2), q)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("validate", [True, False])
def test_half_precision_parameters_are_refused_naming_the_dtype(dtype, validate):
    """torch's Cholesky has no float16/bfloat16 kernel: refused at construction (with or
    without validation, and by ``to``), not as a NotImplementedError from inside log_prob."""
    with pytest.raises(TypeError, match=f"float32 or float64.*got {dtype}"):
        GaussianMixture(
            torch.ones(2, dtype=dtype),
            torch.zeros(2, 3, dtype=dtype),
            torch.eye(3, dtype=dtype).expand(2, 3, 3),
            validate_args=validate,
        )
    with pytest.raises(TypeError, match=f"got {dtype}"):
        random_mixture(seed=1).to(dtype)
