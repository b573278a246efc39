"""The ask/tell optimizers: interface, checkpoints, bad input."""

import pytest
import torch

from dipole_torch import Dipole, GaussianMixture, Power
from tasks.multimodal import MultimodalTask

F64 = torch.float64


def run(opt, task, trials):
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta))
    return opt


def make(cls, task, seed=0):
    return cls(
        task.theta0,
        task.sigma_start,
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


def test_bad_input_is_rejected_before_it_changes_anything():
    task = MultimodalTask()
    opt = make(Dipole, task)
    theta = opt.ask()
    with pytest.raises(ValueError, match="rewards contains non-finite"):
        opt.tell(theta, torch.tensor([0.5] * 9 + [float("nan")]))
    with pytest.raises(ValueError, match=r"rewards must have shape \[10\]"):
        opt.tell(theta, torch.ones(9))
    with pytest.raises(ValueError, match=r"theta must have shape \[10, 2\]"):
        opt.tell(theta[:, :1], torch.ones(10))
    with pytest.raises(ValueError, match="outside reward_range"):
        opt.tell(theta, torch.full((10,), 2.0))
    assert opt.trials == 0 and opt.thetas.numel() == 0
    opt.tell(theta, task.evaluate(theta))  # the same ask is still pending and valid
    assert opt.trials == 10


def test_tell_without_ask_and_positive_rewards_without_range():
    opt = Power(torch.zeros(2), torch.eye(2))
    with pytest.raises(RuntimeError, match="without a preceding ask"):
        opt.tell(torch.zeros(5, 2), torch.ones(5))
    theta = opt.ask()
    with pytest.raises(ValueError, match="rewards must be positive"):
        opt.tell(theta, -torch.ones(theta.shape[0]))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"sigma_start": -torch.eye(2)}, "sigma_start is not positive definite"),
        ({"sigma_start": torch.eye(3)}, r"sigma_start must have shape \[2, 2\]"),
        ({"theta0": torch.zeros(2, 1)}, r"theta0 must have shape \[N\]"),
        ({"theta0": torch.tensor([0.0, float("nan")])}, "theta0 contains non-finite"),
        ({"alpha": 0.0}, "alpha"),
        ({"m": 0}, "m \\(auxiliary components\\)"),
        ({"M": 0}, "M \\(importance-set size\\)"),
        ({"n0": -1}, "n0"),
        ({"reward_range": (1.0, 0.0)}, "high > low"),
        ({"cluster_every": 0}, "cluster_every"),
    ],
)
def test_bad_constructor_arguments(kwargs, message):
    args = {"theta0": torch.zeros(2), "sigma_start": torch.eye(2)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Dipole(**args)
