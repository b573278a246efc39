"""The slice sampler: clusters recovered, chain bookkeeping, bad input, CUDA.
(Its exactness is checked against the enumerated posterior in tests/test_dp_exact.py.)"""

import pytest
import torch
from sklearn.metrics import adjusted_rand_score

from dipole_torch import DPMixture, DPMixtureState, NormalInverseWishartPrior, fit_dp_mixture
from dipole_torch.slice_sampler import SliceChain, slice_sweep

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
    state = fit_dp_mixture(y, prior, 10, generator=g, init="sequential", sampler="slice")
    assert isinstance(state, DPMixtureState) and state.num_components == 4
    assert adjusted_rand_score(truth.numpy(), state.labels.numpy()) > 0.99
    assert torch.equal(state.labels.unique(), torch.arange(4))  # contiguous
    # The fitted components sit on the clusters.
    for c in range(4):
        points = y[state.labels == c]
        assert (state.means[c] - points.mean(0)).norm() < 0.5


def test_dp_mixture_wrapper_takes_the_sampler():
    y, truth, prior = clusters(400, 2, seed=1)
    fit = DPMixture(prior, sampler="slice").fit(
        y, 5, generator=torch.Generator().manual_seed(0), init="sequential"
    )
    direct = fit_dp_mixture(
        y,
        prior,
        5,
        generator=torch.Generator().manual_seed(0),
        init="sequential",
        update_prior=False,
        sampler="slice",
    )
    assert torch.equal(fit.labels, direct.labels)
    assert adjusted_rand_score(truth.numpy(), fit.labels.numpy()) > 0.95  # tail points aside


def test_chain_keeps_stick_labels_and_is_reproducible():
    y, _, prior = clusters(200, 2)
    g = torch.Generator().manual_seed(1)
    start = fit_dp_mixture(y, prior, 1, generator=g, init="sequential")
    runs = []
    for _ in range(2):
        chain = SliceChain.from_state(start)
        g = torch.Generator().manual_seed(2)
        for _ in range(5):
            chain = slice_sweep(y, chain, 1.0, g, update_prior=False)
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
    state = fit_dp_mixture(y, prior, 3, generator=g, init="sequential", sampler="slice")
    assert not torch.equal(state.prior.mean_loc, prior.mean_loc)
    fixed = fit_dp_mixture(
        y, prior, 3, generator=g, init="sequential", sampler="slice", update_prior=False
    )
    assert fixed.prior is prior


def test_bad_input_is_refused():
    y, _, prior = clusters(40, 2)
    with pytest.raises(ValueError, match="sampler must be"):
        fit_dp_mixture(y, prior, 1, sampler="gibbs")
    with pytest.raises(ValueError, match="reward_weighted and reuse_auxiliary"):
        fit_dp_mixture(y, prior, 1, sampler="slice", reward_weighted=True)
    with pytest.raises(ValueError, match="reward_weighted and reuse_auxiliary"):
        fit_dp_mixture(y, prior, 1, sampler="slice", reuse_auxiliary=True)
    chain = SliceChain.from_state(DPMixtureState.single_component(y, prior))
    with pytest.raises(ValueError, match="alpha"):
        slice_sweep(y, chain, alpha=0.0)
    with pytest.raises(ValueError, match="sticks"):  # rather than a loop without end
        slice_sweep(y, chain, alpha=1e9, generator=torch.Generator().manual_seed(0))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_runs_on_cuda_with_a_cpu_generator():
    y, truth, prior = clusters(400, 3, device="cuda")
    g = torch.Generator().manual_seed(0)
    state = fit_dp_mixture(y, prior, 5, generator=g, init="sequential", sampler="slice")
    assert state.labels.device.type == "cuda"
    assert adjusted_rand_score(truth.numpy(), state.labels.cpu().numpy()) > 0.99
