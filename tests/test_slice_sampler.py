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


def test_prior_update_sees_the_covariances_without_the_regularisation():
    """H's update takes the atoms' covariances less R (as Algorithm 8 passes them).

    With R = 3 I on unit clusters the atoms' covariances less R stay near 1 and H's E[Σ]
    follows them (trace 3.7 here, at most 3.9 over seeds 0–5); handing the update the
    covariances with R included puts the trace at 13 (at least 7 over those seeds).
    """
    y, _, prior = clusters(400, 2)
    prior.regularization = 3.0 * torch.eye(2, dtype=F64)
    g = torch.Generator().manual_seed(0)
    state = DPSampler(prior, method="slice").fit(y, 5, generator=g, init="sequential")
    assert float(state.prior.expected_covariance.trace()) < 6.0


def test_new_sticks_draw_their_atoms_from_the_updated_prior():
    """The atoms of the sticks a sweep adds come from H as updated in that same sweep.

    H starts far too wide (E[Σ] = 100 I) for the 5 tight clusters a start holds; one update
    brings its E[Σ] to a trace of 29 to 47 (seeds 0–4), and the new atoms' covariances have
    a median trace of 22 to 39. Drawing them from the H before the update gives 150 to 180.
    """
    y, _, prior = clusters(200, 2)
    start = DPSampler(prior, update_prior=False).fit(
        y, 2, generator=torch.Generator().manual_seed(1), init="sequential"
    )
    wide = NormalInverseWishartPrior(
        prior.mean_loc, prior.mean_covariance, 8.0, 500.0 * torch.eye(2, dtype=F64),
        prior.regularization,
    )  # fmt: skip
    start.prior = wide
    sampler = DPSampler(wide, alpha=5.0, method="slice")
    chain = sampler.sweep(y, SliceChain.from_state(start), torch.Generator().manual_seed(0))
    fresh = chain.covariances[start.num_components :]  # sticks beyond the start's atoms
    assert fresh.shape[0] >= 8
    assert float(chain.prior.expected_covariance.trace()) < 100.0
    assert float(fresh.diagonal(dim1=-2, dim2=-1).sum(-1).median()) < 90.0
