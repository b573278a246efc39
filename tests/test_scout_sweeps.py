"""``scout_sweeps``: a clustering that sees scouts alone runs that many Gibbs sweeps."""

import pytest
import torch
from test_optimizer import two_optima

from dipole_torch import Dipole, DipoleOptions, DPSampler
from dipole_torch.mechanisms.matching import OverlapMatching

F64 = torch.float64


def traced_run(monkeypatch, trials, **options):
    """A 2-D run on two optima; ``[(scouts alone, sweeps asked, sweeps run)]`` for each
    warm-started clustering."""
    clusterings, pending, sweeps_run = [], [], []
    warm_start, fit, sweep = OverlapMatching.warm_start, Dipole._fit, DPSampler.sweep

    def traced_warm_start(self, search, y, rows):
        pending.append(not bool((search.archive.owner[rows] >= 0).any()))
        return warm_start(self, search, y, rows)

    def traced_fit(self, y, sweeps, start=None):
        sweeps_run.clear()
        try:
            return fit(self, y, sweeps, start)
        finally:
            if start is not None:
                clusterings.append((pending.pop(), sweeps, len(sweeps_run)))

    def counted_sweep(self, y, chain, generator=None):
        sweeps_run.append(1)
        return sweep(self, y, chain, generator)

    monkeypatch.setattr(OverlapMatching, "warm_start", traced_warm_start)
    monkeypatch.setattr(Dipole, "_fit", traced_fit)
    monkeypatch.setattr(DPSampler, "sweep", counted_sweep)
    opt = Dipole(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                 generator=torch.Generator().manual_seed(0), **options)  # fmt: skip
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
    return opt, clusterings


def test_a_clustering_of_scouts_alone_runs_scout_sweeps(monkeypatch):
    opt, clusterings = traced_run(monkeypatch, 1500)
    scouts = [c for c in clusterings if c[0]]
    others = [c for c in clusterings if not c[0]]
    # Every policy retires on its optimum long before 1500 trials: restarts cluster scouts.
    assert len(scouts) >= 10 and others
    assert all(asked == 1 and run == 1 for _, asked, run in scouts)
    assert all(asked == opt.options.sweeps for _, asked, _ in others)
    # Both optima are still found and converged on.
    returns = two_optima(opt.policy_means)
    for optimum in (1.0, -1.0):
        near = ((opt.policy_means - optimum).abs().amax(-1) < 1e-2) & (returns > -1e-2)
        assert bool(near.any()), f"no converged policy at {optimum}: {opt.policy_means}"


def test_without_scout_sweeps_scouts_are_clustered_as_any_warm_start(monkeypatch):
    opt, clusterings = traced_run(monkeypatch, 1500, scout_sweeps=None)
    scouts = [c for c in clusterings if c[0]]
    assert len(scouts) >= 10
    assert all(asked == opt.options.sweeps for _, asked, _ in scouts)
    # A partition of fresh scouts seldom settles: most of these run more than one sweep.
    assert sum(run > 1 for _, _, run in scouts) > len(scouts) // 2


def test_scout_sweeps_option():
    assert DipoleOptions().scout_sweeps == 1
    assert DipoleOptions.paper().scout_sweeps is None
    assert DipoleOptions(scout_sweeps=3).scout_sweeps == 3


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "1"])
def test_bad_scout_sweeps_are_refused(bad):
    with pytest.raises(ValueError, match="scout_sweeps"):
        DipoleOptions(scout_sweeps=bad)
