"""Many optima close together (the CEC 2013 niching functions' kind): converged policies are
not dropped for a wide new one, a replacement starts from its refuting sample, and a new
policy starts within its own hill."""

import math

import pytest
import torch

from dipole_torch import Dipole

DTYPE = torch.float64


def equal_maxima(theta: torch.Tensor) -> torch.Tensor:
    """sin⁶(5πx) on [0, 1]: five equal optima at 0.1, 0.3, …, 0.9, valleys of 0 between."""
    return torch.sin(5.0 * math.pi * theta[:, 0]).pow(6)


def started() -> Dipole:
    """A 1-D DIPOLE on [0, 1] (Σ_start std 0.25) after its first tell."""
    opt = Dipole(
        torch.tensor([0.5], dtype=DTYPE),
        torch.tensor([[0.25**2]], dtype=DTYPE),
        bounds=(0.0, 1.0),
        generator=torch.Generator().manual_seed(0),
    )
    theta = opt.ask()
    opt.tell(theta, equal_maxima(theta))
    return opt


def set_policies(opt: Dipole, means, stds, active, samples) -> None:
    """Replace the policies: one kept sample each (``samples``), scouts and queues emptied."""
    k = len(means)
    opt.policy_set.reset(
        torch.tensor(means, dtype=DTYPE)[:, None],
        torch.tensor(stds, dtype=DTYPE).square()[:, None, None],
    )
    opt.policy_set.active = torch.tensor(active)
    thetas = torch.tensor(samples, dtype=DTYPE)[:, None]
    opt.archive.replace(thetas, equal_maxima(thetas), torch.arange(k))


def test_a_wide_new_policy_does_not_drop_the_converged_ones_it_covers():
    # Three optima found and retired (std 2e-4); a new policy at 0.62 explores with std
    # 0.22, so 0.5 and 0.7 both lie within one of its stds, and its one sample (at 0.7,
    # closer to the top than the retired policy's) is the best of all. It is a duplicate of
    # neither in particular: nothing may be dropped (the merge used to drop 0.5 and 0.7).
    opt = started()
    set_policies(
        opt,
        means=[0.3, 0.5, 0.7, 0.62],
        stds=[2e-4, 2e-4, 2e-4, 0.22],
        active=[False, False, False, True],
        samples=[0.3001, 0.5001, 0.7001, 0.70001],
    )
    opt.retirement.retire_and_merge(opt)
    assert opt.policy_means[:, 0].tolist() == [0.3, 0.5, 0.7, 0.62]


def test_a_narrow_policy_still_replaces_the_retired_one_it_improves_on():
    # The same rule with one retired policy in reach: the active one goes on, the retired
    # one (short of the top) goes.
    opt = started()
    set_policies(
        opt,
        means=[0.3, 0.7002, 0.7],
        stds=[2e-4, 2e-4, 0.01],
        active=[False, False, True],
        samples=[0.3001, 0.7002, 0.70001],
    )
    opt.retirement.retire_and_merge(opt)
    assert opt.policy_means[:, 0].tolist() == [0.3, 0.7]
    assert opt.active.tolist() == [False, True]


def queue_candidate(opt: Dipole, mean, std, sample, partner) -> None:
    samples = torch.tensor([[sample]], dtype=DTYPE)
    vetting = opt.vetting
    vetting.add_candidates(
        torch.tensor([[mean]], dtype=DTYPE),
        torch.tensor([[[std**2]]], dtype=DTYPE),
        samples,
        equal_maxima(samples),
    )
    vetting._probe_candidates(opt)
    assert vetting.candidate_partners.tolist() == [partner]
    vetting.probe_rewards = equal_maxima(vetting.candidate_probes)


def test_a_replacement_starts_from_its_refuting_sample():
    # A scout closer to the top at 0.7 than the retired policy there (no valley between
    # them) replaces it; its component's mean (0.7147) lies towards the next hill, so the
    # replacement starts from the scout, exploring no wider than the gap.
    opt = started()
    set_policies(opt, [0.3, 0.7003], [2e-4, 2e-4], [False, False], [0.3001, 0.7003])
    queue_candidate(opt, mean=0.7147, std=0.227, sample=0.70001, partner=1)
    opt.vetting.judge(opt)
    assert opt.policy_means[:, 0].tolist() == [0.3, 0.70001]
    # Half the gap, but no narrower than the policy it replaces (std 2e-4).
    half_gap = 0.5 * abs(0.7003 - 0.70001)
    std = float(opt.policy_covariances[1, 0, 0].sqrt())
    assert std == pytest.approx(max(half_gap, 2e-4), rel=1e-9)


def test_a_new_hill_starts_within_half_the_gap_to_its_partner():
    opt = started()
    set_policies(opt, [0.3], [2e-4], [False], [0.3001])
    queue_candidate(opt, mean=0.52, std=0.2, sample=0.49, partner=0)
    opt.vetting.judge(opt)  # the midpoint 0.395 lies in the valley: a new policy
    assert opt.policy_means[:, 0].tolist() == [0.3, 0.52]
    std = float(opt.policy_covariances[1, 0, 0].sqrt())
    assert std == pytest.approx(0.5 * (0.49 - 0.3001), rel=1e-9)


def test_equal_maxima_keeps_all_five_optima():
    """The run where the merge used to lose found optima: by 5000 trials every optimum has
    been found and retired, and the restarts' scouts must not cost any of them."""
    opt = started()
    while opt.trials < 5000:
        theta = opt.ask()
        opt.tell(theta, equal_maxima(theta))
    top = equal_maxima(opt.policy_means)
    for centre in (0.1, 0.3, 0.5, 0.7, 0.9):
        near = (opt.policy_means[:, 0] - centre).abs() < 1e-3
        assert bool(near.any()) and float(top[near].max()) > 1 - 1e-4, centre
