"""A changing world on the viapoint task: obstacles on the arm's path, the block that puts one
on a learned route, and switching to a stored route (optimizer.reevaluate), in the library and
in train.py (task=viapoint_blocked)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from dipole_torch.tasks.viapoint import ViapointTask
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from test_train import compose_config, train
from test_viapoint import route_policies

from dipole_torch import Dipole
from dipole_torch.training.hydra_compat import instantiate

F64 = torch.float64


@pytest.fixture(scope="module")
def task() -> ViapointTask:
    return ViapointTask(dtype=F64, kinematics="wam_dh")


@pytest.fixture(scope="module")
def routes(task):
    return route_policies(task)  # θ [8, 9] passing every viapoint of each route exactly


def test_an_obstacle_costs_reward_only_where_the_arm_path_enters_it(task, routes):
    thetas, route_list = routes
    far = route_list.index((0, 1, 1))  # passes the far viapoint at 1.2 s
    near = route_list.index((0, 0, 1))
    blocked = task.with_obstacles([{"centre": [0.6, 0.06, 0.0], "radius": 0.08}])
    open_rewards, rewards = task.evaluate(thetas), blocked.evaluate(thetas)
    paths = blocked.trajectory(thetas)
    depth = blocked.penetration(paths)
    # The routes through "far" go through the sphere's centre: 8 cm deep.
    enters = depth > 0
    assert enters.tolist() == [route[1] == 1 for route in route_list]
    assert float(depth[far]) == pytest.approx(0.08, abs=2e-3)
    expected = open_rewards * torch.exp(-depth / blocked.penetration_scale)
    torch.testing.assert_close(rewards, expected)
    assert float(rewards[far]) < 0.05 and torch.equal(rewards[~enters], open_rewards[~enters])
    assert float(rewards[near]) >= 0.99
    # Continuous in the depth: a path grazing the sphere keeps almost all of its reward.
    distance = (paths[far] - torch.tensor([0.6, 0.06, 0.0], dtype=F64)).norm(dim=-1).min()
    graze = task.with_obstacles([{"centre": [0.6, 0.06, 0.0], "radius": float(distance) + 1e-3}])
    assert float(graze.evaluate(thetas[far : far + 1])[0]) > 0.94
    # The task without obstacles is eq. 9 exactly, and the copy left the original open.
    assert task.obstacles == [] and blocked.obstacles[0]["radius"] == 0.08
    assert torch.equal(open_rewards, ViapointTask(dtype=F64, kinematics="wam_dh").evaluate(thetas))


def test_obstacles_are_checked_on_the_path_the_arm_makes(task):
    """A sphere beyond the arm's reach on the DS-GMR reference path: the reference enters it,
    the tracked end-effector path cannot, and the reward is unchanged."""
    theta = task.theta0.clone()
    theta[3:6] = torch.tensor([2.0, 0.0, 0.5], dtype=F64)  # middle attractor 2 m out
    desired = task.desired_trajectory(theta[None])
    actual = task.trajectory(theta[None])
    outermost = desired[0, desired[0].norm(dim=-1).argmax()]
    clearance = float((actual[0] - outermost).norm(dim=-1).min())
    assert clearance > 0.2
    blocked = task.with_obstacles([{"centre": outermost.tolist(), "radius": clearance / 2}])
    assert float(blocked.penetration(desired)[0]) > 0 and float(blocked.penetration(actual)) == 0
    torch.testing.assert_close(blocked.evaluate(theta[None]), task.evaluate(theta[None]))


def test_obstacles_from_the_config_and_bad_obstacles():
    cfg = compose_config("task=viapoint", "task.env.kinematics=wam_dh")
    assert cfg.task.env.obstacles == [] and cfg.task.block is None
    assert instantiate(cfg.task.env).obstacles == []
    sphere = "{centre: [0.4, 0.06, 0.0], radius: 0.05}"
    cfg = compose_config("task=viapoint", f"task.env.obstacles=[{sphere}]")
    task = instantiate(cfg.task.env)
    assert task.obstacles == [{"centre": [0.4, 0.06, 0.0], "radius": 0.05}]
    blocked = compose_config("task=viapoint_blocked")
    assert blocked.task.name == "viapoint_blocked"
    assert blocked.task.env == compose_config("task=viapoint").task.env  # the open layout
    assert blocked.task.block.trial == 300 and blocked.task.block.radius == 0.08
    cfg = compose_config("task=viapoint", "task.env.obstacles=[{centre: [0.4, 0.0, 0.0]}]")
    with pytest.raises(Exception, match="obstacles.*radius"):  # a missing value, named
        instantiate(cfg.task.env)
    with pytest.raises(Exception, match="obstacles.*radius"):  # a wrong type, named
        compose_config(
            "task=viapoint", "task.env.obstacles=[{centre: [0.4, 0.0, 0.0], radius: big}]"
        )
    with pytest.raises(ValueError, match=r"obstacles\[0\].radius must be a finite positive"):
        task.set_obstacles([{"centre": [0.4, 0.06, 0.0], "radius": -0.1}])
    with pytest.raises(ValueError, match=r"obstacles\[1\].centre must be a finite"):
        task.set_obstacles(
            [{"centre": [0.4, 0.06, 0.0], "radius": 0.1}, {"centre": [0.4], "radius": 0.1}]
        )
    with pytest.raises(ValueError, match=r"obstacles\[0\].*holds the start point"):
        task.set_obstacles([{"centre": [0.5, -0.3, 0.0], "radius": 0.1}])
    with pytest.raises(ValueError, match=r"obstacles\[0\] must be"):
        task.set_obstacles([[0.4, 0.06, 0.0, 0.1]])
    assert task.obstacles == [{"centre": [0.4, 0.06, 0.0], "radius": 0.05}]  # unchanged


def test_obstacles_with_other_keys_no_size_a_nested_centre_or_on_the_start_are_refused(task):
    good = {"centre": [0.4, 0.06, 0.0], "radius": 0.05}
    for bad, message in (
        ({**good, "colour": "red"}, r"obstacles\[0\] must be \{'centre'"),
        (
            {**good, "radius": 0},
            r"obstacles\[0\]\.radius must be a finite positive number \(m\), got 0",
        ),
        ({**good, "centre": [[0.4, 0.06, 0.0]]}, r"obstacles\[0\]\.centre must be a finite"),
        # A sphere whose surface passes through the start, (0.5, -0.35, 0), holds it.
        ({"centre": [0.75, -0.35, 0.0], "radius": 0.25}, r"obstacles\[0\].*holds the start"),
    ):
        with pytest.raises(ValueError, match=message):
            task.with_obstacles([bad])


def test_a_radius_is_any_real_scalar_as_a_centre_may_be_a_tensor(task):
    """A 0-d tensor, a NumPy scalar or 0-d array is a radius, kept as the float it holds
    (a Python float exactly); a bool, a complex number, a string or a one-element list is not."""
    centre = torch.tensor([0.4, 0.06, 0.0])
    for radius, kept in (
        (0.05, 0.05),
        (torch.tensor(0.05, dtype=torch.float64), 0.05),
        (torch.tensor(0.05), float(np.float32(0.05))),
        (np.float32(0.05), float(np.float32(0.05))),
        (np.array(0.05), 0.05),
    ):
        blocked = task.with_obstacles([{"centre": centre, "radius": radius}])
        assert blocked.obstacles[0]["radius"] == kept and type(kept) is float
        assert blocked.obstacle_radii.tolist() == pytest.approx([0.05])
    for radius in (
        True,
        np.bool_(True),
        torch.tensor(True),
        torch.tensor(0.05 + 0j),
        "0.05",
        [0.05],
        torch.tensor([0.05]),
        None,
        math.inf,
    ):
        with pytest.raises(ValueError, match=r"obstacles\[0\]\.radius must be a finite positive"):
            task.with_obstacles([{"centre": centre, "radius": radius}])


def test_editing_the_obstacles_a_task_returns_leaves_the_task_be(task):
    blocked = task.with_obstacles([{"centre": [0.4, 0.06, 0.0], "radius": 0.05}])
    blocked.obstacles[0]["radius"] = 1.0
    blocked.obstacles.append({"centre": [0.0, 0.0, 0.0], "radius": 0.1})
    assert blocked.obstacles == [{"centre": [0.4, 0.06, 0.0], "radius": 0.05}]


def test_the_block_keeps_the_other_good_routes_open(task, routes):
    thetas, route_list = routes
    pick = [route_list.index(r) for r in [(0, 0, 1), (0, 1, 1), (1, 1, 1)]]
    slightly_worse = thetas[pick].clone()
    slightly_worse[0, 0] += 0.02  # (0, 0, 1) is no longer the best: (0, 1, 1) or (1, 1, 1)
    obstacle, description = task.blocking_obstacle(slightly_worse, radius=0.08)
    blocked = task.with_obstacles([obstacle])
    returns = blocked.evaluate(slightly_worse)
    best = int(task.evaluate(slightly_worse).argmax())
    # The best route is blocked; of the other two, the pass time chosen leaves one open.
    assert float(returns[best]) < 0.1 and int((returns >= 0.9).sum()) >= 1
    assert "cm on the" in description and "viapoint at t = " in description
    # Alone, a route is blocked at its first pass time.
    obstacle, _ = task.blocking_obstacle(thetas[pick[0] : pick[0] + 1])
    assert obstacle["centre"] == pytest.approx(task.viapoints[0, 0].tolist())


@pytest.mark.parametrize(("other", "differs_at"), [((0, 1, 1), 1), ((0, 0, 0), 2)])
def test_the_block_sits_at_the_pass_time_where_the_other_good_route_differs(
    task, routes, other, differs_at
):
    """With one other good route, equal to the best one but at one pass time, the sphere goes
    on the best route's viapoint at that pass time (anywhere else it would block both)."""
    thetas, route_list = routes
    pair = thetas[[route_list.index((0, 0, 1)), route_list.index(other)]]
    returns = task.evaluate(pair)
    assert float(returns.min()) >= 0.9  # both good: the other route is to be kept open
    best_route = [(0, 0, 1), other][int(returns.argmax())]
    obstacle, description = task.blocking_obstacle(pair)
    expected = task.viapoints[differs_at, best_route[differs_at]].tolist()
    assert obstacle["centre"] == pytest.approx(expected, abs=1e-6)
    assert f"t = {task.pass_times[differs_at]:g} s" in description
    blocked = task.with_obstacles([obstacle]).evaluate(pair)
    assert float(blocked.min()) < 0.1 and float(blocked.max()) >= 0.9


def test_block_the_route_adds_the_obstacle_reevaluates_and_reports(task, routes):
    """train.py's block (dipole_torch.training.block) on a stand-in optimizer holding three
    route policies, on a task that already has an obstacle out of the way."""
    from types import SimpleNamespace

    from dipole_torch.training.block import block_the_route

    class Optimizer:
        def __init__(self, means):
            self.policy_means, self.trials, self.told = means, 300, None
            self.policy_set = SimpleNamespace(ids=torch.tensor([4, 7, 9]))

        def reevaluate(self, returns):
            self.told, self.trials = returns, self.trials + len(returns)

    class Board:
        def __init__(self):
            self.figures, self.texts = [], []

        def figure(self, tag, figure, step):
            self.figures.append((tag, step))

        def text(self, tag, text, step):
            self.texts.append((tag, text, step))

    thetas, _ = routes
    means = thetas[[0, 3, 5]]
    aside = {"centre": [0.0, 0.0, 1.5], "radius": 0.05}
    world = task.with_obstacles([aside])
    optimizer, board = Optimizer(means), Board()
    block = SimpleNamespace(radius=0.08, threshold=0.9)
    blocked, info = block_the_route(world, optimizer, block, board, torch.Generator())
    obstacle, description = world.blocking_obstacle(means, 0.08, 0.9)
    assert world.obstacles == [aside] and blocked.obstacles == [aside, obstacle]
    returns = blocked.evaluate(means)
    torch.testing.assert_close(optimizer.told, returns)
    best_before = int(world.evaluate(means).argmax())
    assert int(returns.argmax()) != best_before  # its route was blocked
    assert info == {
        "trial": 300,
        "obstacle": obstacle,
        "description": description,
        "returns": returns.tolist(),
        "switched_to": [4, 7, 9][int(returns.argmax())],
    }
    assert board.figures == [("world/before", 300), ("world/after", 303)]
    ((tag, report, step),) = board.texts
    assert tag == "world/block" and step == 303
    assert report.startswith(f"block at 300 trials: {description}; the 3 stored policies ")
    assert f"(now 303 trials), switching to policy {info['switched_to']}:" in report
    assert "\nbefore the block: 3 of the 8 routes at return ≥ 0.9" in report
    assert "\nafter it: 2 of the 8 routes at return ≥ 0.9" in report


def test_a_changed_world_empties_the_queued_hill_valley_tests():
    # Their thresholds are returns of the old world: no probe of them is asked after it.
    from dipole_torch.tasks.multimodal import MultimodalTask

    from dipole_torch.archive import PROBE

    task = MultimodalTask()
    opt = Dipole(task.theta0.double(), task.sigma_start.double(),
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    while opt.vetting.probes() is None and opt.iteration < 40:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta).double())
    assert opt.vetting.probes() is not None  # tests queued
    opt.reevaluate(task.evaluate(opt.policy_means.float()).double())
    assert opt.vetting.probes() is None
    opt.ask()
    assert not bool((opt.asked_owner == PROBE).any())


def test_a_changed_world_forgets_the_range_of_the_old_worlds_returns():
    # The range judges the spread of a policy's returns (retire_spread): the new world's are
    # measured afresh, in the state a checkpoint saves too.
    opt = Dipole(torch.zeros(2, dtype=torch.float64), 1.0,
                 generator=torch.Generator().manual_seed(0))  # fmt: skip
    for _ in range(6):
        theta = opt.ask()
        opt.tell(theta, -(theta - 1.0).pow(2).sum(-1))
    assert opt.state_dict()["returns_told"] > 0
    opt.reevaluate(-(opt.policy_means - 3.0).pow(2).sum(-1))
    state = opt.state_dict()
    assert (state["returns_told"], state["waking_low"], state["waking_high"]) == (
        0,
        math.inf,
        -math.inf,
    )


def test_dipole_switches_to_a_stored_route_within_k_trials():
    """The default DIPOLE (seed 3, 3 routes on the open layout, see test_viapoint): after 300
    trials its best route is blocked; re-evaluating its K stored policies (K trials, no
    relearning) finds one at return >= 0.9 on another route."""
    task = ViapointTask(kinematics="wam_dh")
    opt = Dipole(
        task.theta0.double(),
        task.sigma_start.double(),
        n0=30,
        generator=torch.Generator().manual_seed(3),
    )
    while opt.trials < 300:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta.float()))
    means = opt.policy_means.float()
    obstacle, _ = task.blocking_obstacle(means)
    blocked = task.with_obstacles([obstacle])
    before, trials = task.evaluate(means), opt.trials
    returns = blocked.evaluate(means)
    opt.reevaluate(returns)
    assert opt.trials == trials + len(means)
    assert float(returns[int(before.argmax())]) < 0.5  # the route it had was blocked
    assert opt.best()[1] >= 0.9  # a stored policy on another route
    switched = int(returns.argmax())
    assert (
        task.route(means[switched : switched + 1]).tolist()
        != task.route(means[int(before.argmax())][None]).tolist()
    )


@pytest.fixture(scope="module")
def blocked_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("blocked")
    train(
        "task=viapoint_blocked",
        "task.env.kinematics=wam_dh",
        "task.block.trial=45",
        "trials=75",
        "figure_every=0",
        f"hydra.run.dir={run_dir}",
    )
    return run_dir


def test_train_blocks_reevaluates_and_goes_on(blocked_run):
    results = json.loads((blocked_run / "results.json").read_text())
    block = results["block"]
    assert block["trial"] == 45 and results["trials"] == 75  # the block at its trial exactly
    assert block["obstacle"]["radius"] == 0.08 and "viapoint at t = " in block["description"]
    history = results["history"]
    after = history["trials"].index(block["trial"] + len(block["returns"]))
    assert history["trials"][after - 1] == block["trial"]  # the re-evaluation: K trials
    assert history["best_so_far"][after] == pytest.approx(max(block["returns"]))
    assert history["trials"][-1] > history["trials"][after]  # it went on learning
    events = EventAccumulator(str(blocked_run / "tensorboard"), size_guidance={"images": 0})
    events.Reload()
    assert {"world/before", "world/after", "search/figure"} <= set(events.Tags()["images"])
    assert events.Images("world/before")[0].step == block["trial"]
    assert [e.step for e in events.Scalars("reward/best_so_far")] == history["trials"]
    log = (blocked_run / "train.log").read_text()
    assert "block at" in log
    # The routes the stored policies take, before the block and after it.
    before = re.search(r"before the block: (\d) of the 8 routes at return ≥ 0.9", log)
    after = re.search(r"after it: (\d) of the 8 routes at return ≥ 0.9", log)
    assert before and after and int(after[1]) <= int(before[1]), log


def test_a_resumed_blocked_run_continues_exactly(blocked_run, tmp_path):
    common = ["task=viapoint_blocked", "task.env.kinematics=wam_dh", "task.block.trial=45"]
    train(*common, "trials=60", "figure_every=0", f"hydra.run.dir={tmp_path}")
    train(*common, "trials=75", "figure_every=0", f"resume={tmp_path / 'checkpoint.pt'}")
    resumed = json.loads((tmp_path / "results.json").read_text())
    whole = json.loads((blocked_run / "results.json").read_text())
    assert resumed["block"] == whole["block"]
    assert resumed["history"] == whole["history"]
    assert resumed["best_theta"] == whole["best_theta"]


def test_a_block_whose_reevaluation_would_pass_the_budget_ends_the_run_there(blocked_run, tmp_path):
    # At trial 45 the K stored policies would be re-evaluated; a budget one trial short of
    # that ends the run at 45 trials, unblocked, and results.json says 45 of the budget; a
    # budget it fits exactly blocks.
    k = len(json.loads((blocked_run / "results.json").read_text())["block"]["returns"])
    assert k >= 2  # (K = 1 would make the budget 45, refused: the block would never come)
    budget = 45 + k - 1
    common = ["task=viapoint_blocked", "task.env.kinematics=wam_dh", "task.block.trial=45"]
    train(*common, f"trials={budget}", "figure_every=0", f"hydra.run.dir={tmp_path}")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["trials"] == 45 and results["trial_budget"] == budget
    assert "block" not in results and results["history"]["trials"][-1] == 45
    log = (tmp_path / "train.log").read_text()
    assert f"no block: re-evaluating would take the run past {budget}" in log
    # Resumed with a budget the re-evaluation fits exactly, the block comes, at 45.
    train(*common, f"trials={45 + k}", "figure_every=0", f"resume={tmp_path / 'checkpoint.pt'}")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["trials"] == 45 + k and results["block"]["trial"] == 45
    assert len(results["block"]["returns"]) == k


def test_power_on_the_blocked_task(tmp_path):
    train(
        "task=viapoint_blocked",
        "algo=power",
        "task.env.kinematics=wam_dh",
        "task.block.trial=40",
        "trials=50",
        "figure_every=0",
        f"hydra.run.dir={tmp_path}",
    )
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["block"]["trial"] == 40 and len(results["block"]["returns"]) == 1
    assert results["trials"] == 50 and math.isfinite(results["best_reward"])


def test_a_block_before_the_first_batch_or_at_the_budget_is_refused():
    from dipole_torch.training.checks import check_config

    with pytest.raises(ValueError, match="task.block.trial=10 is below task.n0=30"):
        check_config(compose_config("task=viapoint_blocked", "task.block.trial=10"))
    # A block at or after the budget would never come: the run would look like plain viapoint.
    with pytest.raises(ValueError, match="task.block.trial=300 is not below trials=300"):
        check_config(compose_config("task=viapoint_blocked", "trials=300"))
