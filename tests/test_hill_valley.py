"""Hill-valley vetting (dipole_torch.mechanisms.hill_valley): between neighbouring policies
with several probes (Ursem 1999), a valley that lies nearer the worse policy than the
midpoint is found, and one probe is the midpoint test, bit for bit; a retired policy short
of the top is replaced by a better candidate."""

import math

import pytest
import torch

from dipole_torch import Dipole

DTYPE = torch.float64


def two_hills(theta: torch.Tensor) -> torch.Tensor:
    """A wide hill of height 1 at 0 and a narrow one of height 0.9 at 3 (1-D): between a
    point near the top of the first and one at 0.85 on the second, the valley lies at three
    quarters of the way, and the midpoint (0.88 on the wide hill's slope) is above 0.85."""
    x = theta[:, 0]
    return torch.maximum(1.0 - 0.08 * x.abs(), 0.9 - 10.0 * (x - 3.0).abs())


def started(**options) -> Dipole:
    """A DIPOLE with ``options`` that has told its first batch on ``two_hills``."""
    opt = Dipole(
        torch.tensor([1.5], dtype=DTYPE),
        torch.tensor([[1.0]], dtype=DTYPE),
        generator=torch.Generator().manual_seed(0),
        **options,
    )
    theta = opt.ask()
    opt.tell(theta, two_hills(theta))
    return opt


def with_two_policies(pair_points: int, std: float = 2.0) -> Dipole:
    """A started DIPOLE whose two active policies have best samples 0 and 3.005 and explore
    with ``std`` (2: each reaches the other's best sample, 1.5 stds away)."""
    opt = started(pair_points=pair_points)
    means = torch.tensor([[0.0], [3.005]], dtype=DTYPE)
    opt.policy_set.reset(means, torch.full((2, 1, 1), std**2, dtype=DTYPE))
    opt.archive.replace(means.clone(), two_hills(means), torch.arange(2))
    return opt


def judge_pairs(opt: Dipole) -> None:
    opt.vetting._probe_pairs(opt)
    opt.vetting._judge_pairs(opt, two_hills(opt.vetting.pair_probes))


def test_three_probes_find_the_valley_near_the_worse_policy():
    opt = with_two_policies(pair_points=3)
    judge_pairs(opt)
    assert opt.policy_means[:, 0].tolist() == [0.0, 3.005]


def test_the_midpoint_alone_misses_it_and_drops_the_worse_policy():
    opt = with_two_policies(pair_points=1)
    judge_pairs(opt)
    assert opt.policy_means[:, 0].tolist() == [0.0]


def test_a_probe_as_good_as_the_worse_policy_shows_one_hill():
    # A plateau (clipped or quantised returns): a probe that ties the worse end is no valley,
    # so the pair is one hill and the worse policy goes.
    opt = with_two_policies(pair_points=1)
    opt.vetting._probe_pairs(opt)
    worse = float(opt.policy_best_rewards.min())
    opt.vetting._judge_pairs(
        opt, torch.full((opt.vetting.pair_probes.shape[0],), worse, dtype=DTYPE)
    )
    assert opt.policy_means[:, 0].tolist() == [0.0]


def judged_candidate_at(probe_below_threshold: float) -> Dipole:
    """Two policies and a queued candidate at 6 whose probe returns its threshold minus
    ``probe_below_threshold``, judged."""
    opt = with_two_policies(pair_points=1)
    vetting = opt.vetting
    one = torch.ones(1, 1, dtype=DTYPE)
    vetting.add_candidates(6 * one, one[None], 6 * one, 0.5 * one[0])
    vetting._probe_candidates(opt)
    vetting.probe_rewards = vetting.candidate_thresholds - probe_below_threshold
    vetting.judge(opt)
    return opt


def test_a_candidate_whose_probe_ties_its_threshold_is_no_new_optimum():
    # A valley is a probe worse than both ends: a tie is none, and no duplicate policy starts.
    assert judged_candidate_at(0.0).num_policies == 2
    # (Just below the threshold is a valley: the candidate becomes a policy.)
    assert judged_candidate_at(1e-3).num_policies == 3


def test_policies_beyond_each_others_reach_are_not_probed_as_a_pair():
    # 30 exploration stds apart (std 0.1): a probe above the worse one would only show a
    # ridge joining the two hills, not one hill. Both stay, and no trial goes to the probe.
    opt = with_two_policies(pair_points=1, std=0.1)
    judge_pairs(opt)
    assert opt.vetting.pair_probes.shape[0] == 0
    assert opt.policy_means[:, 0].tolist() == [0.0, 3.005]
    # Within reach of one of them (the other still far from it), they are probed.
    opt = with_two_policies(pair_points=1, std=0.1)
    opt.policy_set.covariances = torch.tensor([[[4.0]], [[0.01]]], dtype=DTYPE)
    judge_pairs(opt)
    assert opt.policy_means[:, 0].tolist() == [0.0]


def test_probes_lie_at_quarters_and_one_probe_is_the_midpoint_bit_for_bit():
    opt = with_two_policies(pair_points=3)
    opt.vetting._probe_pairs(opt)
    a, b = opt.thetas[0], opt.thetas[1]
    expected = torch.stack([0.75 * a + 0.25 * b, 0.5 * (a + b), 0.25 * a + 0.75 * b])
    torch.testing.assert_close(opt.vetting.pair_probes, expected, rtol=0, atol=1e-15)
    opt = with_two_policies(pair_points=1)
    opt.archive.thetas = torch.tensor([[0.1], [2.9]], dtype=DTYPE)  # 0.1 + 2.9 rounds
    opt.vetting._probe_pairs(opt)
    assert torch.equal(opt.vetting.pair_probes, 0.5 * (opt.thetas[:1] + opt.thetas[1:]))


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, float("nan"), "3"])
def test_bad_pair_points_are_refused(bad):
    with pytest.raises(ValueError, match="pair_points"):
        Dipole(torch.zeros(2, dtype=DTYPE), torch.eye(2, dtype=DTYPE), pair_points=bad)


def test_a_whole_run_with_three_pair_points_finds_every_optimum():
    # sin⁶(5πx) on [0, 1], five equal optima: all five found and kept by 2000 trials, and
    # every ask holds whole triples of pair probes.
    opt = Dipole(
        torch.tensor([0.5], dtype=DTYPE),
        torch.tensor([[0.25**2]], dtype=DTYPE),
        bounds=(0.0, 1.0),
        pair_points=3,
        generator=torch.Generator().manual_seed(0),
    )
    while opt.trials < 2000:
        theta = opt.ask()
        opt.tell(theta, torch.sin(5.0 * math.pi * theta[:, 0]).pow(6))
        assert opt.vetting.pair_probes.shape[0] == 3 * opt.vetting.pair_index.shape[0]
    means = opt.policy_means[:, 0]
    for top in (0.1, 0.3, 0.5, 0.7, 0.9):
        assert (means - top).abs().min() < 1e-3, top


def test_a_retired_policy_short_of_the_top_is_replaced_by_a_better_candidate():
    # One hill, f(θ) = −θ². A policy retired at θ = 2 (its samples straddled, say) claims a
    # top; a candidate on the same hill with a better sample (θ = 1) refutes it: the probe
    # midpoint shows no valley, yet the candidate becomes a policy and the retired one goes.
    # (Before, the candidate was dropped and the retired policy blocked its hill for good.)
    def hill(theta):
        return -theta.double().pow(2).sum(-1)

    opt = Dipole(
        torch.zeros(1, dtype=DTYPE),
        torch.eye(1, dtype=DTYPE),
        generator=torch.Generator().manual_seed(0),
    )
    theta = opt.ask()
    opt.tell(theta, hill(theta))
    one = torch.ones(1, 1, dtype=DTYPE)
    opt.policy_set.reset(2.0 * one, 1e-8 * one[None])
    opt.policy_set.active = torch.zeros(1, dtype=torch.bool)
    opt.archive.replace(
        2.0 * one, torch.tensor([-4.0], dtype=DTYPE), torch.zeros(1, dtype=torch.long)
    )
    vetting = opt.vetting
    vetting.add_candidates(one, 0.1 * one[None], one, torch.tensor([-1.0], dtype=DTYPE))
    vetting._probe_candidates(opt)
    probe = vetting.candidate_probes
    assert torch.allclose(probe, torch.tensor([[1.5]], dtype=DTYPE))
    vetting.probe_rewards = hill(probe)  # -2.25: no valley between θ = 1 and θ = 2
    vetting.judge(opt)
    assert opt.num_policies == 1 and bool(opt.active[0])
    assert torch.allclose(opt.policy_means, one)


def two_policies_and_a_candidate(accept_unjudged: bool, candidate_std: float) -> Dipole:
    """The two-hills DIPOLE of ``with_two_policies`` with one active policy at 0 (std 0.1)
    and a candidate at 3.005 (return 0.85, starting std ``candidate_std``) queued and probed:
    its midpoint probe (0.88 on the wide hill's slope) shows no valley."""
    opt = started(accept_unjudged=accept_unjudged)
    zero = torch.zeros(1, 1, dtype=DTYPE)
    opt.policy_set.reset(zero, torch.full((1, 1, 1), 0.01, dtype=DTYPE))
    opt.archive.replace(zero.clone(), two_hills(zero), torch.zeros(1, dtype=torch.long))
    at = torch.tensor([[3.005]], dtype=DTYPE)
    opt.vetting.add_candidates(at, torch.full((1, 1, 1), candidate_std**2, dtype=DTYPE), at,
                               two_hills(at))  # fmt: skip
    opt.vetting._probe_candidates(opt)
    opt.vetting.probe_rewards = two_hills(opt.vetting.candidate_probes)
    assert bool(opt.vetting.probe_rewards[0] >= two_hills(at)[0])  # no valley shows
    opt.vetting.judge(opt)
    return opt


def test_a_candidate_beyond_reach_that_the_probe_cannot_judge_is_accepted_on_request():
    # 30 stds from the policy, its own start std 0.1: beyond reach both ways.
    assert two_policies_and_a_candidate(False, 0.1).num_policies == 1  # forgotten
    opt = two_policies_and_a_candidate(True, 0.1)
    assert opt.policy_means[:, 0].tolist() == [0.0, 3.005]
    assert opt.policy_set.unjudged.tolist() == [False, True]  # marked for unjudged_share
    # Within reach of its own start (std 2: the policy 1.5 stds away) the probe's "no
    # valley" stands, and the candidate is forgotten.
    assert two_policies_and_a_candidate(True, 2.0).num_policies == 1


def test_accept_unjudged_needs_the_hill_valley_test_and_a_flag():
    with pytest.raises(ValueError, match="accept_unjudged=True needs hill_valley=True"):
        Dipole(torch.zeros(2, dtype=DTYPE), 1.0, hill_valley=False, accept_unjudged=True)
    with pytest.raises((TypeError, ValueError), match="accept_unjudged"):
        Dipole(torch.zeros(2, dtype=DTYPE), 1.0, accept_unjudged="yes")


@pytest.mark.parametrize("share", [None, 0.05])
def test_a_run_that_accepts_unjudged_candidates_resumes_from_a_checkpoint_exactly(tmp_path, share):
    def run(opt, trials):
        while opt.trials < trials:
            theta = opt.ask()
            opt.tell(theta, torch.sin(5.0 * math.pi * theta[:, 0]).pow(6))

    def make():
        return Dipole(
            torch.tensor([0.5], dtype=DTYPE), torch.tensor([[0.25**2]], dtype=DTYPE),
            bounds=(0.0, 1.0), accept_unjudged=True, max_sampled=None,
            unjudged_share=share, generator=torch.Generator().manual_seed(0),
            retire_spread=0.0,  # (with it, every hill is judged: none accepted unjudged)
        )  # fmt: skip

    whole = make()
    run(whole, 600)
    first = make()
    run(first, 300)
    torch.save(first.state_dict(), tmp_path / "opt.pt")
    second = make()
    second.load_state_dict(torch.load(tmp_path / "opt.pt", weights_only=False))
    run(second, 600)
    assert torch.equal(second.policy_means, whole.policy_means)
    assert second.scouting.unjudged_samples == whole.scouting.unjudged_samples
    if share is not None:
        assert whole.scouting.unjudged_samples > 0  # the count is part of what resumed
    # A checkpoint from before the option's queue holds none: it loads with no candidate
    # marked.
    state = {k: v for k, v in first.state_dict().items() if k != "candidate_unjudged"}
    old = make()
    old.load_state_dict(state)
    assert old.vetting.candidate_unjudged.shape == old.vetting.candidate_probes.shape[:1]


def test_batch_size_counts_the_probes_asked_beside_the_samples():
    # (train.py reads batch_size to fit the next batch into the trial budget.)
    from dipole_torch.tasks.multimodal import MultimodalTask

    from dipole_torch.archive import PROBE

    task = MultimodalTask()  # D = 2: a probe's row count differs from its width
    opt = Dipole(task.theta0.double(), task.sigma_start.double(),
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    probed = 0
    for _ in range(12):
        size = opt.batch_size
        theta = opt.ask()
        assert theta.shape[0] == size
        probed += int((opt.asked_owner == PROBE).sum())
        opt.tell(theta, task.evaluate(theta).double())
    assert probed > 0
