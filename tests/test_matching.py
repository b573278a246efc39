"""Matching a clustering's components to the policies (dipole_torch.mechanisms.matching)."""

import pytest
import torch
from test_optimizer import started_dipole, two_optima

from dipole_torch import Dipole
from dipole_torch.archive import NO_POLICY
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import mahalanobis
from dipole_torch.mechanisms.matching import adopt_components, capped_start, match_by_overlap

F64 = torch.float64


def test_components_continue_the_policy_owning_most_of_their_samples_largest_first():
    # Old policies 10 and 20 (positions 0, 1); component 0 holds 3 of policy 10's samples,
    # component 1 holds 2 of 10's and 2 of 20's, component 2 one of 20's.
    labels = torch.tensor([0, 0, 0, 1, 1, 1, 1, 2])
    old = torch.tensor([0, 0, 0, 0, 0, 1, 1, 1])
    continues = match_by_overlap(labels, old, 3, torch.tensor([10, 20]))
    # 3 (component 0, policy 10) is matched first; then component 1 takes policy 20 (2);
    # component 2 is left for a new policy.
    assert continues.tolist() == [10, 20, -1]
    # Equal overlaps: the first in the flattened order wins, and one policy continues once.
    assert match_by_overlap(torch.tensor([0, 1]), torch.tensor([0, 0]), 2, torch.tensor([7]))[
        0
    ] in (7, -1)
    assert sorted(match_by_overlap(torch.tensor([0, 1]), torch.tensor([0, 0]), 2,
                                   torch.tensor([7])).tolist()) == [-1, 7]  # fmt: skip


def test_adopted_components_become_the_policies_the_best_max_policies_kept():
    opt = started_dipole(2, two_optima)
    y = torch.tensor([[1.0, 1.0, 0.9], [1.1, 1.0, 0.8], [-1.0, -1.0, 0.5], [3.0, 3.0, 0.1]])
    y = y.to(F64)
    opt.archive.replace(y[:, :2].clone(), torch.tensor([-0.1, -0.2, -0.5, -9.0], dtype=F64),
                        torch.zeros(4, dtype=torch.long))  # fmt: skip
    state = DPMixtureState.from_labels(y, torch.tensor([0, 0, 1, 2]), opt.dp_state.prior)
    opt.max_policies = 2  # (the cap in force: `max_policies`, or `coverage_max_policies`)
    components = adopt_components(opt, state)
    assert components.tolist() == [0, 1]  # component 2 (best return -9) dropped
    assert opt.num_policies == 2 and torch.equal(opt.policy_means, state.means[:2, :2])
    assert opt.owner.tolist() == [0, 0, 1]  # its sample went with it
    assert opt.active.all() and (opt.policy_set.success == opt.options.success_target).all()


def _match_by_overlap_on_tensors(labels, old, num_components, policies):
    """The greedy matching on tensors (argmax of the flattened counts), as a reference."""
    overlap = torch.zeros(num_components, policies.numel(), dtype=torch.long)
    overlap.index_put_((labels, old), torch.ones_like(labels), accumulate=True)
    continues = torch.full((num_components,), -1, dtype=torch.long)
    while bool((overlap > 0).any()):
        c, j = divmod(int(overlap.argmax()), overlap.shape[1])
        continues[c] = int(policies[j])
        overlap[c] = 0
        overlap[:, j] = 0
    return continues


def test_the_host_matching_equals_the_greedy_matching_on_tensors():
    # Many ties (few samples, few components and policies): the first in the flattened
    # order is matched first either way.
    g = torch.Generator().manual_seed(0)
    for _ in range(300):
        n = int(torch.randint(1, 12, (1,), generator=g))
        c = int(torch.randint(1, 5, (1,), generator=g))
        p = int(torch.randint(1, 5, (1,), generator=g))
        labels = torch.randint(0, c, (n,), generator=g)
        old = torch.randint(0, p, (n,), generator=g)
        policies = torch.randperm(10, generator=g)[:p]
        expected = _match_by_overlap_on_tensors(labels, old, c, policies)
        assert torch.equal(match_by_overlap(labels, old, c, policies), expected)


def _sphere(theta):
    return -(theta.double() - 0.5).square().sum(-1)


def _count_fits(opt) -> list:
    """A list that gains an entry at each of ``opt``'s clusterings that runs sweeps."""
    fits, fit = [], opt._fit
    opt._fit = lambda *args, **kwargs: fits.append(1) or fit(*args, **kwargs)
    return fits


def test_a_clustering_that_would_see_one_policys_samples_alone_is_skipped():
    # One policy (max_policies=1) and its samples alone: nothing to match but that policy,
    # so no sweep runs; with a scout, or a second policy's samples, the clustering runs.
    opt = Dipole(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), max_policies=1,
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    theta = opt.ask()
    opt.tell(theta, _sphere(theta))
    assert opt.num_policies == 1 and bool((opt.owner == 0).all())
    fits = _count_fits(opt)
    assert opt.matching.clustered_rows(opt).numel() == 0
    opt._cluster()
    assert fits == []

    scout = torch.tensor([[2.0, -2.0]], dtype=F64)
    opt.archive.append(scout, _sphere(scout), torch.tensor([NO_POLICY]))
    assert opt.matching.clustered_rows(opt).numel() == len(opt.archive)
    opt._cluster()
    assert fits == [1]

    opt = Dipole(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), max_policies=1,
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    theta = opt.ask()
    opt.tell(theta, _sphere(theta))
    opt.policy_set.extend(scout, 0.1 * torch.eye(2, dtype=F64)[None])  # a second, active one
    opt.archive.append(scout, _sphere(scout), torch.tensor([1]))
    assert opt.matching.clustered_rows(opt).numel() == len(opt.archive)


def test_a_lone_policy_without_scouts_runs_without_clusterings():
    # explore=0: no scouts while a policy is active; with max_policies=1 the run's
    # clusterings after the first see one policy's samples alone and are all skipped.
    opt = Dipole(
        torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64), max_policies=1, explore=0.0,
        retire_std=0.0, generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    theta = opt.ask()
    opt.tell(theta, _sphere(theta))
    fits = _count_fits(opt)
    while opt.trials < 150:
        theta = opt.ask()
        opt.tell(theta, _sphere(theta))
    assert opt.iteration >= 4 * opt.cluster_every and fits == []
    assert float(opt.best()[1]) > -1e-3  # and it converges all the same


def test_a_new_policy_starts_no_wider_than_a_quarter_of_its_distance_to_the_nearest():
    # Σ_start = diag(4, 1): distances and spreads on its scale.
    opt = Dipole(torch.zeros(2, dtype=F64), torch.tensor([2.0, 1.0], dtype=F64),
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    opt.policy_set.reset(
        torch.tensor([[0.0, 0.0], [8.0, 0.0]], dtype=F64),
        torch.eye(2, dtype=F64).expand(2, 2, 2).clone(),
    )
    sigma = opt.sigma_start
    # A component 2 of Σ_start's stds from policy 0 (1 along θ2, scale 1), one far away, one
    # on policy 0's mean; each at Σ_start's shape and spread, then one 1e-3 as wide.
    means = torch.tensor([[0.0, 2.0], [-40.0, 0.0], [0.0, 0.0], [0.0, 2.0]], dtype=F64)
    covariances = torch.stack([sigma, sigma, sigma, 1e-6 * sigma])
    capped = capped_start(opt, means, covariances, 0.25)
    spread = torch.linalg.solve(sigma, capped).diagonal(dim1=-2, dim2=-1).mean(-1)
    assert spread[0].item() == pytest.approx((0.25 * 2.0) ** 2)  # capped: std 0.5 of 2
    assert torch.equal(capped[1], sigma)  # 20 stds from policy 0: under the cap
    assert torch.equal(capped[3], covariances[3])  # narrower than the cap: kept
    assert 0 < spread[2].item() <= 1e-29  # on a policy's mean: retires at once, still PD
    assert bool((torch.linalg.eigvalsh(capped[2]) > 0).all())
    assert torch.allclose(capped[0] / spread[0], sigma)  # Σ_start's shape kept
    assert torch.equal(capped_start(opt, means, covariances, 0.0), covariances)


def test_the_cap_holds_for_the_policies_a_clustering_starts():
    # On two_optima with start_cap=0.25, every policy started after the first clustering
    # explores at most a quarter of the way to the nearest policy there was.
    g = torch.Generator().manual_seed(2)  # (a seed whose run starts one after the first)
    opt = Dipole(torch.zeros(2, dtype=F64), 2.0, generator=g, start_cap=0.25)
    chol = torch.linalg.cholesky(opt.sigma_start)
    started = 0
    while opt.trials < 400:
        before, next_id = opt.policy_means.clone(), opt.policy_set.next_id
        clustered = opt.dp_state is not None  # (the first clustering adopts its components)
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
        new = opt.policy_set.ids >= next_id
        if not clustered or not bool(new.any()):
            continue
        means, covariances = opt.policy_means[new], opt.policy_covariances[new]
        distance = mahalanobis(chol, (before[None] - means[:, None])).amin(-1)
        spread = torch.linalg.solve(opt.sigma_start, covariances).diagonal(dim1=-2, dim2=-1)
        assert bool((spread.mean(-1) <= (0.25 * distance).square() * (1 + 1e-9)).all())
        started += int(new.sum())
    assert started > 0


def _clustered(**options):
    """A DIPOLE with one policy at (1, 1) and a clustering of six kept samples into three
    components: the policy's two samples, two scouts at (−1, −1) and (−1.4, −0.6) (returns
    −0.3 and −5), and two at (3, −3) and (3.2, −2.8) (returns −20 and −1)."""
    opt = Dipole(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                 generator=torch.Generator().manual_seed(0), **options)  # fmt: skip
    theta = opt.ask()
    opt.tell(theta, two_optima(theta))
    opt.policy_set.reset(torch.tensor([[1.0, 1.0]], dtype=F64), torch.eye(2, dtype=F64)[None] * 0.1)
    thetas = torch.tensor(
        [[1.0, 1.0], [1.1, 0.9], [-1.0, -1.0], [-1.4, -0.6], [3.0, -3.0], [3.2, -2.8]], dtype=F64
    )
    rewards = torch.tensor([-0.1, -0.2, -0.3, -5.0, -20.0, -1.0], dtype=F64)
    opt.archive.replace(thetas, rewards, torch.tensor([0, 0, NO_POLICY, NO_POLICY, NO_POLICY,
                                                       NO_POLICY]))  # fmt: skip
    rows = torch.arange(6)
    y = opt._augmented(rows)
    state = DPMixtureState.from_labels(y, torch.tensor([0, 0, 1, 1, 2, 2]), opt.dp_state.prior)
    return opt, rows, y, state


def test_a_new_policy_starts_at_its_components_eq7_average():
    opt, rows, y, state = _clustered(hill_valley=False)
    opt.matching.apply(opt, rows, y, state)
    w = y[:, -1]  # the reward column: eq. 7's weights
    for k, members in ((1, slice(2, 4)), (2, slice(4, 6))):
        average = (w[members, None] * y[members, :2]).sum(0) / w[members].sum()
        assert torch.allclose(opt.policy_means[k], average, atol=1e-12, rtol=0)
    assert not torch.allclose(opt.policy_means[1], y[2:4, :2].mean(0))  # not the plain mean


def test_with_room_for_one_new_policy_the_component_with_the_best_sample_gets_it():
    opt, rows, y, state = _clustered(hill_valley=False, max_policies=2)
    opt.matching.apply(opt, rows, y, state)
    assert opt.num_policies == 2  # the continued policy and one new one
    assert float(opt.policy_means[1].sub(torch.tensor([-1.0, -1.0], dtype=F64)).norm()) < 0.5


def test_a_candidate_is_judged_by_its_components_best_sample_and_return():
    opt, rows, y, state = _clustered()
    opt.matching.apply(opt, rows, y, state)
    vetting = opt.vetting
    assert vetting.candidate_samples.tolist() == [[-1.0, -1.0], [3.2, -2.8]]
    assert vetting.candidate_rewards.tolist() == [-0.3, -1.0]


def test_the_papers_clustering_starts_from_the_policies_current_means():
    """Algorithm 1's warm start (the paper's variant, `matching="replace"`): each chain starts
    from the components at the policies' PoWER-updated means, not the last clustering's."""
    opt = Dipole.paper(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64),
                       generator=torch.Generator().manual_seed(0))  # fmt: skip

    def reward(theta):
        theta = theta.double()
        return torch.exp(-torch.minimum((theta - 1).pow(2).sum(-1), (theta + 1).pow(2).sum(-1)))

    moved = False
    while opt.trials < 200 and not moved:  # until PoWER has moved the policies since
        theta = opt.ask()
        opt.tell(theta, reward(theta))
        moved = opt.trials > 30 and not torch.equal(opt.policy_means, opt.dp_state.means[:, :2])
    assert moved
    rows = opt.matching.clustered_rows(opt)
    start = opt.matching.warm_start(opt, opt._augmented(rows), rows)
    assert torch.equal(start.means[:, :2], opt.policy_means)
