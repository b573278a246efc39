"""Exploration (dipole_torch.mechanisms.exploration): the success rule's constants and
updates, and a new policy's starting covariance."""

import pytest
import torch
from test_optimizer import two_optima

from dipole_torch import Dipole

F64 = torch.float64


def test_new_policies_explore_with_the_shape_of_sigma_start():
    # The default variant starts each policy at Σ_start's shape, scaled to its component's
    # spread (a few points in 10-D give a badly conditioned posterior covariance); the
    # paper's variant keeps the posterior covariance itself.
    d = 10
    sigma_start = torch.diag(torch.linspace(0.5, 2.0, d, dtype=F64))
    for paper in (False, True):
        build = Dipole.paper if paper else Dipole
        extra = {"reward_range": (-1e4, 0.0)} if paper else {}
        opt = build(
            torch.zeros(d, dtype=F64),
            sigma_start,
            generator=torch.Generator().manual_seed(0),
            **extra,
        )
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
        ratio = opt.policy_covariances / sigma_start  # elementwise: off-diagonals are 0/0
        diag = ratio.diagonal(dim1=-2, dim2=-1)  # [K, D]
        condition = torch.linalg.cond(opt.policy_covariances)
        if paper:
            assert (condition > 5 * torch.linalg.cond(sigma_start)).all()
        else:
            assert torch.allclose(diag, diag[:, :1].expand_as(diag))
            assert (diag <= 1.0 + 1e-12).all()
            off = opt.policy_covariances - torch.diag_embed(
                opt.policy_covariances.diagonal(dim1=-2, dim2=-1)
            )
            assert off.abs().max() < 1e-12


def test_a_long_streak_of_successes_up_a_ridge_keeps_the_covariance_factorisable():
    """Up a narrow peak (1 − √distance) from 3 units away with Σ_start = 1e-3 I, nearly
    every sample succeeds along one direction: the rank-one update shrank the other one by
    (1 − c_cov) each time, until at trial 326 the covariance had rank one to rounding
    (eigenvalues −1e-19 and 1.6e-3) and the next ask failed to factorise it. With the
    condition number bounded, the run goes on to the peak."""
    centre = torch.tensor([-2.2174632234891436, 2.4956688703858863], dtype=F64)

    def peak(theta):
        return 1.0 - (theta - centre).norm(dim=-1).sqrt()

    opt = Dipole(
        torch.full((2,), -0.5361559892466568, dtype=F64),
        1e-3 * torch.eye(2, dtype=F64),
        generator=torch.Generator().manual_seed(3),
    )
    while opt.trials < 1500:
        theta = opt.ask()
        opt.tell(theta, peak(theta))
        assert (torch.linalg.cholesky_ex(opt.policy_covariances)[1] == 0).all()
    assert float(peak(opt.policy_means).max()) > 0.99


def test_the_condition_floor_acts_only_on_covariances_that_lack_margin():
    from dipole_torch.mechanisms.exploration import MAX_CONDITION, bounded_condition

    sigma_start = torch.diag(torch.tensor([1e-6, 1e4], dtype=F64))
    opt = Dipole(torch.zeros(2, dtype=F64), sigma_start, generator=torch.Generator())
    scale = sigma_start.diagonal().sqrt()
    direction = torch.tensor([1.0, 1.0], dtype=F64) * scale
    rank_one = direction[:, None] * direction[None, :]  # singular
    fine = torch.diag(torch.tensor([1.0, 1e-6], dtype=F64)) * sigma_start  # condition 1e6
    covs = torch.stack((rank_one, fine))
    out = bounded_condition(opt, covs)
    assert torch.equal(out[1], fine)
    whitened = out[0] / (scale[:, None] * scale[None, :])
    eig = torch.linalg.eigvalsh(whitened)
    assert eig.min() > 0 and eig.max() / eig.min() < 3 * MAX_CONDITION
    assert torch.equal(bounded_condition(opt, fine[None]), fine[None])


def test_a_policy_that_never_retires_keeps_a_floor_under_its_exploration():
    """With ``retire_std=0`` a converged policy fails on and on and the success rule shrinks
    its covariance at every failure; it went on to underflow (variances of 1e-323, found
    at trial 4543 by the fuzz of long runs) and the next ask failed. It now stops at
    ``MIN_RELATIVE_STD`` of Σ_start's std, reached here by trial ~700 (1e-15·0.9^300 at
    trial 1000 without the floor), and the policy goes on sampling."""
    from dipole_torch.mechanisms.exploration import MIN_RELATIVE_STD

    def peak(theta: torch.Tensor) -> torch.Tensor:
        return torch.exp(-(theta - 0.5).square().sum(-1))

    opt = Dipole(torch.zeros(2, dtype=torch.float64), 1e-3 * torch.eye(2, dtype=torch.float64),
                 retire_std=0.0, max_policies=1, explore=0.0,
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    while opt.trials < 1000:
        theta = opt.ask()
        assert torch.isfinite(theta).all()
        opt.tell(theta, peak(theta))
    relative = opt.relative_std()
    assert bool(opt.active.all())  # never retired
    assert MIN_RELATIVE_STD > 0
    assert float(relative.min()) == pytest.approx(MIN_RELATIVE_STD, rel=1e-6, abs=0.0)
    assert float((opt.policy_means - 0.5).abs().max()) < 1e-6  # it did converge


def test_a_new_policy_never_starts_below_the_success_rules_floor():
    """A component whose samples are equal to rounding has a spread that underflows (5e-324,
    0): a policy started there explored nothing, and with ``retire_std=0`` the next ask
    failed in its Cholesky factor. It starts at ``MIN_RELATIVE_STD``² of Σ_start, the floor
    the success rule keeps, and wider spreads are as before."""
    from dipole_torch.mechanisms.exploration import MIN_RELATIVE_STD

    sigma_start = torch.diag(torch.tensor([1e6, 4e6], dtype=F64))
    opt = Dipole(torch.zeros(2, dtype=F64), sigma_start, generator=torch.Generator())
    tiny = torch.stack([torch.zeros(2, 2, dtype=F64), 5e-324 * torch.eye(2, dtype=F64)])
    start = opt.exploration.starting_covariance(opt, tiny)
    assert torch.equal(start, (MIN_RELATIVE_STD**2 * sigma_start).expand(2, 2, 2))
    assert (torch.linalg.cholesky_ex(start)[1] == 0).all()
    wide = torch.stack([0.25 * sigma_start, 9.0 * sigma_start])  # capped at Σ_start
    torch.testing.assert_close(
        opt.exploration.starting_covariance(opt, wide),
        torch.stack([0.25 * sigma_start, sigma_start]),
    )


def test_a_new_policys_spread_is_the_trace_of_its_covariance_whitened_by_sigma_start():
    """``start_spread`` is tr(Σ_start⁻¹ Σ)/D, on each axis in Σ_start's units (1 for Σ_start
    itself), and a new policy starts at that multiple of Σ_start, at most Σ_start."""
    from types import SimpleNamespace

    from dipole_torch.mechanisms.exploration import SuccessRule, start_spread

    sigma_start = torch.tensor([[1.0, 0.0], [0.0, 100.0]], dtype=F64)
    search = SimpleNamespace(sigma_start=sigma_start)
    covariances = torch.stack(
        (
            sigma_start,
            torch.diag(torch.tensor([0.5, 100.0], dtype=F64)),  # (0.5 + 1) / 2
            torch.tensor([[0.25, 1.0], [1.0, 25.0]], dtype=F64),  # (0.25 + 0.25) / 2
            4.0 * sigma_start,
        )
    )
    spread = start_spread(search, covariances)
    torch.testing.assert_close(spread, torch.tensor([1.0, 0.75, 0.25, 4.0], dtype=F64))
    start = SuccessRule(2).starting_covariance(search, covariances)
    expected = torch.tensor([1.0, 0.75, 0.25, 1.0], dtype=F64)[:, None, None] * sigma_start
    torch.testing.assert_close(start, expected)


def test_the_condition_floor_is_1e12_in_sigma_starts_per_axis_units():
    """A covariance whose smallest Cholesky pivot², in Σ_start's per-axis units, is below
    1/``MAX_CONDITION`` = 1e-12 of its largest variance gets that much of Σ_start's
    diagonal (not of Σ_start) added; one at 10^-11.5 is left as it is."""
    from types import SimpleNamespace

    from dipole_torch.mechanisms.exploration import bounded_condition

    for sigma_start in (
        torch.tensor([[1.0, 0.5], [0.5, 1.0]], dtype=F64),
        torch.diag(torch.tensor([1e-6, 1e4], dtype=F64)),
    ):
        search = SimpleNamespace(sigma_start=sigma_start)
        variances = sigma_start.diagonal()
        low = torch.diag(torch.tensor([1.0, 10**-12.5], dtype=F64)) * torch.diag(variances)
        fine = torch.diag(torch.tensor([1.0, 10**-11.5], dtype=F64)) * torch.diag(variances)
        out = bounded_condition(search, torch.stack((low, fine)))
        torch.testing.assert_close(out[0], low + 1e-12 * torch.diag(variances), rtol=1e-12, atol=0)
        assert torch.equal(out[1], fine)


def test_the_papers_policies_hold_their_own_copy_of_the_posterior_covariances():
    # PosteriorExploration hands a policy its component's covariance: a copy, so that a
    # policy's exploration written in place (a retirement's restart does) leaves the DP
    # state, which a checkpoint saves and the next clustering reads, as drawn.
    opt = Dipole.paper(torch.zeros(2, dtype=F64), 1.0, reward_range=(-1e4, 0.0),
                       generator=torch.Generator().manual_seed(0))  # fmt: skip
    theta = opt.ask()
    opt.tell(theta, two_optima(theta))
    state = opt.dp_state.covariances.clone()
    opt.policy_set.covariances[0] *= 2.0
    assert torch.equal(opt.dp_state.covariances, state)
