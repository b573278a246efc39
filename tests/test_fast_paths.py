"""The shortcuts taken for speed at small sizes give the numbers of the paths they replace."""

import pytest
import torch
from torch.distributions import MultivariateNormal

import dipole_torch.sampling as sampling
from dipole_torch import NormalInverseWishartPrior
from dipole_torch.sampling import draw, draw_gaussian, draw_with_uniforms

F64 = torch.float64


def spd(d, seed):
    a = torch.randn(d, d, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return a @ a.T + d * torch.eye(d, dtype=F64)


def forked(monkeypatch, fn, *args):
    """``fn(*args)`` through draw_with_uniforms' generic path (forked global RNG)."""
    with monkeypatch.context() as patch:
        patch.setattr(sampling, "MultivariateNormal", type(None))
        return fn(*args)


@pytest.mark.parametrize("shape", [(), (3,), (40,), (7, 2)])
@pytest.mark.parametrize("d", [1, 2, 10, 33])
@pytest.mark.parametrize("batch", [None, 4])
@pytest.mark.parametrize("num_uniforms", [0, 5])
def test_normal_draw_equals_forked_global_rng(monkeypatch, shape, d, batch, num_uniforms):
    loc_shape = (d,) if batch is None else (batch, d)
    loc = torch.randn(loc_shape, generator=torch.Generator().manual_seed(d), dtype=F64)
    mvn = MultivariateNormal(loc, covariance_matrix=spd(d, 1))
    fast_gen, slow_gen = torch.Generator().manual_seed(11), torch.Generator().manual_seed(11)
    global_state = torch.random.get_rng_state()
    fast = draw_with_uniforms(mvn, num_uniforms, shape, fast_gen)
    assert torch.equal(torch.random.get_rng_state(), global_state)  # global RNG untouched
    slow = forked(monkeypatch, draw_with_uniforms, mvn, num_uniforms, shape, slow_gen)
    for a, b in zip(fast, slow, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert torch.equal(fast_gen.get_state(), slow_gen.get_state())


def test_normal_draw_float32(monkeypatch):
    mvn = MultivariateNormal(torch.zeros(3), covariance_matrix=torch.eye(3))
    fast = draw(mvn, (20,), torch.Generator().manual_seed(1))
    slow = forked(monkeypatch, draw, mvn, (20,), torch.Generator().manual_seed(1))
    assert fast.dtype == torch.float32 and torch.equal(fast, slow)


def test_prior_memos_follow_their_fields():
    prior = NormalInverseWishartPrior.from_exploration(torch.zeros(3, dtype=F64), spd(3, 2))
    assert torch.equal(prior._mean_tril(), torch.linalg.cholesky(prior.mean_covariance))
    assert prior._mean_tril() is prior._mean_tril()  # memoised
    prior.mean_covariance.mul_(4.0)  # in place: recomputed
    assert torch.equal(prior._mean_tril(), torch.linalg.cholesky(prior.mean_covariance))
    prior.scale = spd(3, 5)  # replaced: recomputed
    expected = torch.cholesky_inverse(torch.linalg.cholesky(prior.scale))
    assert torch.equal(prior._scale_inverse(), 0.5 * (expected + expected.T))


def test_memos_under_inference_mode():
    """Inference tensors have no version counter: the memos step aside, same numbers."""
    from dipole_torch import DPSampler

    y = torch.randn(12, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    y[:, -1] = y[:, -1].abs() + 0.1

    def fit():
        prior = NormalInverseWishartPrior.from_exploration(y.mean(0), torch.cov(y.T))
        g = torch.Generator().manual_seed(1)
        return DPSampler(prior, reward_weighted=True).fit(y, 3, generator=g)

    plain = fit()
    with torch.inference_mode():
        inferred = fit()
    assert torch.equal(plain.labels, inferred.labels)
    assert torch.equal(plain.covariances, inferred.covariances)


@pytest.mark.parametrize("shape", [(), (3,), (40,)])
@pytest.mark.parametrize("d", [1, 2, 10])
@pytest.mark.parametrize("loc_batch", [(), (4,)])
@pytest.mark.parametrize("cov_batch", [(), (4,)])
def test_draw_gaussian_equals_draw_of_the_distribution(monkeypatch, shape, d, loc_batch, cov_batch):
    loc = torch.randn(*loc_batch, d, generator=torch.Generator().manual_seed(d), dtype=F64)
    cov = spd(d, 3).expand(*cov_batch, d, d)
    fast_gen, slow_gen = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    fast = draw_gaussian(loc, cov, shape, fast_gen)
    mvn = MultivariateNormal(loc, covariance_matrix=cov, validate_args=False)
    slow = forked(monkeypatch, draw, mvn, shape, slow_gen)
    assert fast.shape == slow.shape and torch.equal(fast, slow)
    assert torch.equal(fast_gen.get_state(), slow_gen.get_state())
