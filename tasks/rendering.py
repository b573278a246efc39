"""Frames of the classic-control tasks, drawn with numpy, and a window that shows them.

* ``Canvas``: a small anti-aliased rasteriser (convex polygons, discs, thick line
  segments, the ground under a curve) into an ``[H, W, 3]`` image.
* ``cartpole_frame``, ``mountain_car_frame``: one state of
  ``CartPoleTask`` or
  ``MountainCarTask`` as an RGB ``uint8`` array
  ``[400, 600, 3]``, laid out and coloured as gymnasium's classic-control renderers
  (``CartPole-v1``, ``MountainCar-v0``) draw them.
* ``Window``: shows frames in a pygame window, the ``render_mode="human"`` of the
  gymnasium environments (``dipole_torch.tasks.gym_envs``); pygame is needed only there.

Drawing reads a state and returns a new array: nothing here touches the dynamics.

Coordinates are the image's: ``x`` to the right and ``y`` down, in pixels; the pixel in row
``i`` and column ``j`` covers ``[j, j + 1] × [i, i + 1]``. A shape covers a pixel by the
fraction ``clip(0.5 - d, 0, 1)``, ``d`` the signed distance from the pixel's centre to the
shape's edge (negative inside), and its colour is blended in by that fraction: edges are
smooth without supersampling.

Example:
    >>> canvas = Canvas(8, 6)
    >>> canvas.polygon([(2, 1), (6, 1), (6, 5), (2, 5)], (0, 0, 0))
    >>> image = canvas.image()
    >>> image.shape, image.dtype, image[3, 4].tolist(), image[3, 0].tolist()
    ((6, 8, 3), dtype('uint8'), [0, 0, 0], [255, 255, 255])
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from gymnasium.error import DependencyNotInstalled

if TYPE_CHECKING:
    from dipole_torch.tasks.cartpole import CartPoleTask
    from dipole_torch.tasks.mountain_car import MountainCarTask

__all__ = ["Canvas", "Window", "cartpole_frame", "mountain_car_frame"]

Color = tuple[int, int, int]
Point = tuple[float, float]

WHITE: Color = (255, 255, 255)
BLACK: Color = (0, 0, 0)

FRAME_WIDTH = 600  # pixels, gymnasium's classic-control screen_width
FRAME_HEIGHT = 400  # pixels, gymnasium's classic-control screen_height


class Canvas:
    """An RGB image of ``width × height`` pixels that anti-aliased shapes are drawn into.

    Args:
        width, height: size in pixels (positive).
        background: the colour every pixel starts with.
    """

    def __init__(self, width: int, height: int, background: Color = WHITE) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"width and height must be positive, got {width} x {height}")
        self.width = int(width)
        self.height = int(height)
        self._pixels = np.empty((self.height, self.width, 3), dtype=np.float32)
        self._pixels[:] = background

    def image(self) -> np.ndarray:
        """The picture so far: ``[height, width, 3]`` ``uint8`` (a new array)."""
        return np.rint(self._pixels).clip(0, 255).astype(np.uint8)

    def polygon(self, points: Sequence[Point], color: Color) -> None:
        """Fill the convex polygon with the corners ``points: [N, 2]`` (either orientation)."""
        corners = np.asarray(points, dtype=np.float64)
        if corners.ndim != 2 or corners.shape[0] < 3 or corners.shape[1] != 2:
            raise ValueError(f"points must have shape [N >= 3, 2], got {list(corners.shape)}")
        window = self._window(
            corners[:, 0].min(), corners[:, 0].max(), corners[:, 1].min(), corners[:, 1].max()
        )
        if window is None:
            return
        region, xs, ys = window
        edges = np.roll(corners, -1, axis=0) - corners
        signed_area = np.sum(
            corners[:, 0] * np.roll(corners[:, 1], -1) - np.roll(corners[:, 0], -1) * corners[:, 1]
        )
        orientation = 1.0 if signed_area >= 0 else -1.0
        distance = np.full((ys.shape[0], xs.shape[1]), -np.inf, dtype=np.float32)
        for (start_x, start_y), (edge_x, edge_y) in zip(
            corners.tolist(), edges.tolist(), strict=True
        ):
            length = math.hypot(edge_x, edge_y)
            if length == 0.0:
                continue
            # Outward unit normal of the edge; the polygon is where every edge distance is < 0.
            normal_x, normal_y = orientation * edge_y / length, -orientation * edge_x / length
            np.maximum(
                distance, normal_x * (xs - start_x) + normal_y * (ys - start_y), out=distance
            )
        self._blend(region, 0.5 - distance, color)

    def disc(self, center: Point, radius: float, color: Color) -> None:
        """Fill the disc of ``radius`` pixels around ``center``."""
        cx, cy = center
        window = self._window(cx - radius, cx + radius, cy - radius, cy + radius)
        if window is None:
            return
        region, xs, ys = window
        self._blend(region, radius + 0.5 - np.hypot(xs - cx, ys - cy), color)

    def segment(self, start: Point, end: Point, width: float, color: Color) -> None:
        """Draw the line from ``start`` to ``end``, ``width`` pixels thick, with round ends."""
        (x0, y0), (x1, y1) = start, end
        # (Python's min and max below pass over a NaN second argument: check the ends here.)
        if not all(map(math.isfinite, (x0, y0, x1, y1))):
            raise ValueError("shape coordinates must be finite")
        half = width / 2
        window = self._window(
            min(x0, x1) - half, max(x0, x1) + half, min(y0, y1) - half, max(y0, y1) + half
        )
        if window is None:
            return
        region, xs, ys = window
        dx, dy = x1 - x0, y1 - y0
        squared_length = dx * dx + dy * dy
        if squared_length == 0.0:
            along = np.zeros((1, 1), dtype=np.float32)
        else:
            along = np.clip(((xs - x0) * dx + (ys - y0) * dy) / squared_length, 0.0, 1.0)
        distance = np.hypot(xs - (x0 + along * dx), ys - (y0 + along * dy))
        self._blend(region, half + 0.5 - distance, color)

    def ground(
        self, surface: np.ndarray, slope: np.ndarray, color: Color, outline: Color | None = None
    ) -> None:
        """Fill below a curve given per column: ``surface: [width]``, the curve's ``y`` at each
        column's centre, and ``slope: [width]``, its ``dy/dx`` there; ``outline`` draws the
        curve itself 2 pixels thick on top."""
        surface = np.asarray(surface, dtype=np.float32)
        slope = np.asarray(slope, dtype=np.float32)
        if surface.shape != (self.width,) or slope.shape != (self.width,):
            raise ValueError(
                f"surface and slope must have shape [{self.width}], "
                f"got {list(surface.shape)} and {list(slope.shape)}"
            )
        top = max(int(math.floor(float(surface.min()))) - 2, 0)
        if top >= self.height:
            return
        ys = np.arange(top, self.height, dtype=np.float32)[:, None] + 0.5
        # Distance to the curve across it: the vertical distance times cos(slope angle).
        across = (ys - surface[None, :]) / np.sqrt(1.0 + slope * slope)[None, :]
        region = (slice(top, self.height), slice(0, self.width))
        self._blend(region, 0.5 + across, color)
        if outline is not None:
            self._blend(region, 1.5 - np.abs(across), outline)

    # ------------------------------------------------------------------ internals
    def _window(
        self, x_min: float, x_max: float, y_min: float, y_max: float
    ) -> tuple[tuple[slice, slice], np.ndarray, np.ndarray] | None:
        """The pixels a shape with this bounding box can touch: the image region and the
        centres of its columns ``xs: [1, w]`` and rows ``ys: [h, 1]``; ``None`` when the box
        misses the image."""
        if not all(map(math.isfinite, (x_min, x_max, y_min, y_max))):
            raise ValueError("shape coordinates must be finite")
        j0 = max(int(math.floor(x_min)) - 1, 0)
        j1 = min(int(math.ceil(x_max)) + 1, self.width)
        i0 = max(int(math.floor(y_min)) - 1, 0)
        i1 = min(int(math.ceil(y_max)) + 1, self.height)
        if j0 >= j1 or i0 >= i1:
            return None
        xs = np.arange(j0, j1, dtype=np.float32)[None, :] + 0.5
        ys = np.arange(i0, i1, dtype=np.float32)[:, None] + 0.5
        return (slice(i0, i1), slice(j0, j1)), xs, ys

    def _blend(self, region: tuple[slice, slice], coverage: np.ndarray, color: Color) -> None:
        """Mix ``color`` into ``region`` by ``clip(coverage, 0, 1)`` per pixel."""
        coverage = np.clip(coverage, 0.0, 1.0)[..., None]
        target = self._pixels[region]
        target += coverage * (np.asarray(color, dtype=np.float32) - target)


# ---------------------------------------------------------------------- cart-pole
CART_SIZE = (50.0, 30.0)  # pixels, width and height of the cart (gymnasium's)
POLE_WIDTH = 10.0  # pixels
TRACK_HEIGHT = 100.0  # pixels from the bottom of the image to the track and cart centre
POLE_COLOR: Color = (202, 152, 101)
AXLE_COLOR: Color = (129, 132, 203)


def cartpole_frame(
    task: CartPoleTask, state: Sequence[float], width: int = FRAME_WIDTH, height: int = FRAME_HEIGHT
) -> np.ndarray:
    """The cart and pole of ``state = [x, ẋ, φ, φ̇]``: an RGB ``uint8`` image ``[height, width, 3]``.

    The image spans the track between the failure thresholds ``±task.x_threshold``
    (``width / (2 x_threshold)`` pixels a metre): the cart sits at the centre at ``x = 0``
    and half leaves the picture at a threshold. The pole is drawn ``2 · task.length`` long at
    that scale, leaning right for ``φ > 0``; the velocities do not show.
    """
    x, _, angle, _ = (float(value) for value in state)
    canvas = Canvas(width, height)
    scale = width / (2 * task.x_threshold)  # pixels a metre
    track_y = height - TRACK_HEIGHT
    cart_x = width / 2 + x * scale
    rail_y = track_y + 0.5  # the centre of a pixel row: a crisp 1-pixel line
    canvas.segment((-1.0, rail_y), (width + 1.0, rail_y), 1.0, BLACK)
    cart_width, cart_height = CART_SIZE
    canvas.polygon(
        [
            (cart_x - cart_width / 2, track_y - cart_height / 2),
            (cart_x + cart_width / 2, track_y - cart_height / 2),
            (cart_x + cart_width / 2, track_y + cart_height / 2),
            (cart_x - cart_width / 2, track_y + cart_height / 2),
        ],
        BLACK,
    )
    axle = (cart_x, track_y - cart_height / 4)
    along = (math.sin(angle), -math.cos(angle))  # from the axle to the pole's tip (y is down)
    across = (math.cos(angle), math.sin(angle))
    pole_length = 2 * task.length * scale
    corners = []
    for distance_along, distance_across in (
        (-POLE_WIDTH / 2, -POLE_WIDTH / 2),
        (pole_length - POLE_WIDTH / 2, -POLE_WIDTH / 2),
        (pole_length - POLE_WIDTH / 2, POLE_WIDTH / 2),
        (-POLE_WIDTH / 2, POLE_WIDTH / 2),
    ):
        corners.append(
            (
                axle[0] + distance_along * along[0] + distance_across * across[0],
                axle[1] + distance_along * along[1] + distance_across * across[1],
            )
        )
    canvas.polygon(corners, POLE_COLOR)
    canvas.disc(axle, POLE_WIDTH / 2, AXLE_COLOR)
    return canvas.image()


# ---------------------------------------------------------------------- mountain car
HILL_AMPLITUDE = 0.45  # height of the hill drawn as HILL_AMPLITUDE · sin(3x) (gymnasium's)
WORLD_MARGIN = 0.2  # position units shown beyond each end of the position range
CAR_SIZE = (40.0, 20.0)  # pixels, width and height of the car body
CLEARANCE = 9.0  # pixels from the road to the bottom of the body and the wheel centres
WHEEL_RADIUS = 8.0  # pixels
FLAG_HEIGHT = 50.0  # pixels
GROUND_COLOR: Color = (226, 218, 196)
WALL_COLOR: Color = (96, 96, 96)
WALL_WIDTH = 6.0  # pixels
WHEEL_COLOR: Color = (128, 128, 128)
FLAG_COLOR: Color = (204, 204, 0)


def mountain_car_frame(
    task: MountainCarTask,
    state: Sequence[float],
    width: int = FRAME_WIDTH,
    height: int = FRAME_HEIGHT,
) -> np.ndarray:
    """The car of ``state = [x, ẋ]`` on its hill as an RGB ``uint8`` image ``[height, width, 3]``.

    The road is the hill the dynamics' gravity term ``−β cos(3x)`` descends from, a height
    proportional to ``sin(3x)``, drawn as ``0.45 sin(3x)`` (gymnasium's ``MountainCar-v0``
    profile) at the scale of the position axis, over the whole range
    ``[task.min_position, task.max_position]`` plus a margin, with a wall at each end; the
    valley floor is at ``x = −π/6`` and the flag marks ``task.goal_position``. The car is
    tilted with the road; the velocity does not show.
    """
    position = float(state[0])
    canvas = Canvas(width, height)
    world_min = task.min_position - WORLD_MARGIN
    scale = width / (task.max_position - task.min_position + 2 * WORLD_MARGIN)  # pixels a unit
    level_y = 0.6 * height  # the image row of height 0

    def road(x: float | np.ndarray) -> tuple[float | np.ndarray, float | np.ndarray]:
        """Image coordinates of the road at position ``x``."""
        return (x - world_min) * scale, level_y - HILL_AMPLITUDE * np.sin(3 * x) * scale

    columns = world_min + (np.arange(width, dtype=np.float64) + 0.5) / scale
    _, surface = road(columns)
    slope = -3 * HILL_AMPLITUDE * np.cos(3 * columns)  # dy/dx in image coordinates (y is down)
    canvas.ground(surface, slope, GROUND_COLOR, outline=BLACK)

    # A wall at each end of the position range, where a car stopped there touches it.
    car_width, car_height = CAR_SIZE
    for limit, side in ((task.min_position, -1.0), (task.max_position, 1.0)):
        wall_x = road(limit)[0] + side * (car_width / 2 + WALL_WIDTH / 2)
        wall_y = road(world_min + wall_x / scale)[1]
        canvas.segment((wall_x, wall_y + 2.0), (wall_x, wall_y - 40.0), WALL_WIDTH, WALL_COLOR)

    flag_x, flag_y = road(task.goal_position)
    flag_top = flag_y - FLAG_HEIGHT
    canvas.segment((flag_x, flag_y), (flag_x, flag_top), 1.5, BLACK)
    canvas.polygon(
        [(flag_x, flag_top), (flag_x, flag_top + 10), (flag_x + 25, flag_top + 5)], FLAG_COLOR
    )

    # The car: its frame is the road's tangent and upward normal at its position.
    road_x, road_y = road(position)
    gradient = -3 * HILL_AMPLITUDE * math.cos(3 * position)
    norm = math.hypot(1.0, gradient)
    tangent = (1.0 / norm, gradient / norm)
    normal = (gradient / norm, -1.0 / norm)

    def on_car(distance_along: float, distance_up: float) -> Point:
        return (
            road_x + distance_along * tangent[0] + distance_up * normal[0],
            road_y + distance_along * tangent[1] + distance_up * normal[1],
        )

    canvas.polygon(
        [
            on_car(-car_width / 2, CLEARANCE),
            on_car(car_width / 2, CLEARANCE),
            on_car(car_width / 2, CLEARANCE + car_height),
            on_car(-car_width / 2, CLEARANCE + car_height),
        ],
        BLACK,
    )
    for wheel in (-car_width / 4, car_width / 4):
        canvas.disc(on_car(wheel, CLEARANCE), WHEEL_RADIUS, WHEEL_COLOR)
    return canvas.image()


# ---------------------------------------------------------------------- human rendering
def _pygame_with_display():
    """pygame, with its display initialised; a clear error where there is no pygame or no
    display to open a window on."""
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame
    except ImportError as error:
        raise DependencyNotInstalled(
            'render_mode="human" shows the frames in a pygame window, and pygame is not '
            'installed: `pip install pygame`, or use render_mode="rgb_array"'
        ) from error
    # X11 and Wayland systems name their display in the environment; SDL_VIDEODRIVER picks
    # a backend explicitly (its "dummy" driver runs without a screen).
    needs_display_variable = os.name == "posix" and sys.platform != "darwin"
    display_variables = ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")
    if needs_display_variable and not any(os.environ.get(name) for name in display_variables):
        raise RuntimeError(
            'render_mode="human" needs a display to open a window on, and none is set '
            f"({', '.join(display_variables)} are all unset); "
            'render_mode="rgb_array" draws the same frames into arrays (e.g. for '
            "gymnasium.wrappers.RecordVideo)"
        )
    try:
        pygame.display.init()
    except pygame.error as error:
        raise RuntimeError(
            f'render_mode="human" found no display to open a window on ({error}); '
            'render_mode="rgb_array" draws the same frames into arrays'
        ) from error
    # Where the named display cannot be reached, SDL falls back to a driver that shows
    # nothing: refuse that unless it was asked for.
    driver = pygame.display.get_driver()
    if driver in ("offscreen", "dummy") and os.environ.get("SDL_VIDEODRIVER") != driver:
        pygame.display.quit()
        shown = ", ".join(f"{name}={os.environ.get(name)!r}" for name in display_variables[:2])
        raise RuntimeError(
            f'render_mode="human" found no display to open a window on ({shown}; SDL fell '
            f"back to its {driver!r} video driver, which shows nothing; set "
            f"SDL_VIDEODRIVER={driver} to run without a screen on purpose); "
            'render_mode="rgb_array" draws the same frames into arrays'
        )
    return pygame


class Window:
    """A pygame window that shows ``[height, width, 3]`` frames, at most ``fps`` a second.

    Construction checks that pygame and a display are there (raising
    ``gymnasium.error.DependencyNotInstalled`` or ``RuntimeError`` otherwise); the
    window opens with the first frame.
    """

    def __init__(self, title: str, width: int, height: int, fps: float) -> None:
        self._pygame = _pygame_with_display()
        self.title = title
        self.size = (int(width), int(height))
        self.fps = fps
        self._screen = None
        self._clock = None

    def show(self, frame: np.ndarray) -> None:
        """Draw ``frame`` in the window, then wait for the next frame's time."""
        pygame = self._pygame
        if frame.shape != (self.size[1], self.size[0], 3):
            raise ValueError(
                f"frame must have shape [{self.size[1]}, {self.size[0]}, 3], "
                f"got {list(frame.shape)}"
            )
        if self._screen is None:
            pygame.display.init()
            self._screen = pygame.display.set_mode(self.size)
            pygame.display.set_caption(self.title)
            self._clock = pygame.time.Clock()
        surface = pygame.surfarray.make_surface(np.ascontiguousarray(frame.swapaxes(0, 1)))
        self._screen.blit(surface, (0, 0))
        pygame.event.pump()
        pygame.display.flip()
        self._clock.tick(self.fps)

    def close(self) -> None:
        """Close the window (again: nothing to do)."""
        if self._screen is not None:
            self._pygame.display.quit()
            self._screen = None
            self._clock = None
