"""The DP sampler (Algorithm 8, the slice sampler) as a Pyro MCMC kernel: run by
pyro.infer.MCMC, the same chains as the sampler's own sweeps."""

import pytest
import torch
from pyro.infer import MCMC

from dipole_torch import DPSampler, NormalInverseWishartPrior
from dipole_torch.mcmc import DPMixtureKernel
from dipole_torch.pyro_model import canonical_state, dp_log_joint

F64 = torch.float64


def two_groups(seed=0, n=12):
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(2 * n, 2, generator=g, dtype=F64)
    y[:n] -= 3.0
    y[n:] += 3.0
    prior = NormalInverseWishartPrior.from_exploration(
        torch.zeros(2, dtype=F64), 9 * torch.eye(2, dtype=F64)
    )
    return y, prior


@pytest.mark.parametrize("update_prior", [False, True])
def test_mcmc_runs_exactly_the_sweeps_of_the_sampler(update_prior, capsys):
    y, prior = two_groups()
    sampler = DPSampler(prior, alpha=1.0, m=3, update_prior=update_prior)
    kernel = DPMixtureKernel(sampler, generator=torch.Generator().manual_seed(5))
    seen = []
    mcmc = MCMC(
        kernel,
        num_samples=6,
        warmup_steps=4,
        disable_progbar=True,
        hook_fn=lambda kernel, params, stage, i: seen.append(kernel.state.num_components),
    )
    mcmc.run(y)
    direct = sampler.fit(y, num_sweeps=10, generator=torch.Generator().manual_seed(5))
    assert torch.equal(kernel.state.labels, direct.labels)
    assert torch.equal(kernel.state.means, direct.means)
    assert torch.equal(kernel.state.prior.scale, direct.prior.scale)

    samples = mcmc.get_samples()
    assert samples["labels"].shape == (6, 24) and samples["point_means"].shape == (6, 24, 2)
    assert samples["num_components"].shape == (6,) and samples["log_joint"].shape == (6,)
    assert len(seen) == 10 and seen[-1] == samples["num_components"][-1]
    last = canonical_state(direct)
    assert torch.equal(samples["labels"][-1], last.labels.to(F64))
    torch.testing.assert_close(samples["point_means"][-1], last.means[last.labels])
    torch.testing.assert_close(samples["log_joint"][-1], dp_log_joint(y, direct, 1.0))
    assert mcmc.diagnostics()["num_sweeps"] == {"chain 0": 10}
    mcmc.summary()
    assert "num_components" in capsys.readouterr().out


def test_the_chain_separates_two_groups_and_keeps_labels_from_switching():
    y, prior = two_groups(seed=1)
    sampler = DPSampler(prior, m=3, update_prior=False)
    kernel = DPMixtureKernel(sampler, init="sequential", generator=torch.Generator().manual_seed(0))
    mcmc = MCMC(kernel, num_samples=15, warmup_steps=5, disable_progbar=True)
    mcmc.run(y)
    labels = mcmc.get_samples()["labels"]
    assert (labels[:, :12, None] != labels[:, None, 12:]).all()  # the groups never share
    assert (labels[:, 0] == 0).all()  # first-appearance numbering
    assert kernel.logging() == {"K": kernel.state.num_components}


def test_initial_params_start_the_chain_from_given_labels():
    y, prior = two_groups()
    sampler = DPSampler(prior, m=3, update_prior=False)
    kernel = DPMixtureKernel(sampler, generator=torch.Generator().manual_seed(0))
    labels = torch.tensor([4] * 12 + [7] * 12)
    kernel.initial_params = {"labels": labels}
    kernel.setup(0, y)
    assert kernel.state.num_components == 2
    assert kernel.initial_params["labels"].tolist() == [0.0] * 12 + [1.0] * 12
    # MCMC passes them through as well (one chain: [N] labels).
    mcmc = MCMC(kernel, num_samples=1, initial_params={"labels": labels}, disable_progbar=True)
    mcmc.run(y)
    assert mcmc.get_samples()["labels"].shape == (1, 24)


def test_bad_arguments_are_rejected():
    y, prior = two_groups()
    with pytest.raises(ValueError, match="alpha"):
        DPSampler(prior, alpha=0.0)
    with pytest.raises(ValueError, match="init"):
        DPMixtureKernel(DPSampler(prior), init="kmeans")
    with pytest.raises(TypeError, match="prior"):
        DPSampler("not a prior")
    with pytest.raises(TypeError, match="sampler must be a DPSampler"):
        DPMixtureKernel(prior)
    kernel = DPMixtureKernel(DPSampler(prior))
    with pytest.raises(RuntimeError, match="setup"):
        kernel.sample({})
    with pytest.raises(ValueError, match="y must have shape"):
        kernel.setup(0, y[:, :1])
    with pytest.raises(ValueError, match="'labels'"):
        kernel.initial_params = {"means": y}
    kernel.initial_params = {"labels": torch.zeros(5, dtype=torch.long)}
    with pytest.raises(ValueError, match="initial labels must have shape \\[24\\]"):
        kernel.setup(0, y)
    for labels in (torch.tensor([0.0, 0.5, 1.0]), torch.zeros(2, 12, dtype=torch.long)):
        with pytest.raises(ValueError, match="initial labels must be \\[N\\] integers"):
            kernel.initial_params = {"labels": labels}
    fresh = DPMixtureKernel(DPSampler(prior))
    with pytest.raises(ValueError, match="at least one point"):
        fresh.setup(0, y[:0])
    bad = y.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="y contains non-finite"):
        fresh.setup(0, bad)


def test_a_kernel_set_up_again_counts_its_sweeps_from_zero():
    y, prior = two_groups()
    kernel = DPMixtureKernel(DPSampler(prior, m=3), generator=torch.Generator().manual_seed(0))
    kernel.setup(0, y)
    kernel.sample({})
    kernel.sample({})
    assert kernel.diagnostics() == {"num_sweeps": 2}
    kernel.setup(0, y)
    assert kernel.diagnostics() == {"num_sweeps": 0}


@pytest.mark.parametrize("update_prior", [False, True])
def test_slice_kernel_runs_exactly_the_sweeps_of_the_slice_sampler(update_prior):
    y, prior = two_groups(n=40)
    sampler = DPSampler(prior, update_prior=update_prior, method="slice")
    kernel = DPMixtureKernel(sampler, init="sequential", generator=torch.Generator().manual_seed(5))
    mcmc = MCMC(kernel, num_samples=6, warmup_steps=4, disable_progbar=True)
    mcmc.run(y)
    direct = sampler.fit(
        y, num_sweeps=10, generator=torch.Generator().manual_seed(5), init="sequential"
    )
    assert torch.equal(kernel.state.labels, direct.labels)
    assert torch.equal(kernel.state.means, direct.means)
    assert torch.equal(kernel.state.prior.scale, direct.prior.scale)
    assert kernel.chain.means.shape[0] > int(kernel.chain.labels.max())
    labels = mcmc.get_samples()["labels"]
    assert labels.shape == (6, 80) and (labels[:, :40, None] != labels[:, None, 40:]).all()
    with pytest.raises(RuntimeError, match="setup"):
        DPMixtureKernel(DPSampler(prior, method="slice")).sample({})
