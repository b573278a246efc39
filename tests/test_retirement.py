"""Retirement, merging and restarts (dipole_torch.mechanisms.retirement): a policy whose
samples straddle two hills restarts from its best one."""

import torch
from test_optimizer import started_dipole, two_optima

from dipole_torch import Dipole

F64 = torch.float64


def restart(opt, in_valley):
    """The straddler restart, with ``in_valley [K]`` as the told batch would have set it."""
    opt.retirement._in_valley = tuple(in_valley.tolist())
    opt.retirement.restart_straddlers(opt)


def test_a_policy_whose_samples_straddle_two_hills_restarts_from_its_best():
    # Kept samples on both optima of two_optima, the mean between them (in the valley) and
    # a shrunken exploration: such a policy would retire in the valley. It restarts from
    # its best sample, keeping that sample only, with Σ_start's shape at its samples'
    # spread.
    opt = started_dipole(2, two_optima)
    thetas = torch.tensor([[1.0, 1.0], [1.01, 1.0], [-1.0, -0.98], [-1.02, -1.0]], dtype=F64)
    opt.archive.replace(thetas, two_optima(thetas), torch.zeros(4, dtype=torch.long))
    opt.policy_set.reset(torch.zeros(1, 2, dtype=F64), 1e-6 * torch.eye(2, dtype=F64)[None])
    means, covs = opt.policy_means.clone(), opt.policy_covariances.clone()
    restart(opt, in_valley=torch.zeros(1, dtype=torch.bool))  # latest sample: a tie
    assert torch.equal(opt.policy_means, means) and torch.equal(opt.policy_covariances, covs)
    restart(opt, in_valley=torch.ones(1, dtype=torch.bool))  # latest sample: worse
    assert torch.equal(opt.policy_means[0], thetas[0])
    assert float(opt.policy_covariances[0, 0, 0]) > 0.1
    assert torch.equal(opt.thetas, thetas[:1])


def test_a_straddler_restart_writes_into_no_tensor_a_snapshot_holds():
    # A tell's snapshot (PolicySearch._snapshot) holds the optimizer's tensors themselves:
    # the restart must replace them, not write into them.
    opt = started_dipole(2, two_optima)
    thetas = torch.tensor([[1.0, 1.0], [1.01, 1.0], [-1.0, -0.98], [-1.02, -1.0]], dtype=F64)
    opt.archive.replace(thetas, two_optima(thetas), torch.zeros(4, dtype=torch.long))
    opt.policy_set.reset(torch.zeros(1, 2, dtype=F64), 1e-6 * torch.eye(2, dtype=F64)[None])
    snapshot = opt._snapshot()
    copies = opt.state_dict()
    restart(opt, in_valley=torch.ones(1, dtype=torch.bool))
    assert torch.equal(opt.policy_means[0], thetas[0])  # it did restart
    for key, value in snapshot.items():
        if isinstance(value, torch.Tensor) and key != "generator":
            assert torch.equal(value, copies[key]), key


# ---------------------------------------------------------------- retirement by spread
def kept(opt, spread: float, relative_std: float, samples: int = 5):
    """One policy at 0 with ``samples`` kept returns 0 … ``spread`` (every return told
    spans 0 … 1) and an exploration of ``relative_std`` times Σ_start's (= I)."""
    thetas = torch.zeros(samples, 2, dtype=F64)
    returns = torch.linspace(0.0, spread, samples, dtype=F64)
    opt.archive.replace(thetas, returns, torch.zeros(samples, dtype=torch.long))
    opt.policy_set.reset(torch.zeros(1, 2, dtype=F64), relative_std**2 * torch.eye(2)[None])
    opt.retirement.returns.low, opt.retirement.returns.high = 0.0, 1.0
    return opt


def test_a_policy_whose_kept_returns_agree_retires_before_its_exploration_is_small():
    # retire_spread = 1e-4 of the returns' range (0 … 1), retire_std = 1e-3: a policy at
    # 0.05 of Σ_start's std retires on a spread below 1e-4, not above it.
    opt = started_dipole(2, two_optima)
    assert (opt.options.retire_std, opt.options.retire_spread) == (1e-3, 1e-4)
    assert kept(opt, 0.5e-4, 0.05).retirement.converged(opt).tolist() == [True]
    assert kept(opt, 2e-4, 0.05).retirement.converged(opt).tolist() == [False]
    # Not judged so while it explores at a tenth of Σ_start's std or more (a policy crawling
    # up a ridge), nor before it keeps M samples.
    assert kept(opt, 0.5e-4, 0.2).retirement.converged(opt).tolist() == [False]
    assert kept(opt, 0.5e-4, 0.05, samples=4).retirement.converged(opt).tolist() == [False]
    # A wake lowers both thresholds by refine (0.1): spreads 1e-5 … 1e-4 show a gain again.
    kept(opt, 0.5e-4, 0.05).policy_set.refinements = torch.ones(1, dtype=torch.long)
    assert opt.retirement.converged(opt).tolist() == [False]
    assert kept(opt, 0.5e-5, 0.05).retirement.converged(opt).tolist() == [True]
    # Off (0): the std alone.
    off = started_dipole(2, two_optima)
    off.retirement.retire_spread = 0.0
    assert kept(off, 0.0, 0.05).retirement.converged(off).tolist() == [False]


def test_the_spread_rule_scales_with_a_range_too_wide_to_subtract():
    # Returns from -1.5e308 to 1.5e308: high - low overflows to inf, which would retire every
    # policy on any spread; the fraction is taken before the subtraction.
    opt = started_dipole(2, two_optima)
    kept(opt, 1e306, 0.05)  # a spread of 1e306: above 1e-4 of the range (3e304)
    opt.retirement.returns.low, opt.retirement.returns.high = -1.5e308, 1.5e308
    assert opt.retirement.returns.fraction(1e-4) == 1e-4 * 1.5e308 - 1e-4 * -1.5e308
    assert opt.retirement.converged(opt).tolist() == [False]


def test_a_broad_optimum_frees_its_trials_sooner_and_is_still_refined():
    # A broad bowl (returns fall by 1 over Σ_start's std): the kept returns agree to 1e-4 of
    # the range while the exploration is still 10-30 × retire_std, so the policy first
    # retires well before it would on its std; wakes refine it to the same precision.
    def bowl(theta):
        return -theta.square().sum(-1)

    def first_retirement(retire_spread, seed):
        generator = torch.Generator().manual_seed(seed)
        opt = Dipole(torch.full((2,), 0.5, dtype=F64), torch.eye(2, dtype=F64),
                     retire_spread=retire_spread, generator=generator)  # fmt: skip
        retired_at = None
        while opt.trials < 800:
            theta = opt.ask()
            opt.tell(theta, bowl(theta))
            if retired_at is None and not bool(opt.policy_set.active.any()):
                retired_at = opt.trials
        return retired_at, float(bowl(opt.policy_means).max())

    spread = [first_retirement(1e-4, seed) for seed in range(3)]
    std = [first_retirement(0.0, seed) for seed in range(3)]
    # (Seeds 0-2 retired at 308 trials in all against 495.)
    assert sum(at for at, _ in spread) < 0.8 * sum(at for at, _ in std), (spread, std)
    assert all(gap > -1e-9 for _, gap in spread + std), (spread, std)  # (1e-11 and 1e-14)
