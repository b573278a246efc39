"""Geweke (2004) joint-distribution tests of the whole sweep as DIPOLE runs it: H redrawn
after every sweep (``update_prior=True``), with Algorithm 8's fresh auxiliary draws and
with Favaro & Teh's re-used ones.

The model with H's hyperpriors (those ``NormalInverseWishartPrior.updated`` is the Gibbs
step of, anchored on an initial prior (μ0_i, Σ0_i, ν0, Ψ0_i)), in 1-D:

* μ0 ~ N(μ0_i, Σ0_i), Σ0 ~ IW(D + 3, 2 Σ0_i), Ψ0 ~ Wishart(D + 1, Ψ0_i / (D + 1));
* labels from the Chinese restaurant process (α); per table μ_k ~ N(μ0, Σ0),
  Σ_k ~ IW(ν0, Ψ0) (1-D: an inverse gamma);
* y_i ~ N(μ_{c_i}, Σ_{c_i} + R).

Forward draws of (H, θ, y) against the chain that alternates one sweep (θ, H | y) with
y | θ: both sample the joint when the sweep leaves p(θ, H | y) invariant. The unweighted
sampler (eq. 5): eq. 6's reward weighting has no generative model of this form.
"""

import pytest
import torch
from test_pyro_model import _geweke_z
from test_pyro_model import _test_functions as model_test_functions

from dipole_torch import DPMixtureState, DPSampler, NormalInverseWishartPrior

F64 = torch.float64
N, ALPHA, REG = 3, 1.0, 0.5
INITIAL = NormalInverseWishartPrior(
    mean_loc=torch.zeros(1, dtype=F64),
    mean_covariance=torch.eye(1, dtype=F64),
    df=5.0,  # finite variance of Σ
    scale=3.0 * torch.eye(1, dtype=F64),  # E[Σ] = 1
    regularization=REG * torch.eye(1, dtype=F64),  # R: the Σ step's MH matters
)
Z_LIMIT = 5.0  # eleven test functions, 19-dof batch-means errors: P(false alarm) < 1e-3


def _gamma(shape, rate, g):
    return torch._standard_gamma(torch.as_tensor(shape, dtype=F64), generator=g) / rate


def forward(num_draws, seed):
    """``[num_draws, 11]`` test functions of forward draws of the model."""
    g = torch.Generator().manual_seed(seed)
    b = num_draws
    s0 = float(INITIAL.mean_covariance)
    psi0 = float(INITIAL.scale)
    nu0 = INITIAL.df
    # Hyperparameters. 1-D: IW(ν, ψ) = IG(ν/2, ψ/2); Wishart(ν, v) = v·χ²(ν) = Gamma(ν/2, 1/(2v)).
    mu_h = s0**0.5 * torch.randn(b, generator=g, dtype=F64)
    sigma_h = 1.0 / _gamma(torch.full((b,), 4.0 / 2), 2.0 * s0 / 2, g)
    psi_h = _gamma(torch.full((b,), 2.0 / 2), 1.0 / (2.0 * psi0 / 2.0), g)
    # CRP labels of N points, in order of first appearance.
    labels = torch.zeros(b, N, dtype=torch.long)
    u = torch.rand(b, N, generator=g, dtype=F64)
    for i in range(1, N):
        tables = labels[:, :i].max(1).values + 1
        counts = torch.stack([(labels[:, :i] == t).sum(1) for t in range(N)], 1).to(F64)
        weights = torch.where(torch.arange(N) == tables[:, None], ALPHA, counts)
        cdf = (weights / (i + ALPHA)).cumsum(1)
        draw = u[:, i : i + 1].contiguous()
        labels[:, i] = torch.searchsorted(cdf, draw).squeeze(1).clamp(max=N - 1)
    means = mu_h[:, None] + sigma_h[:, None].sqrt() * torch.randn(b, N, generator=g, dtype=F64)
    sigmas = 1.0 / _gamma(torch.full((b, N), nu0 / 2), psi_h[:, None] / 2, g)
    point_means, point_covs = means.gather(1, labels), sigmas.gather(1, labels) + REG
    y = point_means + point_covs.sqrt() * torch.randn(b, N, generator=g, dtype=F64)
    return _test_functions(labels, point_means, point_covs, y, mu_h, sigma_h, psi_h)


def _test_functions(labels, point_means, point_covs, y, mu_h, sigma_h, psi_h):
    """``[B, 11]`` the Pyro model test's eight functions of (θ, y), then μ0, log Σ0, log Ψ0."""
    hyper = torch.stack([mu_h, sigma_h.log(), psi_h.log()], -1)
    return torch.cat((model_test_functions(labels, point_means, point_covs, y), hyper), -1)


def chain(num_steps, seed, auxiliary):
    """``[num_steps, 11]`` test functions along the successive-conditional simulator."""
    g = torch.Generator().manual_seed(seed)
    sampler = DPSampler(INITIAL, ALPHA, m=2, inner_steps=1, auxiliary=auxiliary)
    y = torch.randn(N, 1, generator=g, dtype=F64)
    state = DPMixtureState.single_component(y, INITIAL)
    rows = []
    for _ in range(num_steps):
        state = sampler.sweep(y, state, g)  # θ, H | y
        point_means = state.means[state.labels]
        point_covs = state.covariances[state.labels][..., 0]
        y = point_means + point_covs.sqrt() * torch.randn(N, 1, generator=g, dtype=F64)
        prior = state.prior
        rows.append(
            (
                state.labels,
                point_means[:, 0],
                point_covs[:, 0],
                y[:, 0],
                prior.mean_loc[0],
                prior.mean_covariance[0, 0],
                prior.scale[0, 0],
            )
        )
    columns = [torch.stack(column) for column in zip(*rows, strict=True)]
    return _test_functions(*columns)[50:]  # a burn-in from the arbitrary start


@pytest.fixture(scope="module")
def forward_draws():
    return forward(40000, seed=0)


@pytest.mark.parametrize("auxiliary", ["fresh", "reuse"])
def test_geweke_sweep_with_the_prior_update_samples_the_model(forward_draws, auxiliary):
    z = _geweke_z(forward_draws, chain(2050, seed=1, auxiliary=auxiliary))
    assert z.abs().max() < Z_LIMIT, f"Geweke z-scores {z.tolist()}"


def test_geweke_detects_a_broken_prior_update(forward_draws, monkeypatch):
    # μ0's draw shifted by +0.2 (a wrong conditional of H): the chain's μ0, and the component
    # means and points it pulls along, move away from the model's.
    original = NormalInverseWishartPrior.updated

    def broken(self, means, covariances, initial, generator=None):
        new = original(self, means, covariances, initial, generator)
        new.mean_loc = new.mean_loc + 0.2
        return new

    monkeypatch.setattr(NormalInverseWishartPrior, "updated", broken)
    z = _geweke_z(forward_draws, chain(2050, seed=1, auxiliary="reuse"))
    assert z[8].abs() > Z_LIMIT, f"Geweke z-scores {z.tolist()}"
