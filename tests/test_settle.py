"""``settle``: a warm-started clustering that ends once its partition stops changing."""

import pytest
import torch
from test_dp_mixture import clustering_prior
from test_optimizer import two_optima

from dipole_torch import Dipole, DipoleOptions, DPSampler
from dipole_torch.dp import sampler as dp_sampler

F64 = torch.float64


def clusters(generator, k=3, per=8, d=2):
    centres = 20.0 * torch.arange(k, dtype=F64)[:, None].expand(k, d)
    labels = torch.arange(k).repeat_interleave(per)
    return centres[labels] + torch.randn(k * per, d, generator=generator, dtype=F64), labels


def counting(monkeypatch):
    calls = []
    original = DPSampler.sweep

    def sweep(self, y, chain, generator=None):
        out = original(self, y, chain, generator)
        calls.append(dp_sampler._partition(self.to_state(out).labels))
        return out

    monkeypatch.setattr(DPSampler, "sweep", sweep)
    return calls


def test_partition_ignores_label_numbers():
    a = dp_sampler._partition(torch.tensor([2, 2, 0, 1, 0]))
    assert a == dp_sampler._partition(torch.tensor([5, 5, 3, 4, 3])) == (0, 0, 1, 2, 1)
    assert a != dp_sampler._partition(torch.tensor([2, 0, 0, 1, 0]))


@pytest.mark.parametrize("settle", [1, 2])
def test_a_settled_partition_ends_the_chain(settle, monkeypatch):
    g = torch.Generator().manual_seed(0)
    y, labels = clusters(g)
    sampler = DPSampler(clustering_prior(y))
    start = sampler.fit(y, 20, g)  # a converged chain: the clusters found
    calls = counting(monkeypatch)
    state = sampler.fit(y, 20, g, start, settle=settle)
    # The last `settle` sweeps left the partition as it was; no sweep before them did.
    n = len(calls)
    assert n < 20
    before = [dp_sampler._partition(start.labels), *calls]
    assert all(before[i] == before[i + 1] for i in range(n - settle, n))
    assert not any(
        all(before[j] == before[j + 1] for j in range(i - settle, i)) for i in range(settle, n)
    )
    assert dp_sampler._partition(state.labels) == dp_sampler._partition(labels)


def test_a_changing_partition_runs_every_sweep(monkeypatch):
    # From one component the first sweeps split it: with a count that large nothing settles.
    g = torch.Generator().manual_seed(1)
    y, _ = clusters(g)
    calls = counting(monkeypatch)
    DPSampler(clustering_prior(y)).fit(y, 6, g, settle=6)
    assert len(calls) == 6


def test_no_settle_draws_as_before():
    # settle=None is the plain loop: the same draws as a chain without the argument.
    y, _ = clusters(torch.Generator().manual_seed(2))
    sampler = DPSampler(clustering_prior(y))
    a = sampler.fit(y, 7, torch.Generator().manual_seed(3))
    b = sampler.fit(y, 7, torch.Generator().manual_seed(3), settle=None)
    assert torch.equal(a.labels, b.labels) and torch.equal(a.means, b.means)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "1"])
def test_bad_settle_is_refused(bad):
    with pytest.raises(ValueError, match="settle"):
        DipoleOptions(settle=bad)
    y, _ = clusters(torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="settle"):
        DPSampler(clustering_prior(y)).fit(y, 3, settle=bad)


@pytest.mark.parametrize("seed", range(3))
def test_settled_clusterings_find_and_converge_on_both_optima(seed, monkeypatch):
    # A long run with settle=1 runs fewer sweeps and still ends with a converged policy on
    # each optimum, as the default does (tests/test_optimizer.py).
    calls = counting(monkeypatch)
    opt = Dipole(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), settle=1,
                 generator=torch.Generator().manual_seed(seed))  # fmt: skip
    while opt.trials < 1500:
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
    clusterings = opt.iteration // opt.cluster_every
    assert len(calls) < opt.options.initial_sweeps + opt.options.sweeps * clusterings
    returns = two_optima(opt.policy_means)
    for optimum in (1.0, -1.0):
        near = ((opt.policy_means - optimum).abs().amax(-1) < 1e-2) & (returns > -1e-2)
        assert bool(near.any()), f"no converged policy at {optimum}: {opt.policy_means}"
