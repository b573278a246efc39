"""Mountain-car task: dynamics, walls, returns, batching, input checks."""

import math

import pytest
import torch
from conftest import torch_engine_agreement
from dipole_torch.tasks.mountain_car import MountainCarTask

PUMPING = [1.0, 1.0, -10.0, -100.0]  # reaches the goal within 60 steps from every start
ENGINES = pytest.mark.parametrize("engine", ["python", "torch"])


def test_step_follows_the_paper_equation():
    task = MountainCarTask(dtype=torch.float64)
    state = torch.tensor([[-0.5, 0.01], [0.2, -0.02]], dtype=torch.float64)
    force = torch.tensor([4.0, -4.0], dtype=torch.float64)
    out = task.step(state, force)
    for i in range(2):
        x, v = state[i].tolist()
        v_new = v + 0.001 * force[i].item() - 0.0055 * math.cos(3 * x)
        assert out[i].tolist() == pytest.approx([x + v_new, v_new])


def test_velocity_clipped_and_walls_stop_the_car():
    task = MountainCarTask(dtype=torch.float64)
    fast = task.step(torch.tensor([[0.0, 0.069]], dtype=torch.float64), torch.tensor([4.0]))
    assert fast[0, 1].item() <= 0.07
    wall = task.step(torch.tensor([[-1.49, -0.07]], dtype=torch.float64), torch.tensor([-4.0]))
    assert wall[0].tolist() == [-1.5, 0.0]


@ENGINES
def test_cannot_climb_directly_but_pumping_reaches_the_goal(engine):
    task = MountainCarTask(engine=engine)
    starts = torch.stack([torch.linspace(-0.6, -0.4, 21), torch.zeros(21)], dim=-1)
    always_forward = task.evaluate(torch.zeros(21, 4), initial_state=starts)  # sign(0) = +
    right_of_valley = starts[:, 0] > -0.52  # the valley floor is at -π/6 ≈ -0.524
    assert (always_forward[right_of_valley] == 0).all()
    assert (always_forward[starts[:, 0] < -0.55] > 0).all()  # rolling down first is enough
    r = task.evaluate(torch.tensor([PUMPING]).expand(21, 4), initial_state=starts)
    assert (r >= 101 - 60).all() and (r <= 100).all()


@ENGINES
def test_return_counts_steps_to_goal(engine):
    task = MountainCarTask(dtype=torch.float64, engine=engine)
    theta = torch.tensor([PUMPING], dtype=torch.float64)
    state = torch.tensor([[-0.5, 0.0]], dtype=torch.float64)
    t = 0
    while not task.at_goal(state).item():
        state = task.step(state, task.policy(theta, state))
        t += 1
    r = task.evaluate(theta, initial_state=torch.tensor([-0.5, 0.0]))
    assert r.item() == 101 - t


@ENGINES
def test_returns_in_reward_range_and_scale_invariance(engine):
    task = MountainCarTask(engine=engine)
    generator = torch.Generator().manual_seed(0)
    theta = torch.randn(2000, 4, generator=generator) * task.sigma_start.diag().sqrt()
    r = task.evaluate(theta, torch.Generator().manual_seed(1))
    assert r.shape == (2000,) and (r >= 0).all() and (r <= 100).all()
    assert 0.01 < (r > 0).float().mean() < 0.2  # a few random draws succeed
    assert torch.equal(task.evaluate(theta[:50]), task.evaluate(theta[:50] * 7.5))


@ENGINES
def test_batch_independence_and_determinism(engine):
    task = MountainCarTask(engine=engine)
    generator = torch.Generator().manual_seed(2)
    theta = torch.tensor(PUMPING) + torch.randn(8, 4, generator=generator) * torch.tensor(
        [0.5, 0.5, 5.0, 50.0]
    )
    batched = task.evaluate(theta)
    assert torch.equal(batched, task.evaluate(theta))
    alone = torch.cat([task.evaluate(row.unsqueeze(0)) for row in theta])
    assert torch.equal(batched, alone)
    starts = task.sample_initial_state(8, generator)
    assert (starts[:, 0] >= -0.6).all() and (starts[:, 0] <= -0.4).all()
    assert (starts[:, 1] == 0).all()
    batched = task.evaluate(theta, initial_state=starts)
    alone = torch.cat(
        [task.evaluate(t[None], initial_state=s) for t, s in zip(theta, starts, strict=True)]
    )
    assert torch.equal(batched, alone)


def test_engines_agree_on_random_policies_and_starts():
    """The Python episodes and the batched torch rollout (float32 and float64) give the same
    returns (measured: all equal; the margin allows a trajectory grazing the goal)."""
    generator = torch.Generator().manual_seed(0)
    spread = torch.tensor([0.5, 0.5, 5.0, 50.0])
    theta = torch.tensor(PUMPING) + torch.randn(500, 4, generator=generator) * spread
    python = MountainCarTask(engine="python")
    theta = torch.cat(
        (theta, torch.randn(500, 4, generator=generator) * python.sigma_start.diag().sqrt())
    )
    starts = python.sample_initial_state(theta.shape[0], generator)
    returns = python.evaluate(theta, initial_state=starts)
    assert (
        returns.dtype == torch.float32 and (returns > 0).sum() > 300 and (returns == 0).sum() > 300
    )
    assert min(torch_engine_agreement(MountainCarTask, theta, starts, returns)) >= 0.995


def test_engine_choice():
    assert MountainCarTask().engine == "python"  # on the CPU
    assert MountainCarTask(compile=True).engine == "torch"
    with pytest.raises(ValueError, match="engine must be one of"):
        MountainCarTask(engine="jax")


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"steps": -5}, "steps"),
        ({"goal_position": 2.0}, "goal_position"),
        ({"alpha": -0.001}, "alpha"),
        ({"beta": float("nan")}, "beta"),
        ({"exploration_std": 0.0}, "exploration_std"),
    ],
)
def test_bad_constructor_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        MountainCarTask(**kwargs)


def test_bad_evaluate_inputs():
    task = MountainCarTask()
    with pytest.raises(ValueError, match="shape"):
        task.evaluate(torch.zeros(4))
    with pytest.raises(ValueError, match="non-finite"):
        task.evaluate(torch.tensor([[float("inf"), 0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="initial_state"):
        task.evaluate(torch.zeros(1, 4), initial_state=torch.zeros(3))


def test_start_distribution_shapes():
    task = MountainCarTask()
    assert task.theta0.shape == (4,) and task.sigma_start.shape == (4, 4)
    assert task.reward_range == (0.0, 100.0)


def test_bfloat16_rollouts_count_their_steps_exactly():
    gains = torch.tensor([[0.0, 0.0, 10.0, 100.0]])
    wide = MountainCarTask(engine="torch", dtype=torch.float64, steps=500)
    narrow = MountainCarTask(engine="torch", dtype=torch.bfloat16, steps=500)
    for x in torch.linspace(-1.2, 0.3, 7):
        start = torch.tensor([float(x), 0.0])
        expected = float(wide.evaluate(gains.double(), initial_state=start.double()))
        got = float(narrow.evaluate(gains.bfloat16(), initial_state=start.bfloat16()))
        assert got == float(torch.tensor(expected, dtype=torch.bfloat16)) or abs(got - expected) < 8


def test_a_start_outside_the_walls_or_too_fast_is_refused():
    task = MountainCarTask()
    for start in ([100.0, 0.0], [-0.5, 1.0]):
        with pytest.raises(ValueError, match="initial_state must lie between the walls"):
            task.evaluate(task.theta0[None], initial_state=torch.tensor(start))
    with pytest.raises(ValueError, match="dtype must be a floating torch dtype"):
        MountainCarTask(dtype=torch.int64)


def test_the_speed_limit_is_the_papers():
    task = MountainCarTask()
    assert task.max_speed == 0.07 and task.force == 4.0
    x, velocity = (
        torch.tensor([-0.5], dtype=torch.float64),
        torch.tensor([0.5], dtype=torch.float64),
    )
    task._step_(x, velocity, torch.tensor([4.0], dtype=torch.float64))
    assert float(velocity) == 0.07
