"""PolicySet (every per-policy tensor, re-indexed together) and SampleArchive (the kept
samples and their owners)."""

import math

import pytest
import torch

from dipole_torch import Dipole, Power
from dipole_torch.archive import SampleArchive
from dipole_torch.policy_set import PolicyField, PolicySet

F64 = torch.float64


def three_policies() -> PolicySet:
    policies = PolicySet(
        torch.arange(6, dtype=F64).reshape(3, 2), torch.eye(2, dtype=F64).repeat(3, 1, 1)
    )
    policies.register("success", PolicyField(default=0.5))
    policies.register("paths", PolicyField(shape=(2,)))
    return policies


def test_one_index_reindexes_every_tensor_and_ids_stay_with_their_policy():
    policies = three_policies()
    policies.success = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    policies.active = torch.tensor([True, False, True])
    policies.index(torch.tensor([2, 0]))
    assert policies.means.tolist() == [[4.0, 5.0], [0.0, 1.0]]
    assert policies.success.tolist() == [0.3, 0.1] and policies.active.tolist() == [True, True]
    assert policies.ids.tolist() == [2, 0] and policies.paths.shape == (2, 2)
    policies.extend(torch.zeros(2, 2, dtype=F64), torch.eye(2, dtype=F64).repeat(2, 1, 1))
    assert policies.ids.tolist() == [2, 0, 3, 4]  # new numbers, never reused
    assert policies.success.tolist() == [0.3, 0.1, 0.5, 0.5]  # new policies at the default
    policies.reset_fields(torch.tensor([True, False, False, False]))
    assert policies.success.tolist() == [0.5, 0.1, 0.5, 0.5]
    policies.reset(torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None])
    assert (
        policies.ids.tolist() == [5] and len(policies) == 1 and policies.success.tolist() == [0.5]
    )


def test_fields_are_registered_once_and_unknown_ones_refused():
    policies = three_policies()
    with pytest.raises(ValueError, match="'success' exists already"):
        policies.register("success", PolicyField())
    with pytest.raises(AttributeError, match="no field 'speed'"):
        policies.speed = torch.zeros(3)
    with pytest.raises(ValueError, match="unknown policy field"):
        policies.extend(torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None], speed=1)


def test_a_state_of_another_shape_is_refused_naming_the_key():
    policies = three_policies()
    state = policies.state_dict()
    other = three_policies()
    other.load_state_dict(state, torch.device("cpu"))
    assert torch.equal(other.means, policies.means) and other.next_id == policies.next_id
    bad = dict(state, success=torch.zeros(2, dtype=F64))
    with pytest.raises(ValueError, match=r"state_dict\['success'\] must have shape \[3\]"):
        other.load_state_dict(bad, torch.device("cpu"))
    old = {k: v for k, v in state.items() if k not in ("paths", "policy_ids", "next_policy_id")}
    other.load_state_dict(old, torch.device("cpu"))  # a checkpoint from before them
    assert other.paths.abs().sum() == 0 and other.ids.tolist() == [0, 1, 2]


def test_a_checkpoint_without_the_next_id_numbers_new_policies_after_its_own():
    """A state from before ``next_policy_id`` was saved: new policies are numbered from its
    largest id + 1, never again one of its policies' ids (a policy's id is its own)."""
    policies = three_policies()
    policies.index(torch.tensor([2, 0]))  # ids 2, 0
    state = policies.state_dict()
    del state["next_policy_id"]
    other = three_policies()
    other.load_state_dict(state, torch.device("cpu"))
    other.extend(torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64)[None])
    assert other.ids.tolist() == [2, 0, 3]


def test_a_core_name_is_no_field_and_state_dicts_are_copies_unless_asked():
    """``register`` refuses the core tensors' names (a field "means" would reset the policy
    means to its default); ``state_dict()`` copies every tensor, ``copy=False`` gives the
    tensors themselves."""
    policies = three_policies()
    for name in PolicySet.CORE:
        with pytest.raises(ValueError, match=f"{name!r} exists already"):
            policies.register(name, PolicyField())
    assert policies.means.tolist() == [[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]]
    state, shared = policies.state_dict(), policies.state_dict(copy=False)
    policies.means.add_(1.0)
    policies.success.fill_(0.9)
    assert state["policy_means"][0].tolist() == [0.0, 1.0] and state["success"][0] == 0.5
    assert shared["policy_means"] is policies.means and shared["success"] is policies.success


def test_exploration_factors_stand_in_the_identity_where_a_covariance_does_not_factorise():
    """``(L, ok)``: each covariance's Cholesky factor, or the identity (not NaN) where it
    is not positive definite, with ok False there."""
    covariances = torch.stack(
        (
            torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=F64),
            torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=F64),  # indefinite
        )
    )
    policies = PolicySet(torch.zeros(2, 2, dtype=F64), covariances)
    factors, ok = policies.exploration_factors()
    assert ok.tolist() == [True, False]
    torch.testing.assert_close(factors[0], torch.linalg.cholesky(covariances[0]))
    assert torch.equal(factors[1], torch.eye(2, dtype=F64))


def test_the_exploration_factors_are_recomputed_once_written_into():
    # A memoised tuple of tensors is watched as a tensor is: a write into one of them costs a
    # recomputation, never a stale value (Memo's contract).
    policies = PolicySet(torch.zeros(2, 2, dtype=F64), torch.eye(2, dtype=F64).repeat(2, 1, 1))
    factors, ok = policies.exploration_factors()
    assert policies.exploration_factors()[0] is factors  # a hit
    factors[0, 0, 0] = 9.0
    ok[1] = False
    again, ok_again = policies.exploration_factors()
    assert torch.equal(again, torch.eye(2, dtype=F64).repeat(2, 1, 1))
    assert ok_again.tolist() == [True, True]


def test_the_archive_keeps_owners_with_their_samples():
    archive = SampleArchive(1, torch.device("cpu"))
    archive.append(
        torch.tensor([[0.0], [1.0], [2.0], [3.0], [4.0]], dtype=F64),
        torch.tensor([1.0, 5.0, 3.0, -2.0, 4.0], dtype=F64),
        torch.tensor([0, 1, 0, -1, 2]),
    )
    assert archive.per_policy("amax", 4).tolist() == [3.0, 5.0, 4.0, -math.inf]
    assert archive.per_policy("amin", 3).tolist() == [1.0, 5.0, 4.0]
    assert archive.mean_rewards(3).tolist() == [2.0, 5.0, 4.0]
    assert archive.counts(3).tolist() == [2, 1, 1]
    best = archive.best_samples(torch.full((4, 1), 9.0, dtype=F64))
    assert best[:, 0].tolist() == [2.0, 1.0, 4.0, 9.0]  # none kept: the mean
    archive.drop_policies(torch.tensor([True, False, True]))
    assert archive.owner.tolist() == [0, 0, -1, 1]  # policy 2 renumbered 1; scouts stay
    assert archive.thetas[:, 0].tolist() == [0.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize("path", ["host", "tensor"])
def test_each_policys_best_row_is_the_last_of_equal_returns(path, monkeypatch):
    """The repeats' rows and the best samples come from one search: of a policy's rows of
    equal best return, the last; a scout of equal return is no policy's. On the CPU it runs
    in Python numbers, elsewhere (here: beyond HOST_ROWS) in reductions (a sort and an
    indexed write would leave the choice among repeated indices to the device)."""
    if path == "tensor":
        monkeypatch.setattr("dipole_torch.archive.HOST_ROWS", 0)
    archive = SampleArchive(1, torch.device("cpu"))
    archive.append(
        torch.tensor([[0.0], [1.0], [2.0], [3.0], [4.0], [5.0], [6.0]], dtype=F64),
        torch.tensor([3.0, 3.0, 1.0, 7.0, 7.0, 9.0, 7.0], dtype=F64),
        torch.tensor([0, 0, 0, 1, 1, -1, 1]),
    )
    assert archive.best_row_index(3).tolist() == [1, 6, -1]
    assert archive.best_rows([1, 2, 0], 3) == [6, -1, 1]
    means = torch.full((3, 1), 9.5, dtype=F64)
    assert archive.best_samples(means)[:, 0].tolist() == [1.0, 6.0, 9.5]
    # By hand: the last row of each policy's largest return.
    owner, rewards = archive.owner.tolist(), archive.rewards.tolist()
    for policy in range(2):
        rows = [i for i, o in enumerate(owner) if o == policy]
        top = max(rewards[i] for i in rows)
        assert archive.best_row_index(3)[policy] == max(i for i in rows if rewards[i] == top)
    empty = SampleArchive(1, torch.device("cpu"))
    assert empty.best_row_index(2).tolist() == [-1, -1]
    assert torch.equal(empty.best_samples(means), means)


@pytest.mark.parametrize("build", [Dipole, Power])
def test_a_state_of_another_dimension_is_refused(build):
    three = build(torch.zeros(3, dtype=F64), 1.0, generator=torch.Generator().manual_seed(0))
    theta = three.ask()
    three.tell(theta, -theta.square().sum(-1))
    two = build(torch.zeros(2, dtype=F64), 1.0)
    before = two.state_dict()
    with pytest.raises(ValueError, match=r"of dimension D = 3; this one has D = 2"):
        two.load_state_dict(three.state_dict())
    # Without the settings (which name the dimension first), the archive's own check.
    state = {key: value for key, value in three.state_dict().items() if key != "settings"}
    with pytest.raises(ValueError, match=r"state_dict\['thetas'\] must have shape \[N, 2\]"):
        two.load_state_dict(state)
    two.load_state_dict(before)


def test_the_archive_memos_follow_every_change():
    # per_policy, counts and best_samples are memoised while the archive stands still: a
    # tensor replaced or written into, or a memoised value written into, recomputes them.
    archive = SampleArchive(1, torch.device("cpu"))
    archive.append(
        torch.tensor([[0.0], [1.0], [2.0]], dtype=F64),
        torch.tensor([1.0, 5.0, 3.0], dtype=F64),
        torch.tensor([0, 1, -1]),
    )
    means = torch.zeros(2, 1, dtype=F64)
    best = archive.per_policy("amax", 2)
    assert archive.per_policy("amax", 2) is best  # a hit
    archive.rewards[0] = 7.0  # written into
    assert archive.per_policy("amax", 2).tolist() == [7.0, 5.0]
    archive.owner = torch.tensor([0, 0, -1])  # replaced
    assert archive.per_policy("amax", 2).tolist() == [7.0, -math.inf]
    assert archive.counts(2).tolist() == [2, 0]
    assert archive.best_samples(means)[:, 0].tolist() == [0.0, 0.0]
    archive.thetas[0, 0] = 4.0
    assert archive.best_samples(means)[:, 0].tolist() == [4.0, 0.0]
    archive.best_samples(means)[0, 0] = 9.0  # a memoised value written into
    assert archive.best_samples(means)[:, 0].tolist() == [4.0, 0.0]
    assert archive.per_policy("amax", 3).tolist() == [7.0, -math.inf, -math.inf]
    with torch.inference_mode():  # no version counters: nothing memoised, same numbers
        frozen = SampleArchive(1, torch.device("cpu"))
        frozen.append(archive.thetas.clone(), archive.rewards.clone(), archive.owner.clone())
        assert frozen.per_policy("amax", 2).tolist() == [7.0, -math.inf]
        assert frozen.best_samples(means)[:, 0].tolist() == [4.0, 0.0]
