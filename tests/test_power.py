import math

import pytest
import torch
from test_optimizer import started_dipole, two_optima

from dipole_torch import Power, importance_sets, power_update
from dipole_torch.power import PolicyImportance, _tensor_rows, _tensor_sets, importance_rows

F64 = torch.float64


def test_power_update_is_eq7_batched_over_policies():
    g = torch.Generator().manual_seed(0)
    mean = torch.randn(3, 4, generator=g, dtype=F64)
    samples = torch.randn(3, 5, 4, generator=g, dtype=F64)
    weights = torch.rand(3, 5, generator=g, dtype=F64)
    weights[2, 3:] = 0.0  # padding
    updated = power_update(mean, samples, weights)
    for k in range(3):
        step = sum(weights[k, m] * (samples[k, m] - mean[k]) for m in range(5)) / weights[k].sum()
        torch.testing.assert_close(updated[k], mean[k] + step)


def test_power_update_keeps_a_policy_without_samples():
    mean = torch.ones(2, 3, dtype=F64)
    out = power_update(mean, torch.zeros(2, 4, 3, dtype=F64), torch.zeros(2, 4, dtype=F64))
    assert torch.equal(out, mean)


@pytest.mark.parametrize(
    "mean, samples, weights, message",
    [
        # A mean of another D ended in torch's broadcasting error.
        (torch.zeros(2, 3), torch.zeros(2, 4, 2), torch.ones(2, 4), "expected mean"),
        (torch.zeros(3), torch.zeros(2, 4, 3), torch.ones(2, 4), "expected mean"),
        (torch.zeros(2, 3), torch.zeros(2, 4, 3), torch.ones(2, 3), "expected mean"),
        (torch.zeros(2, 3), torch.zeros(2, 4, 3), -torch.ones(2, 4), "non-negative"),
        # NaN weights passed as padding: the mean came back unchanged.
        (torch.zeros(2, 3), torch.zeros(2, 4, 3), torch.full((2, 4), math.nan), "no NaN"),
    ],
)
def test_power_update_refuses_shapes_and_weights_it_cannot_take(mean, samples, weights, message):
    with pytest.raises(ValueError, match=f"power_update: .*{message}"):
        power_update(mean, samples, weights)


# Both paths of each function: the CPU's (Python scalars) and every other device's (tensor
# operations, run here on the CPU).
SETS = pytest.mark.parametrize("sets", [importance_sets, _tensor_sets], ids=["host", "tensor"])
ROWS = pytest.mark.parametrize("rows_of", [importance_rows, _tensor_rows], ids=["host", "tensor"])


@SETS
def test_importance_sets_pick_each_policys_best(sets):
    owner = torch.tensor([0, 1, 0, 0, 1, 2, 0])
    rewards = torch.tensor([1.0, 5.0, 3.0, 2.0, 4.0, 0.0, 7.0])
    keep, index, valid = sets(owner, rewards, 3, 2)
    assert index.tolist() == [[6, 2], [1, 4], [5, -1]]
    assert valid.tolist() == [[True, True], [True, True], [True, False]]
    assert keep.tolist() == [False, True, True, False, True, True, True]


def _sets_by_hand(owner, rewards, k, size):
    """Each policy's best ``size`` samples, ties in archive order (Python's stable sort)."""
    index = [[-1] * size for _ in range(k)]
    for policy in range(k):
        own = [i for i in range(len(owner)) if owner[i] == policy]
        for slot, i in enumerate(sorted(own, key=lambda i: -rewards[i])[:size]):
            index[policy][slot] = i
    return index


def _random_archive(seed, no_policy):
    g = torch.Generator().manual_seed(seed)
    n = int(torch.randint(0 if not no_policy else 1, 50, (1,), generator=g))
    k = int(torch.randint(1, 6, (1,), generator=g))
    size = int(torch.randint(1, 7, (1,), generator=g))
    owner = torch.randint(-1 if no_policy else 0, k, (n,), generator=g)
    # Few distinct values (ties), ±0 among them, or distinct ones.
    rewards = torch.randint(-3, 4, (n,), generator=g).to(F64) * 0.5
    zeros = rewards == 0
    rewards[zeros] = torch.tensor([0.0, -0.0], dtype=F64)[torch.arange(n)[zeros] % 2]
    if seed % 2:
        rewards = rewards + 1e-3 * torch.randn(n, generator=g, dtype=F64)
    return owner, rewards, k, size


@SETS
@pytest.mark.parametrize("seed", range(30))
def test_importance_sets_match_a_sort_by_hand(seed, sets):
    owner, rewards, k, size = _random_archive(seed, no_policy=False)
    keep, index, valid = sets(owner, rewards, k, size)
    expected = _sets_by_hand(owner.tolist(), rewards.tolist(), k, size)
    assert index.tolist() == expected
    assert torch.equal(valid, index >= 0)
    chosen = {i for row in expected for i in row if i >= 0}
    assert keep.tolist() == [i in chosen for i in range(owner.shape[0])]


@SETS
@ROWS
def test_importance_sets_of_an_empty_archive(sets, rows_of):
    keep, index, valid = sets(torch.zeros(0, dtype=torch.long), torch.zeros(0), 2, 3)
    assert keep.shape == (0,) and index.tolist() == [[-1] * 3] * 2 and not valid.any()
    assert (keep.dtype, index.dtype, valid.dtype) == (torch.bool, torch.long, torch.bool)
    kept, rows, valid = rows_of(torch.full((2,), -1), torch.zeros(2, dtype=F64), 2, 3)
    assert kept.tolist() == [0, 1] and rows.tolist() == [[0] * 3] * 2 and not valid.any()


@ROWS
@pytest.mark.parametrize("seed", range(30))
def test_importance_rows_keep_samples_of_no_policy(seed, rows_of):
    owner, rewards, k, size = _random_archive(seed, no_policy=True)
    kept, rows, valid = rows_of(owner, rewards, k, size)
    assert (kept.dtype, rows.dtype, valid.dtype) == (torch.long, torch.long, torch.bool)
    expected = _sets_by_hand(owner.tolist(), rewards.tolist(), k, size)
    owned = [i for i in range(owner.shape[0]) if owner[i] >= 0]
    empty = owned[0] if owned else 0  # an empty slot points at the first owned row
    assert rows.tolist() == [[i if i >= 0 else empty for i in row] for row in expected]
    assert valid.tolist() == [[i >= 0 for i in row] for row in expected]
    chosen = {i for row in expected for i in row if i >= 0}
    assert kept.tolist() == [i for i in range(owner.shape[0]) if owner[i] < 0 or i in chosen]


def test_a_large_archive_takes_the_tensor_path_with_the_same_sets():
    """Beyond ``HOST_ROWS`` samples the sets come from the tensor path (its sorts are the
    faster there): the same sets as a sort by hand."""
    from dipole_torch.power import HOST_ROWS

    g = torch.Generator().manual_seed(5)
    n, k, size = HOST_ROWS + 100, 4, 5
    owner = torch.randint(-1, k, (n,), generator=g)
    rewards = torch.randint(-3, 4, (n,), generator=g).to(F64)  # (many ties)
    kept, rows, valid = importance_rows(owner, rewards, k, size)
    expected = _sets_by_hand(owner.tolist(), rewards.tolist(), k, size)
    assert rows.tolist() == expected and valid.all()
    chosen = {i for row in expected for i in row}
    assert kept.tolist() == [i for i in range(n) if owner[i] < 0 or i in chosen]
    keep, index, _ = importance_sets(owner.clamp_min(0), rewards, k, size)
    assert index.tolist() == _sets_by_hand(owner.clamp_min(0).tolist(), rewards.tolist(), k, size)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_power_converges_on_a_concave_quadratic(seed):
    optimum = torch.tensor([1.0, -2.0, 0.5], dtype=F64)

    def reward(theta):
        return 10.0 - (theta - optimum).pow(2).sum(-1).clamp(max=10.0)

    opt = Power(
        torch.zeros(3, dtype=F64),
        0.25 * torch.eye(3, dtype=F64),
        reward_range=(0.0, 10.0),
        generator=torch.Generator().manual_seed(seed),
    )
    start = torch.linalg.norm(opt.policy_means[0] - optimum)
    while opt.trials < 400:
        theta = opt.ask()
        opt.tell(theta, reward(theta))
    # A fixed exploration covariance limits how close the mean gets: within 0.25 of the
    # optimum, from 2.3 away.
    assert torch.linalg.norm(opt.policy_means[0] - optimum) < 0.25 < start


def test_each_policy_weighs_its_samples_by_its_own_returns():
    # Per-policy importance sets take eq. 7's weights from the policy's own M returns
    # (best 1, worst the floor): a scout's or another policy's return never moves a policy.
    opt = started_dipole(2, two_optima)
    weights = PolicyImportance().slot_weights
    _, index, valid = importance_sets(opt.owner, opt.rewards, opt.num_policies, opt.M)
    before = weights(opt, index, valid)
    filled = valid.sum(-1) > 1
    assert torch.allclose(before[filled, 0], torch.ones_like(before[filled, 0]))
    assert torch.allclose(before[valid].min(), torch.tensor(opt.reward_scale.floor, dtype=F64))
    # A far worse return elsewhere (a scout's) changes nothing.
    opt.archive.append(
        torch.zeros(1, 2, dtype=F64), torch.tensor([-1e9], dtype=F64), torch.tensor([-1])
    )
    assert torch.equal(weights(opt, index, valid), before)


@pytest.mark.parametrize("seed", range(6))
def test_the_host_step_is_the_tensor_step(seed):
    # PolicyImportance.power_step on the CPU (Python scalars, the active policies alone) and
    # on any other device (tensor operations, here on the CPU): the same means, bit for bit,
    # and the same archive, with retired policies, scouts and partly filled sets.
    opt = started_dipole(2, two_optima)
    g = torch.Generator().manual_seed(seed)
    for _ in range(int(torch.randint(3, 30, (1,), generator=g))):
        theta = opt.ask()
        opt.tell(theta, two_optima(theta))
    k = opt.num_policies
    opt.policy_set.active = torch.rand(k, generator=g) < 0.6
    scouts = torch.randn(3, 2, generator=g, dtype=F64)
    opt.archive.append(scouts, two_optima(scouts), torch.full((3,), -1))
    results = []
    for step in ("_host_step", "_tensor_step"):
        copy = started_dipole(2, two_optima)
        copy.load_state_dict(opt.state_dict())
        getattr(PolicyImportance(), step)(copy)
        results.append((copy.policy_means, copy.archive.thetas, copy.archive.owner))
    for host, tensor in zip(*results, strict=True):
        assert torch.equal(host, tensor)


@pytest.mark.parametrize("seed", range(4))
def test_mean_rewards_host_and_tensor_paths_agree(seed):
    from dipole_torch.archive import SampleArchive

    g = torch.Generator().manual_seed(seed)
    n, k = int(torch.randint(0, 40, (1,), generator=g)), int(torch.randint(1, 6, (1,), generator=g))
    archive = SampleArchive(2, torch.device("cpu"))
    archive.append(
        torch.randn(n, 2, generator=g, dtype=F64),
        torch.randn(n, generator=g, dtype=F64) * 10.0 ** float(torch.randint(-3, 4, (1,))),
        torch.randint(-1, k, (n,), generator=g),
    )
    assert torch.equal(archive.mean_rewards(k), archive._tensor_mean_rewards(k))


def test_powers_first_batch_is_n0_and_its_exploration_decays_to_its_floor():
    """PoWER's first batch has ``n0`` rows (default M), and after iteration t its
    exploration is Σ_start · max(decay^t, min_exploration): 0.5, 0.25, 0.125, then the
    floor 0.1."""
    assert Power([0.0], 1.0, M=3).ask().shape[0] == 3
    sigma = torch.diag(torch.tensor([1.0, 4.0], dtype=F64))
    opt = Power(torch.zeros(2, dtype=F64), sigma, M=3, n0=7, exploration_decay=0.5,
                min_exploration=0.1, generator=torch.Generator().manual_seed(0))  # fmt: skip
    theta = opt.ask()
    assert theta.shape[0] == 7
    opt.tell(theta, -theta.square().sum(-1))
    for factor in (0.5, 0.25, 0.125, 0.1, 0.1):
        theta = opt.ask()
        opt.tell(theta, -theta.square().sum(-1))
        torch.testing.assert_close(opt.policy_covariances[0], factor * sigma)


def test_power_keeps_m_samples_of_its_first_batch_and_refuses_a_zero_floor():
    """After the first batch PoWER keeps its importance set, the M best samples, not one
    more; ``min_exploration`` must lie in (0, 1] (0 would let the exploration vanish)."""
    opt = Power([0.0, 0.0], 1.0, M=3, n0=7, generator=torch.Generator().manual_seed(0))
    theta = opt.ask()
    rewards = -theta.square().sum(-1)
    opt.tell(theta, rewards)
    assert torch.equal(opt.rewards.sort().values, rewards.sort().values[-3:])
    with pytest.raises(ValueError, match=r"min_exploration must lie in \(0, 1\]"):
        Power([0.0], 1.0, exploration_decay=0.5, min_exploration=0.0)


def test_powers_defaults_are_written_out():
    # The paper's M = 5 and n0 = M, and the defaults the docstring states, written out here
    # (not read from the signature).
    opt = Power([0.0, 0.0], 0.5)
    settings = opt._settings()  # what a checkpoint records and a resume compares
    assert (settings["M"], settings["n0"], settings["reward_range"]) == (5, 5, None)
    assert settings["reward_floor"] == 1e-3 and settings["exploration_decay"] == 1.0
    assert settings["min_exploration"] == 1e-2 and settings["best_evaluations"] == 1
    assert opt.ask().shape == (5, 2)


@pytest.mark.parametrize("n0", [0, -1, 2.5, True, "5"])
def test_power_refuses_a_bad_n0_naming_it(n0):
    with pytest.raises(ValueError, match=r"n0 \(initial samples\) must be a positive integer"):
        Power([0.0], 1.0, n0=n0)
