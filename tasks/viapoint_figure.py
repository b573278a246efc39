"""The figure of ``ViapointTask.plot_policies``: the end-effector paths of a set of policies
in 3-D, with the viapoints, obstacles, start and target, laid out for a TensorBoard image card.

matplotlib is imported when a figure is drawn: a run that never draws one does not load it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from dipole_torch.models.wam import URDF_PATH
from torch import Tensor

if TYPE_CHECKING:
    from dipole_torch.tasks.viapoint import ViapointTask
    from matplotlib.figure import Figure

__all__ = ["paths_figure"]


def paths_figure(
    task: ViapointTask,
    theta: Tensor,
    labels: Sequence[str] | None = None,
    title: str | None = None,
) -> Figure:
    """The figure of ``task.plot_policies(theta, labels, title)`` for ``theta: [K, 3K']``
    (see there)."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    with torch.no_grad():
        path = task.trajectory(theta)
        rewards = task.reward(path).tolist()
        routes = task.viapoint_distances(path).argmin(-1).tolist()
    path = path.double().cpu().numpy()
    if labels is None:
        labels = [
            f"{task.route_name(route)} (r = {reward:.2f})"
            for route, reward in zip(routes, rewards, strict=True)
        ]
    if len(labels) != path.shape[0]:
        raise ValueError(f"labels must give one entry per policy ({path.shape[0]})")
    # Laid out for TensorBoard, which scales an image down to the width of its card
    # (about 350-420 px): 440 px wide at 100 dpi, 7-9 pt text, the legend below the axes.
    rows = max(path.shape[0], len(task.num_alternatives) + 2 + bool(task.obstacles))
    legend_height = 0.16 + 0.145 * rows  # in: 7 pt lines
    axes_height = 2.6  # in
    height = axes_height + legend_height
    figure = Figure(figsize=(4.4, height), dpi=100)
    FigureCanvasAgg(figure)
    ax = figure.add_axes((0.0, legend_height / height, 1.0, axes_height / height), projection="3d")
    cmap = matplotlib.colormaps["tab10"]
    paths = [
        ax.plot(*path[k].T, color=cmap(k % 10), lw=1.6, label=labels[k])[0]
        for k in range(path.shape[0])
    ]
    points = []
    markers = ("o", "s", "^", "D", "v", "P")
    names = task.alternative_names
    for i, count in enumerate(task.num_alternatives):
        viapoints = task.viapoints[i, :count].double().cpu().numpy()
        points.append(
            ax.scatter(
                *viapoints.T,
                s=55,
                marker=markers[i % len(markers)],
                facecolors="none",
                edgecolors="black",
                linewidths=1.3,
                label=f"via t = {task.pass_times[i]:g} s",
            )
        )
        for point, name in zip(viapoints, names[i], strict=True):
            ax.text(*point, f" {name}", fontsize=7, color="0.25")
    # Obstacles as wireframe spheres; their extremes join the box so the scale stays equal.
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    unit = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])  # [3, 12, 24]
    extremes = [np.zeros((0, 3))]
    for j, obstacle in enumerate(task.obstacles):
        centre, radius = np.array(obstacle["centre"]), obstacle["radius"]
        sphere = centre[:, None, None] + radius * unit
        wireframe = ax.plot_wireframe(*sphere, color="0.35", lw=0.5, alpha=0.5, label="obstacle")
        if j == 0:
            points.append(wireframe)
        extremes.append(centre + radius * np.concatenate([np.eye(3), -np.eye(3)]))
    start, target = (point.detach().cpu().double().numpy() for point in (task.start, task.target))
    points.append(ax.scatter(*start, s=70, color="green", marker="*", label="start"))
    points.append(ax.scatter(*target, s=70, color="red", marker="*", label="target"))
    everything = np.concatenate(
        [path.reshape(-1, 3), task.viapoints.reshape(-1, 3).double().cpu(), *extremes]
    )
    aspect = np.ptp(everything, axis=0) + 0.02  # equal scale on x, y, z
    for axis, name, length in zip((ax.xaxis, ax.yaxis, ax.zaxis), "xyz", aspect, strict=True):
        # Up to 5 ticks on the longest side, fewer on shorter ones: no crowded labels.
        bins = int(np.clip(round(5 * length / aspect.max()), 2, 5))
        axis.set_major_locator(MaxNLocator(nbins=bins, steps=[1, 2, 5, 10]))
        axis.set_label_text(f"{name} [m]", fontsize=8)
        axis.labelpad = -2
    ax.tick_params(labelsize=7, pad=-1)
    ax.view_init(elev=20, azim=-35)
    _zoom_to_fill(ax, aspect, top_margin=22.0)  # px: the band the title goes in
    arm = "WAM" if task.kinematics.urdf_path == URDF_PATH.resolve() else None
    arm = arm or task.kinematics.robot_name
    policies = f"{path.shape[0]} {'policy' if path.shape[0] == 1 else 'policies'}"
    # In the band at the top of the axes, which reach the figure's top edge.
    ax.set_title(title or f"{arm} end-effector paths of {policies}", fontsize=9, y=0.97, pad=0)
    # Paths in the left column, the points in the right one (blank entries pad them).
    blank = Line2D([], [], linestyle="none", label=" ")
    handles = paths + [blank] * (rows - len(paths)) + points + [blank] * (rows - len(points))
    ax.legend(
        handles=handles,
        loc="lower center",
        bbox_to_anchor=(0.5, 0.0),
        bbox_transform=figure.transFigure,
        ncol=2,
        fontsize=7,
        frameon=False,
        borderaxespad=0.3,
        columnspacing=1.2,
        handlelength=1.4,
    )
    return figure


def _zoom_to_fill(ax, box_aspect: np.ndarray, top_margin: float) -> None:
    """Zoom the 3-D axes ``ax`` (box aspect ``[3]``) so that its box, with its ticks and axis
    labels, fills the rectangle the axes were given, less ``top_margin`` px at the
    top. mplot3d draws into the largest square centred in that rectangle, at a zoom that
    leaves wide margins; on a wide (or tall) rectangle, the box can grow beyond the square.
    Measured on a draw (labels keep their size in px while the box scales, hence the second
    pass)."""
    from matplotlib.transforms import Bbox
    from mpl_toolkits.mplot3d import proj3d

    figure = ax.figure
    given = ax.get_position(original=True).transformed(figure.transFigure)  # px
    centre_x, centre_y = given.x0 + 0.5 * given.width, given.y0 + 0.5 * given.height
    limits = (ax.get_xlim3d(), ax.get_ylim3d(), ax.get_zlim3d())
    corners = np.array(list(itertools.product(*limits))).T  # [3, 8]
    zoom = 1.0
    for _ in range(2):
        ax.set_box_aspect(box_aspect, zoom=zoom)
        figure.canvas.draw()
        renderer = figure.canvas.get_renderer()
        x, y, _ = proj3d.proj_transform(*corners, ax.get_proj())
        box = ax.transData.transform(np.column_stack([x, y]))  # [8, 2] px
        boxes = [Bbox([box.min(0), box.max(0)])]
        boxes += [axis.get_tightbbox(renderer) for axis in (ax.xaxis, ax.yaxis, ax.zaxis)]
        drawn = Bbox.union([box for box in boxes if box is not None and box.width > 0])
        zoom *= min(
            (centre_x - given.x0) / max(centre_x - drawn.x0, 1.0),
            (given.x1 - centre_x) / max(drawn.x1 - centre_x, 1.0),
            (centre_y - given.y0) / max(centre_y - drawn.y0, 1.0),
            (given.y1 - top_margin - centre_y) / max(drawn.y1 - centre_y, 1.0),
        )
    ax.set_box_aspect(box_aspect, zoom=0.98 * zoom)
