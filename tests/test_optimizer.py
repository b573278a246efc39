"""The ask/tell optimizers: interface, checkpoints, bad input."""

import math

import numpy as np
import pytest
import torch
from dipole_torch.tasks.multimodal import MultimodalTask
from test_reliability import assert_same

from dipole_torch import Dipole, DipoleOptions, DPSampler, GaussianMixture, Power
from dipole_torch.result import SearchResult
from dipole_torch.settings import setting_differences

F64 = torch.float64


def run(opt, task, trials):
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta))
    return opt


def make(cls, task, seed=0, dtype=None):
    return cls(
        task.theta0.to(dtype),
        task.sigma_start.to(dtype),
        n0=10,
        reward_range=task.reward_range,
        generator=torch.Generator().manual_seed(seed),
    )


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_ask_shapes_and_trial_count(cls):
    task = MultimodalTask()
    opt = make(cls, task)
    first = opt.ask()
    assert first.shape == (10, 2) and first.dtype == task.theta0.dtype
    opt.tell(first, task.evaluate(first))
    second = opt.ask()
    assert second.shape == (opt.num_policies, 2)
    opt.tell(second, task.evaluate(second))
    assert opt.trials == 10 + second.shape[0]
    assert isinstance(opt.policies, GaussianMixture)
    theta, reward = opt.best()
    assert theta.shape == (2,) and reward == pytest.approx(float(task.evaluate(theta[None])))


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_resumed_run_makes_exactly_the_same_draws(cls):
    task = MultimodalTask()
    straight = run(make(cls, task, seed=3), task, 120)
    first = run(make(cls, task, seed=3), task, 60)
    state = first.state_dict()
    resumed = make(cls, task, seed=99)  # another seed: the checkpoint must override it
    resumed.load_state_dict(state)
    run(resumed, task, 120)
    assert resumed.trials == straight.trials
    torch.testing.assert_close(resumed.policy_means, straight.policy_means, rtol=0, atol=0)
    torch.testing.assert_close(resumed.thetas, straight.thetas, rtol=0, atol=0)
    assert torch.equal(resumed.ask(), straight.ask())


def test_the_priors_reward_variance_is_floored_at_a_hundredth_of_the_largest_weight_squared():
    # A first batch of nearly equal returns: var w (2.5e-4) is below the floor 1e-2 · 0.35².
    opt = Dipole(torch.zeros(2, dtype=F64), 1.0, reward_range=(0.0, 10.0),
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    theta = opt.ask()
    returns = torch.full((theta.shape[0],), 3.0, dtype=F64)
    returns[0] = 3.5  # weights 0.35 and 0.3
    opt.tell(theta, returns)
    variance = float(opt.initial_prior.mean_covariance[-1, -1])
    assert variance == pytest.approx(1e-2 * 0.35**2, rel=1e-12)
    assert opt.initial_prior.mean_covariance[:-1, :-1].equal(torch.eye(2, dtype=F64))


def test_dipole_mixture_predicts_returns_in_return_units():
    task = MultimodalTask()
    opt = run(make(Dipole, task, seed=1), task, 200)
    mixture = opt.mixture
    assert mixture.event_shape == (3,)
    predicted = opt.policy_rewards
    assert predicted.shape == (opt.num_policies,)
    assert ((predicted > -0.5) & (predicted < 1.5)).all()
    given_high = mixture.condition([2], torch.tensor([1.0], dtype=F64))
    assert given_high.event_shape == (2,)


def test_the_mixture_is_the_last_clusterings_in_return_units_at_the_policies_means():
    # matching="replace": the components are the policies, at their current means and
    # weighted by their kept samples now; the reward axis in return units (slope 4).
    opt = Dipole(torch.zeros(2, dtype=F64), 1.0, matching="replace", retire_std=0.0,
                 reward_range=(0.0, 4.0), generator=torch.Generator().manual_seed(0))  # fmt: skip
    for _ in range(3):  # the first batch's clustering, then two iterations without one
        theta = opt.ask()
        opt.tell(theta, (4.0 - (theta - 1.0).pow(2).sum(-1)).clamp(0.0, 4.0))
    mixture, state, k = opt.mixture, opt.dp_state, opt.num_policies
    counts = opt.archive.counts(k).to(F64)
    assert not torch.equal(counts, state.counts.to(F64))  # policies sampled since
    torch.testing.assert_close(mixture.weights, counts / counts.sum())
    assert torch.equal(mixture.means[:, :2], opt.policy_means)
    torch.testing.assert_close(mixture.means[:, 2], 4.0 * state.means[:, 2])
    scale = torch.tensor([1.0, 1.0, 4.0], dtype=F64)
    torch.testing.assert_close(mixture.covariances, state.covariances * scale[:, None] * scale)


def test_after_a_merge_the_mixture_keeps_the_last_clusterings_components():
    # matching="replace" with merges: a policy merged since the clustering leaves fewer
    # policies than components, and the mixture is the clustering's as it was.
    options = DipoleOptions.paper(merge_radius=1.0, reward_range=None)
    opt = Dipole(torch.zeros(2, dtype=F64), 1.0, options=options,
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    for _ in range(2):
        theta = opt.ask()
        opt.tell(theta, -(theta - 0.5).square().sum(-1))
    state = opt.dp_state
    assert opt.num_policies < state.means.shape[0]  # merged since the clustering
    mixture = opt.mixture
    assert torch.equal(mixture.means[:, :2], state.means[:, :2])
    counts = state.counts.to(F64)
    torch.testing.assert_close(mixture.weights, counts / counts.sum())


def test_the_mixture_before_the_first_tell_is_a_clear_error():
    opt = Dipole(torch.zeros(2, dtype=F64), 1.0)
    with pytest.raises(RuntimeError, match=r"the mixture exists after the first tell\(\)"):
        opt.mixture  # noqa: B018


def test_bad_input_is_rejected_before_it_changes_anything():
    task = MultimodalTask()
    opt = make(Dipole, task)
    theta = opt.ask()
    with pytest.raises(ValueError, match="rewards contains non-finite"):
        opt.tell(theta, torch.tensor([0.5] * 9 + [float("nan")]))
    with pytest.raises(ValueError, match=r"rewards must have shape \[10\]"):
        opt.tell(theta, torch.ones(9))
    with pytest.raises(ValueError, match=r"theta must have shape \[N, 2\]"):
        opt.tell(theta[:, :1], torch.ones(10))
    with pytest.raises(ValueError, match="outside reward_range"):
        opt.tell(theta, torch.full((10,), 2.0))
    assert opt.trials == 0 and opt.thetas.numel() == 0
    opt.tell(theta, task.evaluate(theta))  # the same ask is still pending and valid
    assert opt.trials == 10


def test_tell_without_ask_and_positive_rewards_without_range():
    opt = Power(torch.zeros(2), torch.eye(2), reward_range="positive")
    with pytest.raises(RuntimeError, match="without a pending ask"):
        opt.tell(torch.zeros(5, 2), torch.ones(5))
    theta = opt.ask()
    with pytest.raises(ValueError, match="rewards must be positive"):
        opt.tell(theta, -torch.ones(theta.shape[0]))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"sigma_start": -torch.eye(2)}, "sigma_start is not positive definite"),
        ({"sigma_start": torch.eye(3)}, r"sigma_start must have shape \[2, 2\]"),
        (
            {"theta0": torch.zeros(2, 1)},
            r"theta0 must have shape \[D\] \(D parameters\), got \[2, 1\]",
        ),
        ({"theta0": torch.tensor([0.0, float("nan")])}, "theta0 contains non-finite"),
        ({"alpha": 0.0}, "alpha"),
        ({"m": 0}, "m \\(auxiliary components\\)"),
        ({"M": 0}, "M \\(importance-set size\\)"),
        ({"n0": -1}, "n0"),
        ({"reward_range": (1.0, 0.0)}, "high > low"),
        ({"cluster_every": 0}, "cluster_every"),
        ({"auxiliary": "fast"}, "auxiliary must be 'auto', 'fresh' or 'reuse'"),
        ({"max_sampled": 0}, "max_sampled must be a positive integer or None"),
        ({"max_sampled": 2.5}, "max_sampled must be a positive integer or None"),
    ],
)
def test_bad_constructor_arguments(kwargs, message):
    args = {"theta0": torch.zeros(2), "sigma_start": torch.eye(2)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Dipole(**args)


# ---------------------------------------------------------------- any reward scale
def two_optima(theta):
    """f(θ) = −100·min ‖θ ∓ 1‖²: two optima at ±1, every return negative."""
    theta = theta.double()
    return -100.0 * torch.minimum((theta - 1).pow(2).sum(-1), (theta + 1).pow(2).sum(-1))


def learn(opt, f, trials):
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, f(theta))
    return opt


@pytest.mark.parametrize(
    "scale, offset", [(1.0, 0.0), (1e-9, 0.0), (1e9, 0.0), (1e-9, -5e-7), (1e9, 3e12)]
)
def test_dipole_needs_no_reward_range(scale, offset):
    # Negative returns, returns of order 1e-9 and 1e9, large offsets: no range is given and
    # the run must learn as well as on the unit scale (it ran into a reward_range error at
    # trial 56 with a guessed range before).
    opt = Dipole(torch.zeros(2), 0.5 * torch.eye(2), generator=torch.Generator().manual_seed(0))
    learn(opt, lambda t: offset + scale * two_optima(t), 800)
    theta, best = opt.best()
    assert (best - offset) / scale > -1e-3
    on = (opt.policy_means.abs() - 1).abs().amax(-1) < 0.05
    signs = set(opt.policy_means[on, 0].sign().tolist())
    assert signs == {-1.0, 1.0}, opt.policy_means  # both optima kept


def test_unit_changes_do_not_change_the_run():
    # Weights are the kept returns' min-max: r -> a r + b (a > 0) leaves every decision alone.
    runs = []
    for a, b in ((1.0, 0.0), (1e6, -3e6), (1e-6, 2.0)):
        opt = Dipole(
            torch.zeros(2, dtype=F64),
            0.5 * torch.eye(2, dtype=F64),
            generator=torch.Generator().manual_seed(4),
        )
        runs.append(learn(opt, lambda t, a=a, b=b: b + a * two_optima(t), 150))
    for other in runs[1:]:
        assert other.trials == runs[0].trials
        torch.testing.assert_close(other.policy_means, runs[0].policy_means, rtol=1e-6, atol=1e-8)


def test_a_range_that_grows_during_the_run():
    # Returns grow by orders of magnitude as learning succeeds (exp of a quadratic).
    opt = Dipole(torch.zeros(3), torch.eye(3), generator=torch.Generator().manual_seed(1))
    learn(opt, lambda t: torch.exp(20.0 - 10.0 * (t.double() - 2).pow(2).sum(-1)), 600)
    assert opt.best()[1] > math.exp(19.0)


def test_fixed_range_is_still_accepted_and_enforced():
    opt = Dipole(torch.zeros(2), torch.eye(2), reward_range=(-1.0, 1.0))
    theta = opt.ask()
    with pytest.raises(ValueError, match="outside reward_range"):
        opt.tell(theta, torch.full((theta.shape[0],), 3.0))
    with pytest.raises(ValueError, match="finite with high > low"):
        Dipole(torch.zeros(2), torch.eye(2), reward_range=(-math.inf, 1.0))


# ---------------------------------------------------------------- convergence
def test_a_policy_converges_on_a_smooth_bump_in_10d():
    # One anisotropic Gaussian bump in 10-D: by 2000 trials some policy mean returns within
    # 1e-3 (relative) of the bump's height, and the exploration has shrunk.
    g = torch.Generator().manual_seed(0)
    d = 10
    q, _ = torch.linalg.qr(torch.randn(d, d, generator=g, dtype=F64))
    stds = 0.5 + torch.rand(d, generator=g, dtype=F64)
    precision = q @ torch.diag(stds**-2) @ q.T
    centre = 2 * torch.rand(d, generator=g, dtype=F64) - 1

    def bump(theta):
        diff = theta.double() - centre
        return 7.0 * torch.exp(-0.5 * ((diff @ precision) * diff).sum(-1))

    opt = Dipole(
        torch.zeros(d, dtype=F64),
        4 * torch.eye(d, dtype=F64),
        generator=torch.Generator().manual_seed(0),
    )
    learn(opt, bump, 2000)
    assert float(bump(opt.policy_means).max()) >= 7.0 * (1 - 1e-3)
    assert float(opt.policy_covariances.diagonal(dim1=-2, dim2=-1).max()) < 1e-2 * 4


def test_auxiliary_draws_auto_reuse_them_in_high_dimension_only(monkeypatch):
    """auxiliary="auto" re-uses the auxiliary draws once p = D + 1 >= 32 (where they are
    most of a sweep's cost), never in the paper's variant, and the clusterings get it."""

    def build(d, **kwargs):
        return Dipole(torch.zeros(d, dtype=F64), torch.eye(d, dtype=F64), **kwargs)

    assert build(30).auxiliary == "fresh" and build(31).auxiliary == "reuse"
    assert build(2, auxiliary="reuse").auxiliary == "reuse"
    assert build(40, auxiliary="fresh").auxiliary == "fresh"
    assert Dipole.paper(torch.zeros(40, dtype=F64), torch.eye(40, dtype=F64)).auxiliary == "fresh"
    asked = []
    original = DPSampler.fit

    def recording(self, *args, **kwargs):
        asked.append(self.auxiliary == "reuse")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(DPSampler, "fit", recording)
    for d, expected in ((2, False), (31, True)):
        asked.clear()
        learn(build(d, generator=torch.Generator().manual_seed(0)), two_optima, 40)
        assert asked and set(asked) == {expected}


@pytest.mark.parametrize("seed", range(4))
def test_reused_auxiliary_draws_find_and_converge_on_both_optima(seed):
    """Favaro & Teh's sampler in the whole optimizer: a long run on two optima in 2-D never
    raises and ends with a converged policy on each, as Algorithm 8's does. (The sampler's
    exactness is tested against the enumerated posterior in ``tests/test_dp_exact.py``.)"""
    opt = Dipole(
        torch.zeros(2, dtype=F64),
        torch.eye(2, dtype=F64),
        auxiliary="reuse",
        generator=torch.Generator().manual_seed(seed),
    )
    learn(opt, two_optima, 1500)
    returns = two_optima(opt.policy_means)
    for optimum in (1.0, -1.0):
        near = ((opt.policy_means - optimum).abs().amax(-1) < 1e-2) & (returns > -1e-2)
        assert bool(near.any()), f"no converged policy at {optimum}: {opt.policy_means}"


def test_long_successful_run_retires_converged_policies_and_keeps_going():
    # 4000 trials on two optima: policies converge, retire, scouts restart the search; the
    # run never raises, retired policies are no longer asked and are still returned.
    opt = Dipole(
        torch.zeros(2, dtype=F64),
        torch.eye(2, dtype=F64),
        generator=torch.Generator().manual_seed(2),
    )
    while opt.trials < 4000:
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
        assert opt.last_rewards.numel() > 0  # also after a batch of scouts only
    assert (~opt.active).any()
    retired = opt.policy_means[~opt.active]
    assert ((retired.abs() - 1).abs().amax(-1) < 1e-2).all()
    asked = opt.ask()
    assert (opt.asked_owner >= 0).sum() == min(int(opt.active.sum()), opt.options.max_sampled)
    assert asked.shape[0] >= int(opt.active.sum())


def test_the_result_names_each_row_by_the_id_train_py_gives_it():
    # Policies are dropped and added during a run, so rows move while ids stay: the result's
    # ids are the numbers results.json and train.py's summary use, row for row.
    from dipole_torch.training.results import policy_summary

    task = MultimodalTask(dim=2, num_optima=4)
    opt = Dipole(task.theta0, task.sigma_start, generator=torch.Generator().manual_seed(0))
    while opt.trials < 400:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta))
    result = opt.result
    assert result.ids.dtype == torch.int64 and result.ids.shape == (opt.num_policies,)
    assert len(set(result.ids.tolist())) == opt.num_policies
    assert int(result.ids.max()) >= opt.num_policies  # some were dropped: ids are not rows
    by_id = {p["id"]: p for p in policy_summary(task, opt)}
    assert sorted(by_id) == sorted(result.ids.tolist())
    for k, policy_id in enumerate(result.ids.tolist()):
        assert f"means[{k}] = " in str(result) and f"policy {policy_id})" in str(result)
        mean = torch.tensor(by_id[policy_id]["mean"], dtype=result.means.dtype)
        assert torch.equal(mean, result.means[k])  # the same row (in the task's dtype)
        covariance = torch.tensor(by_id[policy_id]["covariance"], dtype=F64)
        assert torch.equal(covariance, opt.policy_covariances[k])
        assert by_id[policy_id]["weight"] == float(opt.policies.weights[k])


def test_powers_result_is_one_policy_with_id_zero():
    opt = Power(torch.zeros(2, dtype=F64), 1.0, generator=torch.Generator().manual_seed(0))
    theta = opt.ask()
    opt.tell(theta, two_optima(theta))
    assert opt.result.ids.tolist() == [0]
    assert "; 1 policy, best first:" in str(opt.result) and "(active, policy 0)" in str(opt.result)


def test_a_run_without_scouts_restarts_when_every_policy_has_retired():
    # explore=0 (no scouts): once every policy has converged and retired, the next ask is a
    # restart of n0 draws from N(θ0, Σ_start), never an empty batch (which ended the run).
    opt = Dipole(
        torch.zeros(2, dtype=F64),
        torch.eye(2, dtype=F64),
        explore=0.0,
        retire_std=0.05,
        generator=torch.Generator().manual_seed(1),
    )
    restarts = 0
    while opt.trials < 1500:
        retired_all = opt.started and not bool(opt.active.any())
        theta = opt.ask()
        assert theta.shape[0] > 0
        if retired_all:
            restarts += 1
            assert int((opt.asked_owner == -1).sum()) == opt.n0  # (and any probes)
        opt.tell(theta, two_optima(theta))
    assert restarts >= 1


def test_paper_variant_is_reachable():
    task = MultimodalTask()
    opt = Dipole.paper(
        task.theta0,
        task.sigma_start,
        reward_range=task.reward_range,
        generator=torch.Generator().manual_seed(0),
    )
    assert opt.options.importance == "global" and opt.options.exploration == "clustering"
    assert opt.options.explore == 0 and not opt.options.hill_valley
    assert opt.options.matching == "replace"
    run(opt, task, 100)
    assert opt.active.all() and opt.asked_owner is None


# ---------------------------------------------------------------- a transactional tell
def test_tell_leaves_the_optimizer_untouched_when_it_raises(monkeypatch):
    task = MultimodalTask()
    opt = run(make(Dipole, task, seed=5), task, 40)
    theta = opt.ask()
    before = opt.state_dict()

    def broken(*args, **kwargs):
        raise RuntimeError("clustering failed")

    monkeypatch.setattr(DPSampler, "fit", broken)
    for _ in range(20):  # tell until a clustering is due, and fails
        before = opt.state_dict()
        try:
            opt.tell(theta, task.evaluate(theta))
        except RuntimeError as error:
            assert "clustering failed" in str(error)
            break
        theta = opt.ask()
    else:
        raise AssertionError("no clustering within 20 iterations")
    after = opt.state_dict()
    assert before.keys() == after.keys()
    for key, value in before.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, after[key]), key
        elif key == "settings":
            assert setting_differences(value, after[key]) == []
        elif key != "dp_state" and key != "initial_prior":
            assert value == after[key], key


def test_large_offsets_and_tiny_exploration():
    # θ0 = 1e6·1 with Σ_start = 1e-4·I used to make the clustering raise inside tell.
    theta0 = torch.full((3,), 1e6, dtype=F64)
    opt = Dipole(theta0, 1e-4 * torch.eye(3, dtype=F64), generator=torch.Generator().manual_seed(0))
    learn(opt, lambda t: -(t - theta0 - 0.01).pow(2).sum(-1), 300)
    assert (opt.best()[0] - theta0 - 0.01).abs().max() < 5e-3


@pytest.mark.parametrize("paper", [False, True])
def test_a_numerically_failed_clustering_does_not_stop_the_run(monkeypatch, paper):
    # A Cholesky failure inside the DP (seen on a 10-D landscape at the first clustering)
    # must not end a run: the first clustering falls back to Algorithm 1's single
    # component, a later one is skipped, and learning goes on.
    def singular(*args, **kwargs):
        raise torch.linalg.LinAlgError("not positive-definite")

    monkeypatch.setattr(DPSampler, "fit", singular)
    build = Dipole.paper if paper else Dipole
    opt = build(
        torch.zeros(2, dtype=F64),
        torch.eye(2, dtype=F64),
        reward_range=(-1e6, 0.0),
        generator=torch.Generator().manual_seed(0),
    )
    learn(opt, lambda t: -(t - 0.5).pow(2).sum(-1), 200)
    assert opt.clusterings_skipped > 1 and opt.num_policies == 1
    assert opt.best()[1] > -0.05


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("build", [Dipole, Dipole.paper, Power])
def test_optimizers_run_on_cuda(build):
    # A long enough run on the GPU to cluster, retire and probe: draws, clustering and
    # state all stay on the device, and a checkpoint round-trips there.
    device = torch.device("cuda")
    extra = {"reward_range": (-1e4, 0.0)} if build is not Dipole else {}
    opt = build(
        torch.zeros(2, dtype=F64, device=device),
        torch.eye(2, dtype=F64, device=device),
        generator=torch.Generator(device).manual_seed(0),
        **extra,
    )
    learn(opt, two_optima, 400)
    assert opt.policy_means.device.type == "cuda" and opt.ask().device.type == "cuda"
    state = opt.state_dict()
    opt.load_state_dict(state)
    assert opt.best()[1] > -25.0  # within 0.5 of an optimum (the first samples: about -200)


def started_dipole(dim, f):
    """A default Dipole at θ0 = 0, Σ_start = I after its first tell on ``f``."""
    opt = Dipole(
        torch.zeros(dim, dtype=F64),
        torch.eye(dim, dtype=F64),
        generator=torch.Generator().manual_seed(0),
    )
    theta = opt.ask()
    opt.tell(theta, f(theta))
    return opt


def two_hills(theta, heights=(1.0, 1.0)):
    """``[B]`` returns of two equal cones at ∓(2, 2) in 2-D (a hill of height 0 is gone)."""
    centres = torch.tensor([[-2.0, -2.0], [2.0, 2.0]], dtype=theta.dtype)
    distance = torch.cdist(theta, centres)
    return (torch.tensor(heights, dtype=theta.dtype) * (1.0 - distance / 4.0)).amax(-1)


def test_reevaluate_switches_to_a_stored_policy_when_the_world_changes():
    theta0, sigma = torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64) * 4.0
    for seed in range(5):
        opt = Dipole(theta0, sigma, generator=torch.Generator().manual_seed(seed))
        while opt.trials < 400:
            theta = opt.ask()
            opt.tell(theta, two_hills(theta))
        means = opt.policy_means
        on = [bool((torch.linalg.norm(means - c, dim=-1) < 0.1).any()) for c in (-2.0, 2.0)]
        if all(on):
            break
    else:
        pytest.fail("no run found both hills")
    # The hill at (2, 2) disappears: one evaluation per stored policy finds the other.
    trials, k = opt.trials, opt.num_policies
    returns = two_hills(means, heights=(1.0, 0.0))
    opt.reevaluate(returns)
    assert opt.trials == trials + k
    assert torch.equal(opt.last_rewards, returns) and torch.equal(opt.rewards, returns)
    best_theta, best_reward = opt.best()
    assert torch.linalg.norm(best_theta + 2.0) < 0.1 and best_reward > 0.97
    hurt = torch.linalg.norm(means - 2.0, dim=-1) < 0.1
    assert bool(opt.active[hurt].all())  # searching again, from Σ_start
    assert torch.equal(opt.policy_covariances[hurt], sigma.expand(int(hurt.sum()), 2, 2))
    # Learning goes on in the changed world; the switched-to policy stays.
    while opt.trials < trials + k + 100:
        theta = opt.ask()
        opt.tell(theta, two_hills(theta, heights=(1.0, 0.0)))
    assert opt.best()[1] >= best_reward
    assert bool((torch.linalg.norm(opt.policy_means + 2.0, dim=-1) < 0.1).any())


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_reevaluate_rejects_bad_returns_and_leaves_the_optimizer_untouched(cls):
    task = MultimodalTask()
    opt = make(cls, task)
    with pytest.raises(RuntimeError, match="tell"):
        opt.reevaluate(torch.zeros(1, dtype=F64))
    run(opt, task, 40)
    before = opt.state_dict()
    k = opt.num_policies
    for bad, message in (
        (torch.zeros(k + 1, dtype=F64), "shape"),
        (torch.full((k,), math.nan, dtype=F64), "finite|NaN"),
        (torch.full((k,), 1e9, dtype=F64), "range"),
    ):
        with pytest.raises(ValueError, match=message):
            opt.reevaluate(bad)
        after = opt.state_dict()
        for key, value in before.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, after[key]), key
    opt.reevaluate(task.evaluate(opt.policy_means))
    run(opt, task, opt.trials + 20)


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_policies_come_in_the_dtype_of_theta(cls):
    task = MultimodalTask()
    opt = run(make(cls, task, dtype=torch.float32), task, 30)
    assert opt.policies.dtype == torch.float32 and opt.policies.sample((3,)).dtype == torch.float32
    # A converged, ill-conditioned exploration: factorised in float64, then cast.
    eigenvalues = torch.logspace(-14, -2, opt.dim, dtype=F64)
    noise = torch.randn(opt.dim, opt.dim, dtype=F64, generator=torch.Generator().manual_seed(1))
    rotation = torch.linalg.qr(noise)[0]
    opt.policy_set.covariances = (rotation * eigenvalues) @ rotation.T + torch.zeros(
        opt.num_policies, 1, 1, dtype=F64
    )
    policies = opt.policies
    assert torch.isfinite(policies.log_prob(policies.sample((4,)))).all()


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_tell_takes_the_first_rows_of_an_ask(cls):
    """A run can end exactly at a budget: tell the first n rows of the last ask. Queued
    hill-valley tests whose probes were not told are forgotten; the run goes on."""
    task = MultimodalTask()
    opt = make(cls, task)
    run(opt, task, 30)
    for _ in range(200):  # until an ask holds probes (DIPOLE; PoWER asks one row)
        theta = opt.ask()
        if cls is Power or bool((opt.asked_owner == -2).any()):
            break
        opt.tell(theta, task.evaluate(theta))
    else:
        pytest.fail("no ask with probes in 200 iterations")
    before = opt.state_dict()
    for rows in (0, theta.shape[0] + 1):
        bad = torch.zeros(rows, opt.dim, dtype=theta.dtype)
        with pytest.raises(ValueError, match="rows"):
            opt.tell(bad, torch.zeros(rows, dtype=F64))
    assert all(torch.equal(v, opt.state_dict()[k]) for k, v in before.items() if torch.is_tensor(v))
    if theta.shape[0] == 1:
        opt.tell(theta, task.evaluate(theta))
        return
    n = theta.shape[0] - 1
    trials = opt.trials
    opt.tell(theta[:n], task.evaluate(theta[:n]))
    assert opt.trials == trials + n
    if cls is Dipole:  # the queued tests are forgotten
        assert opt.vetting.candidate_probes.shape[0] == 0 and opt.vetting.pair_probes.shape[0] == 0
    run(opt, task, opt.trials + 60)


def test_ties_keep_the_first_best_and_a_tied_reevaluation_is_no_harm():
    # best(): of equal returns, the first told stays the best.
    f64 = torch.float64
    opt = Power(torch.zeros(2, dtype=f64), 1.0, generator=torch.Generator().manual_seed(0))
    theta = opt.ask()
    opt.tell(theta, torch.ones(theta.shape[0], dtype=f64))
    first = theta[0].clone()
    theta = opt.ask()
    opt.tell(theta, torch.ones(theta.shape[0], dtype=f64))
    assert torch.equal(opt.best()[0], first)
    # reevaluate(): a policy whose new return ties its worst kept one is not restarted.
    opt = Power(torch.zeros(2, dtype=f64), 1.0, generator=torch.Generator().manual_seed(0))
    for _ in range(3):
        theta = opt.ask()
        opt.tell(theta, -theta.pow(2).sum(-1))
    worst = opt.archive.per_policy("amin", opt.num_policies)
    opt.policy_set.covariances = 0.25 * opt.policy_covariances
    covariances = opt.policy_covariances.clone()
    opt.reevaluate(worst.clone())
    assert torch.equal(opt.policy_covariances, covariances)


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_stop_meets_the_budget_at_exactly_max_trials(cls):
    """``stop(max_trials)`` reports ``"max_trials"`` once ``trials`` reaches the budget, not
    one trial later: a loop ``while not opt.stop(max_trials=N)`` spends exactly N trials
    when the last ask is cut to fit."""
    opt = cls([0.0, 0.0], 1.0, n0=4, generator=torch.Generator().manual_seed(0))
    assert opt.stop(max_trials=1) == {}
    theta = opt.ask(max_rows=3)
    opt.tell(theta, -theta.square().sum(-1))
    assert opt.stop(max_trials=4) == {} and opt.stop(max_trials=3) == {
        "max_trials": "3 trials of 3"
    }


@pytest.mark.parametrize("cls", [Dipole, Power])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_a_half_precision_run_gives_its_policies_in_float32(cls, dtype):
    """A half-precision θ0 asks and tells in its dtype, but ``policies`` raised (a mixture's
    Cholesky has no half kernel), with "cast them with .float()", which a caller cannot do."""
    opt = cls(torch.zeros(2, dtype=dtype), 1.0, generator=torch.Generator().manual_seed(0))
    for _ in range(5):
        theta = opt.ask()
        opt.tell(theta, -theta.float().square().sum(-1))
    assert theta.dtype == dtype and opt.best()[0].dtype == dtype
    mixture = opt.policies
    assert mixture.means.dtype == torch.float32
    assert torch.allclose(mixture.means, opt.policy_means.float())
    assert bool(mixture.log_prob(torch.zeros(2)).isfinite())


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_tell_takes_the_asked_rows_as_numpy_as_it_takes_the_tensor(cls):
    """``opt.tell(theta.numpy(), r)`` (rows handed to a numpy simulator and told back) makes
    the run a tensor tell makes; a list, or rows clipped by the caller, are refused naming
    what tell takes (and, for clipped rows, the optimizer's bounds)."""
    runs = []
    for as_numpy in (False, True):
        opt = cls([0.0, 0.0], 1.0, n0=4, generator=torch.Generator().manual_seed(0))
        for _ in range(6):
            theta = opt.ask()
            told = theta.numpy() if as_numpy else theta
            opt.tell(told, -theta.square().sum(-1))
        runs.append(opt.state_dict())
    assert_same(*runs)
    theta = opt.ask()
    with pytest.raises(TypeError, match=r"theta must be the rows ask\(\) returned .*got list"):
        opt.tell(theta.tolist(), torch.zeros(theta.shape[0]))
    with pytest.raises(ValueError, match=r"not the row asked .*give the optimizer bounds="):
        opt.tell(theta.clamp(-1e-3, 1e-3), torch.zeros(theta.shape[0]))
    opt.tell(theta[:1], torch.zeros(1))  # the first rows: the others are discarded
    with pytest.raises(RuntimeError, match=r"without a pending ask\(\): each ask is told once"):
        opt.tell(theta[1:], torch.zeros(theta.shape[0] - 1))


@pytest.mark.parametrize("cls", [Dipole, Power])
@pytest.mark.parametrize("budget", [math.nan, math.inf, -1, 2.5, "100", True])
def test_stop_refuses_a_budget_that_is_not_a_whole_number(cls, budget):
    """``while not opt.stop(max_trials=nan)`` looped for ever (no count is >= NaN), and a
    budget read from the environment as a string ended in a comparison's TypeError."""
    opt = cls([0.0, 0.0], 1.0, n0=4, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"max_trials must be an integer >= 0 or None, got"):
        opt.stop(max_trials=budget)
    assert opt.stop(max_trials=0) == {"max_trials": "0 trials of 0"}
    assert opt.stop(max_trials=np.int64(5)) == {} and opt.stop(max_trials=5.0) == {}


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_only_a_tell_of_fewer_rows_than_asked_is_cut(cls, monkeypatch):
    """The told batch is ``cut`` (which makes the hill-valley test forget the tests whose
    probes went untold) when fewer rows are told than were asked, and only then."""
    opt = cls([0.0, 0.0], 1.0, n0=4, generator=torch.Generator().manual_seed(0))
    cuts, observe = [], opt._observe
    monkeypatch.setattr(opt, "_observe", lambda batch: (cuts.append(batch.cut), observe(batch)))
    for rows in (3, None, None, 99):
        theta = opt.ask(max_rows=rows)
        opt.tell(theta, -theta.square().sum(-1))
    assert cuts == [True, False, False, False]


@pytest.mark.parametrize("cls", [Dipole, Power])
def test_reevaluate_discards_a_pending_ask(cls):
    """``reevaluate`` discards a pending ask (its rows were drawn for the world before the
    change): telling them afterwards raises, as a tell with no ask does."""
    opt = cls([0.0, 0.0], 1.0, n0=4, generator=torch.Generator().manual_seed(0))
    theta = opt.ask()
    opt.tell(theta, -theta.square().sum(-1))
    theta = opt.ask()
    opt.reevaluate(torch.zeros(opt.num_policies, dtype=F64))
    assert opt.asked_owner is None
    with pytest.raises(RuntimeError, match="without a pending ask"):
        opt.tell(theta, -theta.square().sum(-1))


def test_the_printed_result_lists_the_best_policy_first():
    """``print(result)`` lists the policies best return first, each named by its row."""
    result = SearchResult(
        best_theta=torch.zeros(1, dtype=F64), best_reward=3.0, trials=9, iterations=2,
        means=torch.tensor([[0.0], [1.0], [2.0]], dtype=F64),
        covariances=torch.ones(3, 1, 1, dtype=F64),
        best_rewards=torch.tensor([1.0, 3.0, 2.0], dtype=F64),
        active=torch.ones(3, dtype=torch.bool), converged=torch.zeros(3, dtype=torch.bool),
        ids=torch.arange(3),
    )  # fmt: skip
    rows = [line.split()[0] for line in str(result).splitlines()[1:]]
    assert rows == ["means[1]", "means[2]", "means[0]"]
