"""Cart-pole task: physics against gymnasium, rewards, batching, input checks."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from conftest import torch_engine_agreement
from dipole_torch.tasks.cartpole import CartPoleTask

LQR_GAIN = [0.91, 2.14, 30.9, 7.9]  # discrete LQR, Q = diag(1, 1, 10, 1), R = 1
ENGINES = pytest.mark.parametrize("engine", ["python", "torch"])


def test_step_matches_gymnasium_cartpole_v1():
    """Same state and force (±force_mag): our step equals gymnasium's CartPole-v1 step."""
    env = gym.make("CartPole-v1").unwrapped
    task = CartPoleTask(dtype=torch.float64)
    rng = np.random.default_rng(0)
    for _ in range(20):
        state = rng.uniform(-0.2, 0.2, size=4)
        action = int(rng.integers(2))
        env.reset(seed=0)
        env.state = state.copy()
        expected, *_ = env.step(action)
        force = torch.tensor([10.0 if action == 1 else -10.0], dtype=torch.float64)
        ours = task.step(torch.tensor(state).unsqueeze(0), force)[0].numpy()
        np.testing.assert_allclose(ours, expected, rtol=1e-6, atol=1e-6)  # gym returns float32


def test_pole_falls_freely_the_way_it_leans():
    """No force: a leaning pole accelerates away from vertical, the cart recoils."""
    task = CartPoleTask(dtype=torch.float64)
    state = torch.tensor([[0.0, 0.0, 0.01, 0.0]], dtype=torch.float64)
    angles, positions = [], []
    for _ in range(40):
        state = task.step(state, torch.zeros(1, dtype=torch.float64))
        angles.append(state[0, 2].item())
        positions.append(state[0, 0].item())
    assert all(
        b > a for a, b in zip(angles[1:], angles[2:], strict=False)
    )  # monotone fall to the right
    assert positions[-1] < 0  # the cart is pushed the other way
    # Small-angle linearisation: φ̈ ≈ g φ / (l (4/3 - m_p / m_total)).
    rate = math.sqrt(task.gravity / (task.length * (4 / 3 - task.masspole / task.total_mass)))
    state = torch.tensor([[0.0, 0.0, 1e-3, 0.0]], dtype=torch.float64)
    state = task.step(state, torch.zeros(1, dtype=torch.float64))
    assert state[0, 3].item() / 1e-3 == pytest.approx(rate**2 * task.tau, rel=1e-3)


@ENGINES
def test_upright_pole_at_rest_stays_and_scores_every_step(engine):
    task = CartPoleTask(engine=engine)
    r = task.evaluate(torch.tensor([[1.0, 2.0, 30.0, 5.0]]), initial_state=torch.zeros(4))
    assert r.item() == 1000.0


@ENGINES
def test_no_control_fails_and_return_counts_absorbing_penalty(engine):
    task = CartPoleTask(steps=200, engine=engine)
    r = task.evaluate(torch.zeros(1, 4), initial_state=torch.tensor([0.0, 0.0, 0.04, 0.0]))
    # Manual rollout: +1 while |φ| < π/60, 0 in between, -1 from the failing step on.
    state, total, failed = torch.tensor([[0.0, 0.0, 0.04, 0.0]]), 0.0, False
    for _ in range(200):
        if not failed:
            state = task.step(state, torch.zeros(1))
            failed = bool(task.failed(state))
        angle = abs(state[0, 2].item())
        total += -1.0 if failed else (1.0 if angle < math.pi / 60 else 0.0)
    assert failed and r.item() == total
    assert -200 < r.item() < 0


@ENGINES
def test_returns_in_reward_range_and_good_policy_scores_high(engine):
    task = CartPoleTask(engine=engine)
    generator = torch.Generator().manual_seed(0)
    theta = task.theta0 + torch.randn(500, 4, generator=generator) * task.sigma_start.diag().sqrt()
    r = task.evaluate(theta, generator)
    low, high = task.reward_range
    assert r.shape == (500,) and (r >= low).all() and (r <= high).all()
    assert task.evaluate(task.theta0.unsqueeze(0)).item() < -900  # θ0: no control
    good = task.evaluate(torch.tensor([LQR_GAIN]).expand(100, 4), generator)
    assert (good >= 990).all()


@ENGINES
def test_batch_independence(engine):
    task = CartPoleTask(engine=engine)
    generator = torch.Generator().manual_seed(1)
    theta = torch.tensor(LQR_GAIN) + 5 * torch.randn(6, 4, generator=generator)
    batched = task.evaluate(theta)
    alone = torch.cat([task.evaluate(row.unsqueeze(0)) for row in theta])
    assert torch.equal(batched, alone)
    starts = task.sample_initial_state(6, generator)
    batched = task.evaluate(theta, initial_state=starts)
    alone = torch.cat(
        [task.evaluate(t[None], initial_state=s) for t, s in zip(theta, starts, strict=True)]
    )
    assert torch.equal(batched, alone)


@ENGINES
def test_determinism_and_generator(engine):
    task = CartPoleTask(engine=engine)
    theta = torch.tensor([[0.0, 0.0, 12.0, 1.0]]).expand(50, 4)
    assert torch.equal(task.evaluate(theta), task.evaluate(theta))
    one = task.evaluate(theta, torch.Generator().manual_seed(3))
    assert torch.equal(one, task.evaluate(theta, torch.Generator().manual_seed(3)))
    assert one.unique().numel() > 1  # different random starts per row
    starts = task.sample_initial_state(1000, torch.Generator().manual_seed(0))
    assert (starts[:, [0, 1, 3]] == 0).all() and (starts[:, 2].abs() <= 0.05).all()


def test_float64_matches_float32_for_robust_policy():
    theta = torch.tensor([LQR_GAIN])
    r32 = CartPoleTask().evaluate(theta)
    r64 = CartPoleTask(dtype=torch.float64).evaluate(theta.double())
    assert r32.item() == r64.item()


def test_engines_agree_on_random_policies_and_starts():
    """The Python episodes and the batched torch rollout (float32 and float64) give the same
    returns: the same physics, policy, failure test and counting (measured: 2000 of 2000
    equal; a trajectory grazing a threshold may differ in the last bit, hence the margin)."""
    generator = torch.Generator().manual_seed(0)
    spread = torch.tensor([1.0, 1.0, 10.0, 3.0])
    theta = torch.tensor(LQR_GAIN) + torch.randn(1000, 4, generator=generator) * spread
    theta = torch.cat((theta, torch.randn(200, 4, generator=generator)))  # mostly failing
    python = CartPoleTask(engine="python")
    starts = python.sample_initial_state(theta.shape[0], generator)
    returns = python.evaluate(theta, initial_state=starts)
    assert returns.dtype == torch.float32 and 100 < (returns == 1000).sum() < 1000
    assert (returns < 0).sum() > 200  # failures, stopped early, counted at -1 a step
    assert min(torch_engine_agreement(CartPoleTask, theta, starts, returns)) >= 0.995


def test_engine_choice():
    assert CartPoleTask().engine == "python"  # on the CPU
    assert CartPoleTask(compile=True).engine == "torch"
    assert CartPoleTask(engine="torch").engine == "torch"
    with pytest.raises(ValueError, match="engine must be one of"):
        CartPoleTask(engine="numpy")
    with pytest.raises(ValueError, match="engine='torch'"):
        CartPoleTask(engine="python", compile=True)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"steps": -1}, "steps"),
        ({"steps": 0}, "steps"),
        ({"force_limit": 0.0}, "force_limit"),
        ({"initial_angle": 1.0}, "initial_angle"),
        ({"theta0": [0.0, 1.0]}, "theta0"),
        ({"steps": True}, "steps"),  # a bool is no count
        ({"theta0": [[0.0, 0.0, 0.0, 0.0]]}, "theta0"),  # 4 numbers, but not a [4] vector
        ({"exploration_std": [1.0, -1.0, 1.0, 1.0]}, "exploration_std"),
    ],
)
def test_bad_constructor_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        CartPoleTask(**kwargs)


def test_bad_evaluate_inputs():
    task = CartPoleTask()
    with pytest.raises(ValueError, match="shape"):
        task.evaluate(torch.zeros(3, 5))
    with pytest.raises(ValueError, match="non-finite"):
        task.evaluate(torch.tensor([[float("nan"), 0.0, 0.0, 0.0]]))
    with pytest.raises(TypeError, match="theta"):
        task.evaluate([[0.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="initial_state"):
        task.evaluate(torch.zeros(2, 4), initial_state=torch.zeros(3, 4))


def test_without_a_generator_every_episode_starts_from_the_default_seeds_draw():
    task = CartPoleTask(default_seed=5)
    start = task.sample_initial_state(1, torch.Generator().manual_seed(task.default_seed))
    theta = torch.tensor([[0.5, 0.3, 8.0, 0.2], [0.0, 0.0, 0.0, 0.0]])
    torch.testing.assert_close(task.evaluate(theta), task.evaluate(theta, initial_state=start[0]))


def test_a_start_beyond_the_tasks_dtype_is_refused():
    task = CartPoleTask()  # float32: 1e39 is beyond its range
    with pytest.raises(ValueError, match="initial_state holds values beyond the task's"):
        task.evaluate(
            torch.zeros(1, 4),
            initial_state=torch.tensor([0.0, 0.0, 1e39, 0.0], dtype=torch.float64),
        )


def test_a_rollout_leaves_the_thread_count_as_it_was():
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        CartPoleTask(engine="torch", steps=5).evaluate(torch.zeros(3, 4))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(previous)


def test_a_task_that_describes_nothing_gives_one_empty_line_per_policy():
    # EpisodicTask's defaults, which results.json's policies index by policy.
    task, theta = CartPoleTask(), torch.zeros(3, 4)
    assert task.describe_policies(theta) == ["", "", ""]
    assert task.policy_scalars(theta) == {} and task.describe_policy_set(theta) == ""
    assert task.plot_policies(theta) is None


def test_start_distribution_shapes():
    task = CartPoleTask()
    assert task.theta0.shape == (4,) and task.sigma_start.shape == (4, 4)
    assert task.reward_range == (-1000.0, 1000.0)
    torch.linalg.cholesky(task.sigma_start)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_rollouts_count_their_steps_exactly(dtype):
    # The counters are integers: in bfloat16 one by one they stalled at 256 and the returns
    # left the reward range (6464 of 5000 steps).
    gains = torch.tensor([[1.0, 2.0, 30.0, 5.0]])
    task = CartPoleTask(steps=5000, engine="torch", dtype=dtype)
    value = float(task.evaluate(gains, generator=torch.Generator().manual_seed(0)))
    low, high = task.reward_range
    assert low <= value <= high and value == float(torch.tensor(high, dtype=dtype))


def test_theta_beyond_the_tasks_dtype_is_refused_not_rolled_out():
    task = CartPoleTask(engine="python")  # float32
    with pytest.raises(ValueError, match="beyond the task's torch.float32 range"):
        task.evaluate(torch.tensor([[1e300, 0.0, 0.0, 0.0]], dtype=torch.float64))
    huge = torch.tensor([[1e30, 1e30, 1e30, 1e30]])  # finite in float32: the force saturates
    returns = [CartPoleTask(engine=e).evaluate(huge) for e in ("python", "torch")]
    assert torch.equal(returns[0], returns[1])


def test_a_dtype_is_a_floating_dtype_or_its_name():
    assert CartPoleTask(dtype="float64").dtype == torch.float64
    for bad in (torch.int64, "int32", "no_such_dtype"):
        with pytest.raises(ValueError, match="dtype must be a floating torch dtype or its name"):
            CartPoleTask(dtype=bad)


def test_the_python_engine_is_the_torch_engines_physics_where_each_term_counts():
    # Episodes where the force clip and the φ̇² sin φ term change the count: the default CPU
    # engine (Python floats) must match the torch engine (gymnasium's step) exactly there.
    cases = [
        ([0.0, 0.0, 400.0, 0.0], [0.0, 0.0, 0.04, 0.0]),  # the force clip: −949
        ([0.91, 2.14, 30.9, 7.9], [0.0, 0.0, 0.0, 1.5]),  # 917
        ([0.0, 0.0, 10.0, 0.5], [0.0, 0.0, -0.15, 1.0]),  # the φ̇² sin φ term: −975
    ]
    for gains, start in cases:
        theta, state = torch.tensor([gains], dtype=torch.float64), torch.tensor(start)
        returns = [
            CartPoleTask(engine=e, dtype=torch.float64).evaluate(theta, initial_state=state)
            for e in ("python", "torch")
        ]
        assert torch.equal(returns[0], returns[1]), (gains, start, returns)


def test_the_constants_are_gymnasiums_and_starts_lean_both_ways():
    env = gym.make("CartPole-v1").unwrapped
    task = CartPoleTask()
    assert task.angle_threshold == env.theta_threshold_radians  # 12°
    assert task.x_threshold == env.x_threshold
    angles = task.sample_initial_state(200, torch.Generator().manual_seed(0))[:, 2]
    assert bool((angles < 0).any() and (angles > 0).any())
    assert float(angles.abs().max()) <= task.initial_angle
