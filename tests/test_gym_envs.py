"""The gymnasium environments: registration and specs, env checker, same returns as the batched
tasks, observation bounds, rendering (rgb_array frames, RenderCollection, RecordVideo, human)."""

import math
import warnings

import dipole_torch.tasks  # noqa: F401  (registers the environments)
import gymnasium as gym
import numpy as np
import pytest
import torch
from dipole_torch.tasks.cartpole import CartPoleTask
from dipole_torch.tasks.gym_envs import _cartpole_bounds
from dipole_torch.tasks.mountain_car import MountainCarTask
from dipole_torch.tasks.rendering import (
    AXLE_COLOR,
    FLAG_COLOR,
    GROUND_COLOR,
    POLE_COLOR,
    WALL_COLOR,
    WHEEL_COLOR,
    Canvas,
)
from gymnasium.error import DependencyNotInstalled
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.passive_env_checker import env_render_passive_checker
from scipy import ndimage

ENV_IDS = ["dipole/CartPole-v1", "dipole/MountainCar-v0"]
DISPLAY_VARIABLES = ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_env_checker_passes_without_warnings(env_id):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(env_id)
        # The render check would also make render_mode="human", which needs a display: the
        # rgb_array mode is checked on its own below (and everything with a display, further on).
        check_env(env.unwrapped, skip_render_check=True)
        env.close()
        rendering = gym.make(env_id, render_mode="rgb_array")
        rendering.reset(seed=0)
        env_render_passive_checker(rendering.unwrapped)
        rendering.close()


@pytest.mark.parametrize(
    ("env_id", "horizon", "threshold"),
    [("dipole/CartPole-v1", 1000, 950.0), ("dipole/MountainCar-v0", 100, 50.0)],
)
def test_specs_carry_the_horizon_and_the_solved_threshold(env_id, horizon, threshold):
    spec = gym.spec(env_id)
    assert spec.max_episode_steps == horizon
    assert spec.reward_threshold == threshold
    env = gym.make(env_id)
    assert env.spec.max_episode_steps == env.unwrapped.task.steps == horizon
    assert env.spec.reward_threshold == threshold
    # The largest return the task allows is above the threshold.
    assert env.unwrapped.task.reward_range[1] > threshold


def test_a_longer_horizon_needs_max_episode_steps_as_the_docs_say():
    """gymnasium's TimeLimit cuts at the registered horizon whatever ``steps`` says: with
    ``steps=200`` alone, a mountain car that never reaches the goal returned 101 (the episode
    cut at 100, before its end's penalty); with ``max_episode_steps=200`` too, its 0."""
    returns = {}
    for extra in ({}, {"max_episode_steps": 200}):
        env = gym.make("dipole/MountainCar-v0", steps=200, **extra)
        env.reset(seed=0)
        total, steps, ended = 0.0, 0, False
        while not ended:
            _, reward, terminated, truncated, _ = env.step(0)  # full throttle backward
            total, steps, ended = total + reward, steps + 1, terminated or truncated
        returns[bool(extra)] = (steps, total)
    assert returns == {False: (100, 101.0), True: (200, 0.0)}


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
    env = gym.make("dipole/CartPole-v1", steps=300, engine=engine)
    task = env.unwrapped.task
    theta = torch.tensor(theta)
    start = task.sample_initial_state(1, torch.Generator().manual_seed(5))[0]
    expected = task.evaluate(theta.unsqueeze(0), initial_state=start).item()

    def push(u):  # the policy's force in newtons as the action, a fraction of force_limit
        return (u.double() / task.force_limit).numpy().reshape(1)

    assert _gym_return(env, task, theta, start.numpy(), push) == expected


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
    env = gym.make("dipole/CartPole-v1")
    assert isinstance(env.unwrapped.task, CartPoleTask)
    assert isinstance(gym.make("dipole/MountainCar-v0").unwrapped.task, MountainCarTask)
    first, _ = env.reset(seed=7)
    again, _ = env.reset(seed=7)
    assert np.array_equal(first, again)
    assert first[2] != 0 and abs(first[2]) <= 0.05


def test_reset_seeds_draw_different_starts_and_unseeded_resets_go_on_drawing():
    env = gym.make("dipole/CartPole-v1")
    first, _ = env.reset(seed=7)
    other, _ = env.reset(seed=8)
    following, _ = env.reset()
    assert len({first[2], other[2], following[2]}) == 3


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_a_truncated_episode_has_ended(env_id):
    # A zero push keeps the pole up and the car short of the goal for three steps.
    env = gym.make(env_id, steps=3).unwrapped
    env.reset(seed=0)
    action = np.zeros(1) if "CartPole" in env_id else 0
    for _ in range(3):
        _, _, terminated, truncated, _ = env.step(action)
    assert truncated and not terminated
    with pytest.raises(RuntimeError, match="episode has ended"):
        env.step(action)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_editing_an_observation_leaves_the_environment_be(env_id):
    runs = []
    for edit in (False, True):
        env = gym.make(env_id).unwrapped
        observation, _ = env.reset(seed=0)
        if edit:
            observation += 0.01
        action = np.ones(1) if "CartPole" in env_id else 1
        runs.append(env.step(action)[0])
    np.testing.assert_array_equal(runs[0], runs[1])


def test_cartpole_spaces_are_the_documented_bounds():
    # The docstring's table and Starting State: ±2.4 m, ±2·2.4/τ, ±12°, ±2·12°/τ live, and
    # the observation bounds derived from them, widened by 0.1%, for the default task.
    env = gym.make("dipole/CartPole-v1").unwrapped
    twelve_degrees = math.radians(12)
    np.testing.assert_allclose(
        env.start_space.high, [2.4, 2 * 2.4 / 0.02, twelve_degrees, 2 * twelve_degrees / 0.02]
    )
    np.testing.assert_allclose(
        env.observation_space.high, [7.212947, 240.8190, 0.6387916, 21.95572], rtol=1e-6
    )
    # Each float32 bound is the first float32 at or above the derived (float64) one.
    _, reached = _cartpole_bounds(env.task)
    high = env.observation_space.high
    assert np.all(high.astype(np.float64) >= reached)
    assert np.all(np.nextafter(high, np.float32(0)).astype(np.float64) < reached)


@pytest.mark.parametrize("force_limit", [10.0, 30.0])
def test_cartpole_observations_stay_in_the_space_from_extreme_starts(force_limit):
    # Starts at the corners of start_space (the fastest live states) under full pushes, until
    # each episode fails: every observation, the failing one included, lies in the space.
    env = gym.make("dipole/CartPole-v1", force_limit=force_limit).unwrapped
    high = env.start_space.high
    rng = np.random.default_rng(0)
    for corner in range(16):
        signs = np.array([1.0 if corner >> bit & 1 else -1.0 for bit in range(4)])
        for scheme in ("with", "against", "random"):
            observation, _ = env.reset(options={"initial_state": signs * high})
            assert env.observation_space.contains(observation)
            done = False
            while not done:
                if scheme == "random":
                    push = rng.choice([-1.0, 1.0])
                else:
                    push = np.sign(observation[3] or 1.0) * (1 if scheme == "with" else -1)
                observation, _, terminated, truncated, _ = env.step(np.array([push]))
                assert env.observation_space.contains(observation), (corner, scheme)
                done = terminated or truncated
    # From the task's own starts the episode does not fail at once.
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)


def test_env_bad_inputs():
    env = gym.make("dipole/CartPole-v1").unwrapped
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1, dtype=np.float32))
    with pytest.raises(ValueError, match="initial_state"):
        env.reset(options={"initial_state": [0.0, 0.0]})
    with pytest.raises(ValueError, match="initial_state must lie in start_space"):
        env.reset(options={"initial_state": [3.0, 0.0, 0.0, 0.0]})  # already failed
    with pytest.raises(ValueError, match="initial_state must lie in start_space"):
        env.reset(options={"initial_state": [0.0, 0.0, np.nan, 0.0]})
    with pytest.raises(ValueError, match="options"):
        env.reset(options={"bogus": 1})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must hold one number"):
        env.step(np.zeros(2, dtype=np.float32))
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(np.array([np.inf]))
    env.reset(options={"initial_state": [0.0, 0.0, 0.2, 5.0]})
    _, _, terminated, _, _ = env.step(np.ones(1))
    assert terminated
    with pytest.raises(RuntimeError, match="episode has ended"):
        env.step(np.ones(1))
    car = gym.make("dipole/MountainCar-v0").unwrapped
    with pytest.raises(ValueError, match="initial_state must lie in start_space"):
        car.reset(options={"initial_state": [0.0, 0.1]})
    with pytest.raises(ValueError, match="short of the goal"):
        car.reset(options={"initial_state": [0.5, 0.0]})
    car.reset(options={"initial_state": [0.4999, 0.0]})  # just short of it: a start
    car.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        car.step(3)


def test_cartpole_action_is_the_push_as_a_fraction_of_force_limit():
    env = gym.make("dipole/CartPole-v1").unwrapped
    assert (env.action_space.low, env.action_space.high) == (-1.0, 1.0)
    start = [0.0, 0.0, 0.01, 0.0]
    task = env.task
    for action, newtons in ((0.25, 2.5), (1.0, 10.0), (3.0, 10.0), (-7.0, -10.0)):
        env.reset(options={"initial_state": start})
        observation, *_ = env.step(np.array([action]))
        state = torch.tensor([start], dtype=task.dtype)
        expected = task.step(state, torch.tensor([newtons], dtype=task.dtype))[0].numpy()
        np.testing.assert_array_equal(observation, expected)


# ------------------------------------------------------------------ rendering
def _centroid_x(frame, color):
    columns = np.nonzero(np.all(frame == np.array(color, dtype=np.uint8), axis=-1))[1]
    assert columns.size > 0, f"no pixel of {color}"
    return columns.mean()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_rgb_array_frames_are_uint8_images_and_the_fps_is_the_time_step(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert isinstance(frame, np.ndarray)
    assert frame.shape == (400, 600, 3) and frame.dtype == np.uint8
    assert (frame == 255).all(axis=-1).mean() > 0.3  # a white background with a drawing on it
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5
    fps = env.metadata["render_fps"]
    assert fps == (1 / CartPoleTask.tau if "CartPole" in env_id else 30)
    assert env.metadata["render_modes"] == ["human", "rgb_array"]


def test_cartpole_frames_follow_the_cart_and_the_pole():
    env = gym.make("dipole/CartPole-v1", render_mode="rgb_array").unwrapped

    def frame(x, angle):
        env.reset(options={"initial_state": [x, 0.0, angle, 0.0]})
        return env.render()

    centre, right, leaning = frame(0.0, 0.0), frame(1.0, 0.0), frame(0.0, 0.15)
    # The track spans ±x_threshold across the 600 pixels: 1 m is 125 pixels.
    assert _centroid_x(centre, AXLE_COLOR) == pytest.approx(300, abs=1)
    assert _centroid_x(right, AXLE_COLOR) == pytest.approx(425, abs=1)
    assert _centroid_x(leaning, AXLE_COLOR) == pytest.approx(300, abs=1)
    # A pole leaning right (φ > 0) has its pixels right of the axle; upright, centred on it.
    assert _centroid_x(centre, POLE_COLOR) == pytest.approx(300, abs=1)
    assert _centroid_x(leaning, POLE_COLOR) > 300 + 5
    assert _centroid_x(frame(0.0, -0.15), POLE_COLOR) < 300 - 5
    assert not np.array_equal(centre, frame(0.0, 0.001))  # any change of state shows


def test_cartpole_frame_stands_the_pole_up_from_the_axle_on_the_track():
    # The track 100 pixels above the bottom (row 300), the 50 × 30 cart centred on it, the
    # axle a quarter of the cart's height above its centre, and the pole 2 · length = 1 m
    # (125 pixels) long upward from the axle; all of it 10 pixels wide (the axle's disc too).
    env = gym.make("dipole/CartPole-v1", render_mode="rgb_array").unwrapped
    env.reset(options={"initial_state": [0.0, 0.0, 0.0, 0.0]})
    frame = env.render()
    cart_rows = np.nonzero(np.all(frame[:, 280] == 0, axis=-1))[0]
    assert cart_rows.tolist() == list(range(285, 315))
    axle_rows, axle_columns = np.nonzero(np.all(frame == np.array(AXLE_COLOR, np.uint8), axis=-1))
    assert axle_rows.mean() == pytest.approx(300 - 30 / 4 - 0.5, abs=0.5)
    assert axle_rows.max() - axle_rows.min() < 10 and axle_columns.max() - axle_columns.min() < 10
    pole_rows = np.nonzero(np.all(frame == np.array(POLE_COLOR, np.uint8), axis=-1))[0]
    assert pole_rows.min() == pytest.approx(292.5 - (125 - 5), abs=1)
    assert pole_rows.max() < 300


def test_mountain_car_frame_lays_out_the_road_walls_flag_and_car():
    # The position axis spans [-1.5 - 0.2, 1.5 + 0.2] over the 600 columns; the road is
    # 0.45 sin(3x) at that scale with its zero at row 0.6 · 400 (y down).
    scale = 600 / 3.4

    def road(x):
        return (x + 1.7) * scale, 240 - 0.45 * math.sin(3 * x) * scale

    env = gym.make("dipole/MountainCar-v0", render_mode="rgb_array").unwrapped

    def pixels(frame, color):
        return np.all(frame == np.array(color, np.uint8), axis=-1)

    env.reset(options={"initial_state": [0.4, 0.0]})
    frame = env.render()
    ground = pixels(frame, GROUND_COLOR)
    tops = np.array([np.nonzero(ground[:, j])[0].min() for j in range(60, 340)])
    floor_x, floor_y = road(-math.pi / 6)  # the valley floor
    assert 60 + np.nonzero(tops == tops.max())[0].mean() == pytest.approx(floor_x, abs=2)
    assert tops.max() == pytest.approx(floor_y, abs=2)
    # A wall 6 pixels wide where a car (40 wide) stopped at either end touches it.
    wall_columns = np.nonzero(pixels(frame, WALL_COLOR))[1]
    left, right = wall_columns[wall_columns < 300], wall_columns[wall_columns > 300]
    assert np.median(left) == pytest.approx(road(-1.5)[0] - 23, abs=1)  # (the median: blends
    assert np.median(right) == pytest.approx(road(1.5)[0] + 23, abs=1)  # can hit the grey)
    assert np.nonzero(pixels(frame, FLAG_COLOR))[1].min() == pytest.approx(road(0.5)[0], abs=1)
    # The car on a slope: two wheels 20 pixels apart along the road, their midpoint 9 pixels
    # above it along the road's upward normal.
    x = -0.9
    env.reset(options={"initial_state": [x, 0.0]})
    labels, count = ndimage.label(pixels(env.render(), WHEEL_COLOR))
    sizes = ndimage.sum_labels(labels > 0, labels, range(1, count + 1))
    wheels = [i + 1 for i in range(count) if sizes[i] > 50]  # (blends can hit the grey)
    assert len(wheels) == 2
    (row_0, column_0), (row_1, column_1) = ndimage.center_of_mass(labels > 0, labels, wheels)
    gradient = -3 * 0.45 * math.cos(3 * x)  # dy/dx of the road in the image
    assert math.hypot(row_1 - row_0, column_1 - column_0) == pytest.approx(20, abs=1)
    assert (row_1 - row_0) / (column_1 - column_0) == pytest.approx(gradient, rel=0.05)
    road_x, road_y = road(x)
    norm = math.hypot(1.0, gradient)
    assert (column_0 + column_1) / 2 == pytest.approx(road_x + 9 * gradient / norm, abs=1)
    assert (row_0 + row_1) / 2 == pytest.approx(road_y - 9 / norm, abs=1)


def test_mountain_car_frames_follow_the_car():
    env = gym.make("dipole/MountainCar-v0", render_mode="rgb_array").unwrapped
    wheels = []
    for position in (-1.2, -0.5, 0.0, 0.4):
        env.reset(options={"initial_state": [position, 0.0]})
        wheels.append(_centroid_x(env.render(), WHEEL_COLOR))
    assert np.all(np.diff(wheels) > 50)
    env.reset(options={"initial_state": [-0.5, 0.0]})
    valley = env.render()
    env.reset(options={"initial_state": [-0.5, 0.05]})
    assert np.array_equal(valley, env.render())  # the velocity does not show


def _shade(coverage):
    """The value of a white pixel with black blended in by ``clip(coverage, 0, 1)``."""
    return round(255 * (1 - min(max(coverage, 0.0), 1.0)))


def test_canvas_shapes_cover_a_pixel_by_a_half_less_its_distance_to_the_edge():
    # The module's rule: coverage clip(0.5 - d, 0, 1), d the signed distance from the pixel's
    # centre (j + 0.5, i + 0.5) to the shape's edge, negative inside; rounded to the nearest.
    for corners in ([(2.25, 1), (6, 1), (6, 5), (2.25, 5)], [(2.25, 5), (6, 5), (6, 1), (2.25, 1)]):
        canvas = Canvas(12, 8)
        canvas.polygon(corners, (0, 0, 0))  # either orientation
        image = canvas.image()[..., 0]
        assert image[3, 2] == _shade(0.5 - (2.25 - 2.5)) == 64  # 63.75, rounded
        assert image[3, 4] == 0 and image[3, 1] == 255 and image[3, 6] == 255
    canvas = Canvas(12, 8)
    canvas.disc((4, 4), 2, (0, 0, 0))
    image = canvas.image()[..., 0]
    assert image[4, 5] == _shade(0.5 - (math.hypot(1.5, 0.5) - 2)) == 21
    assert image[4, 4] == 0 and image[4, 6] == 255
    canvas = Canvas(12, 8)
    canvas.segment((2, 4), (8, 4), 2, (0, 0, 0))  # 2 pixels wide, round ends
    image = canvas.image()[..., 0]
    assert image[4, 5] == 0 and image[5, 5] == _shade(0.5 - (1.5 - 1)) == 255
    assert image[4, 8] == _shade(0.5 - (math.hypot(0.5, 0.5) - 1)) == 53  # the round end
    assert image[4, 9] == 255  # beyond the end, not on the line's continuation


def test_canvas_ground_fills_below_the_curve_and_outlines_it():
    canvas = Canvas(4, 8)
    canvas.ground(np.full(4, 3.25), np.zeros(4), (0, 0, 0))
    assert canvas.image()[:, 1, 0].tolist() == [255, 255, 255, _shade(0.5 + 0.25), 0, 0, 0, 0]
    # The distance across the curve is the vertical one times cos of the slope's angle.
    canvas = Canvas(4, 8)
    canvas.ground(np.full(4, 3.25), np.ones(4), (0, 0, 0))
    assert canvas.image()[3, 1, 0] == _shade(0.5 + 0.25 / math.sqrt(2)) == 82
    # The outline is the curve 2 pixels thick: coverage 1.5 - |d|.
    canvas = Canvas(4, 8)
    canvas.ground(np.full(4, 3.25), np.zeros(4), (255, 255, 255), outline=(0, 0, 0))
    column = canvas.image()[:, 1, 0].tolist()
    assert column == [255, 255, _shade(1.5 - 0.75), 0, _shade(1.5 - 1.25), 255, 255, 255]


def test_canvas_refuses_an_empty_image_too_few_corners_and_coordinates_beyond_finite():
    with pytest.raises(ValueError, match="width and height must be positive"):
        Canvas(0, 5)
    canvas = Canvas(12, 8)
    with pytest.raises(ValueError, match="points must have shape"):
        canvas.polygon([(1, 1), (5, 5)], (0, 0, 0))
    with pytest.raises(ValueError, match="finite"):
        canvas.polygon([(1, 1), (5, 1), (5, np.inf)], (0, 0, 0))
    # Either end of a segment, either coordinate (Python's min and max pass a NaN second
    # argument over: the check is on the ends themselves).
    for end in ((5, np.nan), (np.nan, 3), (5, np.inf)):
        with pytest.raises(ValueError, match="finite"):
            canvas.segment((0, 3), end, 2, (0, 0, 0))
        with pytest.raises(ValueError, match="finite"):
            canvas.segment(end, (0, 3), 2, (0, 0, 0))
    assert (canvas.image() == 255).all()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_rendering_leaves_observations_and_rewards_alone(env_id):
    runs = []
    for render_mode in (None, "rgb_array"):
        env = gym.make(env_id, render_mode=render_mode)
        env.action_space.seed(3)
        observation, _ = env.reset(seed=3)
        record, done = [observation], False
        while not done:
            if render_mode is not None:
                env.render()
            observation, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            record += [observation, reward]
            done = terminated or truncated
        runs.append(record)
    assert len(runs[0]) == len(runs[1])
    for plain, rendered in zip(*runs, strict=True):
        assert np.array_equal(plain, rendered)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_render_collection_keeps_a_frame_per_reset_and_step(env_id):
    env = gym.make(env_id, render_mode="rgb_array_list", max_episode_steps=5)
    env.reset(seed=0)
    done, steps = False, 0
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        steps += 1
        done = terminated or truncated
    frames = env.render()
    assert len(frames) == steps + 1
    assert all(frame.shape == (400, 600, 3) and frame.dtype == np.uint8 for frame in frames)
    assert not np.array_equal(frames[0], frames[-1])


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_record_video_writes_an_episode(env_id, tmp_path):
    pytest.importorskip("moviepy", reason="gymnasium's RecordVideo writes videos with moviepy")
    from gymnasium.wrappers import RecordVideo

    env = gym.make(env_id, render_mode="rgb_array", max_episode_steps=10)
    env = RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda episode: True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        done = terminated or truncated
    env.close()
    (video,) = (tmp_path / "videos").glob("*.mp4")
    assert video.stat().st_size > 0


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_unknown_render_mode_is_refused_naming_the_valid_ones(env_id):
    message = "render_mode must be None or one of 'human', 'rgb_array', got 'ansi'"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gymnasium.make's own warning about the mode
        with pytest.raises(ValueError, match=message):
            gym.make(env_id, render_mode="ansi")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_human_mode_is_refused_without_a_display(env_id, monkeypatch):
    for name in DISPLAY_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    try:
        import pygame  # noqa: F401
    except ImportError:
        with pytest.raises(DependencyNotInstalled, match='render_mode="human".*pip install pygame'):
            gym.make(env_id, render_mode="human")
    else:
        with pytest.raises(RuntimeError, match='render_mode="human" needs a display'):
            gym.make(env_id, render_mode="human")
        monkeypatch.setenv("DISPLAY", ":4093")  # named, but no server there
        with pytest.raises(RuntimeError, match='render_mode="human" found no display'):
            gym.make(env_id, render_mode="human")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_human_mode_shows_frames_in_a_window(env_id, monkeypatch):
    pytest.importorskip("pygame", reason='render_mode="human" draws with pygame')
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")  # a window without a screen
    env = gym.make(env_id, render_mode="human", max_episode_steps=3)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        done = terminated or truncated
    assert env.render() is None
    env.close()
    env.close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make(env_id).unwrapped)  # every render mode included


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_mountain_car_env_runs_in_half_precision(dtype):
    env = gym.make("dipole/MountainCar-v0", dtype=dtype)
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    assert env.unwrapped.start_space.high[0] < env.unwrapped.task.goal_position
    env.step(1)
