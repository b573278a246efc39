"""The gymnasium environments: registration, env checker, same returns as the batched tasks."""

import dipole_torch.tasks  # noqa: F401  (registers the environments)
import gymnasium as gym
import numpy as np
import pytest
import torch
from dipole_torch.tasks.cartpole import CartPoleTask
from dipole_torch.tasks.mountain_car import MountainCarTask
from gymnasium.utils.env_checker import check_env

ENV_IDS = ["dipole/CartPole-v0", "dipole/MountainCar-v0"]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_env_checker_passes(env_id):
    env = gym.make(env_id)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def _gym_return(env, task, theta, initial_state, to_action):
    obs, _ = env.reset(seed=0, options={"initial_state": initial_state})
    total, done = 0.0, False
    while not done:
        u = task.policy(theta.unsqueeze(0), torch.from_numpy(obs).unsqueeze(0))[0]
        obs, reward, terminated, truncated, _ = env.step(to_action(u))
        total += reward
        done = terminated or truncated
    return total


@pytest.mark.parametrize(
    "theta",
    [[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 12.0, 1.0], [0.91, 2.14, 30.9, 7.9], [0.5, 0.3, 8.0, 0.2]],
)
@pytest.mark.parametrize("engine", ["torch", "python"])
def test_cartpole_env_return_equals_batched_rollout(theta, engine):
    env = gym.make("dipole/CartPole-v0", steps=300, engine=engine)
    task = env.unwrapped.task
    theta = torch.tensor(theta)
    start = task.sample_initial_state(1, torch.Generator().manual_seed(5))[0]
    expected = task.evaluate(theta.unsqueeze(0), initial_state=start).item()
    got = _gym_return(env, task, theta, start.numpy(), lambda u: u.numpy().reshape(1))
    assert got == expected


@pytest.mark.parametrize(
    "theta", [[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, -10.0, -100.0], [0.5, 1.0, -10.0, -100.0]]
)
@pytest.mark.parametrize("x0", [-0.6, -0.45])
@pytest.mark.parametrize("engine", ["torch", "python"])
def test_mountain_car_env_return_equals_batched_rollout(theta, x0, engine):
    env = gym.make("dipole/MountainCar-v0", engine=engine)
    task = env.unwrapped.task
    theta = torch.tensor(theta)
    start = np.array([x0, 0.0], dtype=np.float32)
    expected = task.evaluate(theta.unsqueeze(0), initial_state=torch.from_numpy(start)).item()
    got = _gym_return(env, task, theta, start, lambda u: int(u.item() > 0))
    assert got == expected


def test_envs_use_the_task_physics_and_seeding():
    env = gym.make("dipole/CartPole-v0")
    assert isinstance(env.unwrapped.task, CartPoleTask)
    assert isinstance(gym.make("dipole/MountainCar-v0").unwrapped.task, MountainCarTask)
    first, _ = env.reset(seed=7)
    again, _ = env.reset(seed=7)
    assert np.array_equal(first, again)
    assert first[2] != 0 and abs(first[2]) <= 0.05


def test_env_bad_inputs():
    env = gym.make("dipole/CartPole-v0").unwrapped
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1, dtype=np.float32))
    with pytest.raises(ValueError, match="initial_state"):
        env.reset(options={"initial_state": [0.0, 0.0]})
    with pytest.raises(ValueError, match="options"):
        env.reset(options={"bogus": 1})
    car = gym.make("dipole/MountainCar-v0").unwrapped
    car.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        car.step(3)
