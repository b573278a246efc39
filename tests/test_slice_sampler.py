"""The slice sampler: clusters recovered, chain bookkeeping, bad input, CUDA.
(Its exactness is checked against the enumerated posterior in tests/test_dp_exact.py.)"""

import pytest
import torch
from sklearn.metrics import adjusted_rand_score

from dipole_torch import DPMixtureState, DPSampler, NormalInverseWishartPrior
from dipole_torch.dp import SliceChain

F64 = torch.float64


def clusters(n: int, d: int, seed: int = 0, device: str = "cpu"):
    """``[n, D]`` points of 4 unit Gaussians 8·N(0, I) apart, their true labels, and H."""
    g = torch.Generator().manual_seed(seed)
    centres = 8.0 * torch.randn(4, d, generator=g, dtype=F64)
    labels = torch.arange(n) % 4
    y = (centres[labels] + torch.randn(n, d, generator=g, dtype=F64)).to(device)
    prior = NormalInverseWishartPrior(
        mean_loc=y.mean(0),
        mean_covariance=torch.cov(y.T),
        df=d + 6.0,
        scale=10.0 * torch.eye(d, dtype=F64, device=device),
        regularization=1e-3 * torch.eye(d, dtype=F64, device=device),
    )
    return y, labels, prior


@pytest.mark.parametrize("d", [2, 5])
def test_recovers_separated_clusters(d):
    y, truth, prior = clusters(400, d)
    g = torch.Generator().manual_seed(0)
    state = DPSampler(prior, method="slice").fit(y, 10, generator=g, init="sequential")
    assert isinstance(state, DPMixtureState) and state.num_components == 4
    assert adjusted_rand_score(truth.numpy(), state.labels.numpy()) > 0.99
    assert torch.equal(state.labels.unique(), torch.arange(4))  # contiguous
    # The fitted components sit on the clusters.
    for c in range(4):
        points = y[state.labels == c]
        assert (state.means[c] - points.mean(0)).norm() < 0.5


def test_fit_runs_the_sweeps_of_the_slice_sampler_keeping_the_chain():
    y, truth, prior = clusters(400, 2, seed=1)
    sampler = DPSampler(prior, update_prior=False, method="slice")
    fit = sampler.fit(y, 5, generator=torch.Generator().manual_seed(0), init="sequential")
    g = torch.Generator().manual_seed(0)
    chain = sampler.to_chain(sampler.start(y, "sequential", g))
    for _ in range(5):
        chain = sampler.sweep(y, chain, g)
    direct = sampler.to_state(chain)
    assert torch.equal(fit.labels, direct.labels)
    assert adjusted_rand_score(truth.numpy(), fit.labels.numpy()) > 0.95  # tail points aside


def test_chain_keeps_stick_labels_and_is_reproducible():
    y, _, prior = clusters(200, 2)
    g = torch.Generator().manual_seed(1)
    start = DPSampler(prior).fit(y, 1, generator=g, init="sequential")
    sampler = DPSampler(prior, update_prior=False, method="slice")
    runs = []
    for _ in range(2):
        chain = SliceChain.from_state(start)
        g = torch.Generator().manual_seed(2)
        for _ in range(5):
            chain = sampler.sweep(y, chain, g)
        runs.append(chain)
    assert torch.equal(runs[0].labels, runs[1].labels)
    chain = runs[0]
    # Sticks enough for every label, an atom per stick; state() drops the empty ones.
    assert chain.means.shape[0] > int(chain.labels.max())
    assert chain.covariances.shape == (chain.means.shape[0], 2, 2)
    state = chain.state()
    occupied = chain.labels.unique()
    assert state.num_components == occupied.numel()
    torch.testing.assert_close(state.means, chain.means[occupied])
    assert adjusted_rand_score(chain.labels.numpy(), state.labels.numpy()) == 1.0


def test_prior_update_moves_h():
    y, _, prior = clusters(200, 2)
    g = torch.Generator().manual_seed(3)
    state = DPSampler(prior, method="slice").fit(y, 3, generator=g, init="sequential")
    assert not torch.equal(state.prior.mean_loc, prior.mean_loc)
    fixed = DPSampler(prior, update_prior=False, method="slice").fit(
        y, 3, generator=g, init="sequential"
    )
    assert fixed.prior is prior


def test_bad_input_is_refused():
    y, _, prior = clusters(40, 2)
    with pytest.raises(ValueError, match="method must be"):
        DPSampler(prior, method="gibbs")
    with pytest.raises(ValueError, match="reward_weighted must be False and auxiliary 'fresh'"):
        DPSampler(prior, method="slice", reward_weighted=True)
    with pytest.raises(ValueError, match="reward_weighted must be False and auxiliary 'fresh'"):
        DPSampler(prior, method="slice", auxiliary="reuse")
    chain = SliceChain.from_state(DPMixtureState.single_component(y, prior))
    with pytest.raises(ValueError, match="alpha"):
        DPSampler(prior, alpha=0.0, method="slice")
    with pytest.raises(ValueError, match="sticks"):  # rather than a loop without end
        DPSampler(prior, alpha=1e9, method="slice").sweep(
            y, chain, torch.Generator().manual_seed(0)
        )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_runs_on_cuda_with_a_cpu_generator():
    y, truth, prior = clusters(400, 3, device="cuda")
    g = torch.Generator().manual_seed(0)
    state = DPSampler(prior, method="slice").fit(y, 5, generator=g, init="sequential")
    assert state.labels.device.type == "cuda"
    assert adjusted_rand_score(truth.numpy(), state.labels.cpu().numpy()) > 0.99
