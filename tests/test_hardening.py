"""Inputs at the edges of what the optimizers accept: a flat first batch of any size, returns
near the largest float, tensors that track gradients, bad arguments (each error names the
argument), rows that were not asked, and checkpoints of another dimension."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch import Tensor

from dipole_torch import Dipole, NormalInverseWishartPrior, Power, RewardScale

F64 = torch.float64
OPTIMUM = torch.tensor([1.0, 1.0], dtype=F64)


def quadratic(theta: Tensor) -> Tensor:
    """1 at (1, 1), 0 on the circle of radius √2 around it (through θ0 = 0)."""
    return 1.0 - 0.5 * (theta - OPTIMUM).pow(2).sum(-1)


def build(kind: str, reward_range="default", dim: int = 2, seed: int = 0):
    theta0, g = torch.zeros(dim, dtype=F64), torch.Generator().manual_seed(seed)
    if kind == "dipole":
        return Dipole(theta0, 1.0, generator=g)
    if kind == "paper":
        rr = "positive" if reward_range == "default" else reward_range
        return Dipole.paper(theta0, 1.0, generator=g, reward_range=rr)
    rr = None if reward_range == "default" else reward_range
    return Power(theta0, 1.0, generator=g, reward_range=rr)


def tensors(value, path="state"):
    """Every tensor in a nested state dict, with where it lies."""
    if isinstance(value, Tensor):
        yield path, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from tensors(item, f"{path}[{key!r}]")
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            yield from tensors(item, f"{path}[{i}]")


def same_state(a, b) -> bool:
    if isinstance(a, Tensor):
        return isinstance(b, Tensor) and a.shape == b.shape and torch.equal(a, b)
    if isinstance(a, dict):
        return (
            isinstance(b, dict) and a.keys() == b.keys() and all(same_state(a[k], b[k]) for k in a)
        )
    return a == b


def offset_sphere(theta: Tensor) -> Tensor:
    """``[B]`` −1e6 − |θ|²: returns a function of θ, far from zero (mapped by their range)."""
    return -1e6 - theta.square().sum(-1)


def assert_resumes_identically(opt, copy, reward, iterations: int) -> None:
    """Load ``opt``'s state into ``copy``; both then ask the same and end in the same state."""
    copy.load_state_dict(opt.state_dict())
    for _ in range(iterations):
        a, b = opt.ask(), copy.ask()
        assert torch.equal(a, b)
        opt.tell(a, reward(a))
        copy.tell(b, reward(b))
    assert same_state(opt.state_dict(), copy.state_dict())


def run_to(opt, reward, trials: int, after_tell=lambda: None) -> None:
    """Ask, and tell ``reward``'s returns, until ``opt`` has told ``trials``; ``after_tell()``
    after each tell."""
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, reward(theta))
        after_tell()


def finite_policies(opt) -> bool:
    return bool(opt.policy_means.isfinite().all() and opt.policy_covariances.isfinite().all())


# ---------------------------------------------------------------------- a flat first batch
FLAT = [1000.0, -0.5, 1e300, 0.0, 1e-300, -1e-300]


def fitting_range(value: float) -> tuple[float, float]:
    width = max(abs(value), 1.0)
    return value - width, value + width


def flat_cases():
    for value in FLAT:
        yield pytest.param("dipole", "default", value, id=f"dipole-{value:g}")
        yield pytest.param("power", "default", value, id=f"power-{value:g}")
        yield pytest.param("paper", fitting_range(value), value, id=f"paper-range-{value:g}")


@pytest.mark.parametrize("kind, reward_range, value", list(flat_cases()))
def test_a_flat_first_batch_is_told_and_the_run_goes_on(kind, reward_range, value):
    opt = build(kind, reward_range)
    theta = opt.ask()
    opt.tell(theta, torch.full((theta.shape[0],), value, dtype=F64))
    assert finite_policies(opt)
    # Then returns that differ, on the flat batch's scale (inside the fixed range).
    scale = max(abs(value), 1e-300) if value else 1.0
    for _ in range(25):
        theta = opt.ask()
        returns = value + 0.5 * scale * quadratic(theta).clamp(-1.0, 1.0)
        opt.tell(theta, returns)
        assert finite_policies(opt)
    assert opt.trials >= 25
    assert opt.best()[1] > value  # it found returns above the flat batch's


@pytest.mark.parametrize("value", [1000.0, 1e-140])
def test_a_flat_first_batch_of_positive_returns_goes_on_in_the_papers_variant(value):
    opt = build("paper")  # reward_range="positive": the returns are the weights
    theta = opt.ask()
    opt.tell(theta, torch.full((theta.shape[0],), value, dtype=F64))
    for _ in range(10):
        theta = opt.ask()
        opt.tell(theta, value * (1.5 + 0.5 * quadratic(theta).clamp(-1.0, 1.0)))
        assert finite_policies(opt)
    assert opt.best()[1] > value


def test_a_fixed_reward_range_beyond_float32_is_accepted():
    scale = RewardScale(-1e300, 1e300)
    assert float(scale.weights(torch.tensor([0.0], dtype=F64))) == pytest.approx(0.5)


def test_a_reward_above_a_fixed_range_wider_than_the_largest_float_is_refused():
    # Built without __init__, which refuses such a range for another reason (float32 check).
    scale = RewardScale.__new__(RewardScale)
    scale.low, scale.high, scale.floor, scale.positive = -1.5e308, 1.5e308, 1e-3, False
    with pytest.raises(ValueError, match="outside reward_range"):
        scale.validate(torch.tensor([1.7e308], dtype=F64))


def test_reward_scale_maps_inverts_and_bounds_returns():
    """The reward map's pieces that tell() and ``Dipole.mixture`` use: w = (r − low) /
    (high − low) floored, its inverse and slope (a mixture in return units, fixed and
    adaptive ranges), the slack of 1e-9 of the range at its ends, the floor a fixed range
    is built with, a zero return refused as a positive weight, and a first positive batch
    judged by its largest weight."""
    scale = RewardScale(-10.0, 30.0, floor=0.01)
    weights = scale(torch.tensor([-10.0, 10.0, 30.0], dtype=F64))
    torch.testing.assert_close(weights, torch.tensor([0.01, 0.5, 1.0], dtype=F64))
    torch.testing.assert_close(
        scale.inverse(torch.tensor([0.25], dtype=F64)), torch.tensor([0.0], dtype=F64)
    )
    assert scale.slope() == 40.0
    reference = torch.tensor([2.0, 6.0, 3.0], dtype=F64)
    adaptive = RewardScale()
    torch.testing.assert_close(
        adaptive.inverse(torch.tensor([0.5], dtype=F64), reference), torch.tensor([4.0], dtype=F64)
    )
    assert adaptive.slope(reference) == 4.0
    scale.validate(torch.tensor([30.0 + 2e-8, -10.0 - 2e-8], dtype=F64))  # within the slack
    with pytest.raises(ValueError, match="outside reward_range"):
        scale.validate(torch.tensor([30.0 + 1e-6], dtype=F64))
    assert (
        Power([0.0, 0.0], 1.0, reward_range=(-10.0, 30.0), reward_floor=0.05).reward_scale.floor
        == 0.05
    )
    with pytest.raises(ValueError, match=r"floor must lie in \(0, 1\)"):
        RewardScale(floor=1.0)
    positive = RewardScale(positive=True)
    with pytest.raises(ValueError, match="must be positive"):
        positive.validate(torch.tensor([0.0, 1.0], dtype=F64))
    positive.validate(torch.tensor([1e-200, 1.0], dtype=F64), first=True)


def test_a_first_batch_of_positive_weights_too_small_to_square_is_refused_naming_the_limit():
    # The paper's variant weighs by the returns as they are; the DP mixture's variances are
    # their squares, which underflow to 0 below ~1e-154.
    opt = build("paper")
    theta = opt.ask()
    before = opt.state_dict()
    with pytest.raises(ValueError, match=r"first batch.*must reach 1e-150.*max 1e-300"):
        opt.tell(theta, torch.full((theta.shape[0],), 1e-300, dtype=F64))
    assert same_state(opt.state_dict(), before)
    opt.tell(theta, torch.full((theta.shape[0],), 1e-100, dtype=F64))  # rescaled: it goes on
    opt.tell(opt.ask(), torch.full((opt.batch_size,), 1e-300, dtype=F64))  # later: a poor batch
    assert finite_policies(opt)


def test_returns_far_beyond_the_first_batchs_scale_draw_no_label_from_nan():
    # The paper's variant weighs by the returns as they are, and H's reward scale comes
    # from the first batch: here 1e-150, then returns of 1e10.
    opt = build("paper")
    theta = opt.ask()
    opt.tell(theta, torch.full((theta.shape[0],), 1e-150, dtype=F64))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for _ in range(5):  # the fifth tell clusters
            theta = opt.ask()
            opt.tell(theta, 1e10 * (1.5 + quadratic(theta).clamp(-1.0, 1.0)))
    assert finite_policies(opt)


def test_returns_a_hundred_orders_beyond_the_first_batchs_adopt_no_absurd_policy():
    # Found by test_properties: returns of 1e9, then one of 4.6e148 beside parameters in
    # [-1, 1]. The clustering's covariances are then too ill-conditioned for float64 and its
    # estimate put a policy at 1e124 (inf once asked in float32): it must be skipped.
    theta0, g = torch.zeros(1, dtype=torch.float32), torch.Generator().manual_seed(185)
    opt = Dipole.paper(theta0, 0.8, generator=g)

    def bowl(t: Tensor) -> Tensor:
        return 1.5 + (1.0 - 0.5 * (t.to(F64) - 1.0).pow(2).sum(-1)).clamp(-1.0, 1.0)

    for scale in [1e9, 1.0, None, 1.0, 1e-9, 1e-9]:
        theta = opt.ask()
        if scale is None:
            opt.tell(theta, torch.tensor([4.622887283965605e148, 2.926049471361045e15], dtype=F64))
        else:
            opt.tell(theta, scale * bowl(theta))
        assert finite_policies(opt)
        assert float(opt.policy_means.abs().max()) < 10.0
    assert opt.clusterings_skipped >= 1
    assert bool(opt.ask().isfinite().all())


def test_a_first_clustering_that_fails_numerically_is_counted_and_one_component_adopted(
    monkeypatch,
):
    # (train.py logs the count to TensorBoard: search/clusterings_skipped.)
    from dipole_torch import DPSampler

    def singular(*args, **kwargs):
        raise torch.linalg.LinAlgError("a numerically singular covariance")

    monkeypatch.setattr(DPSampler, "fit", singular)
    opt = Dipole(torch.zeros(2, dtype=F64), 1.0, generator=torch.Generator().manual_seed(0))
    theta = opt.ask()
    opt.tell(theta, quadratic(theta))
    assert opt.clusterings_skipped == 1 and opt.num_policies == 1
    assert bool(opt.ask().isfinite().all())


# ---------------------------------------------------------------------- the largest floats
@pytest.mark.parametrize("kind", ["dipole", "power"])
def test_returns_of_plus_minus_1_5e308_are_told_and_learning_goes_on(kind):
    opt = build(kind, seed=1)  # a first batch with returns of both signs
    start = float(torch.linalg.norm(opt.policy_means[0] - OPTIMUM))
    overflowed = False
    while opt.trials < 200:
        theta = opt.ask()
        returns = 1.5e308 * quadratic(theta).clamp(-1.0, 1.0)
        opt.tell(theta, returns)
        # The kept returns' range overflows a float.
        overflowed |= math.isinf(float(opt.rewards.max()) - float(opt.rewards.min()))
        assert finite_policies(opt)
    assert overflowed
    best = opt.policy_means[opt.policy_best_rewards.argmax()]
    assert float(torch.linalg.norm(best - OPTIMUM)) < 0.25 < start
    assert opt.best()[1] > 0.9 * 1.5e308


# ---------------------------------------------------------------------- autograd
@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
def test_tensors_that_track_gradients_are_told_and_leave_no_graph(kind):
    opt = build(kind, reward_range=(-10.0, 2.0))
    for _ in range(12):
        theta = opt.ask().clone().requires_grad_()
        # (requires grad through theta; kept in the fixed range the optimizer is told)
        returns = quadratic(theta).clamp_min(-10.0)
        assert returns.requires_grad
        opt.tell(theta, returns)
    tracked = [path for path, value in tensors(opt.state_dict()) if value.requires_grad]
    assert tracked == []
    assert not opt.policy_means.requires_grad and not opt.best()[0].requires_grad
    assert not opt.policy_covariances.requires_grad and not opt.rewards.requires_grad
    # Later tells of plain tensors keep working.
    for _ in range(3):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta).clamp_min(-10.0))
    assert finite_policies(opt)


# ---------------------------------------------------------------------- bad arguments
@pytest.mark.parametrize("variant", ["dipole", "paper"])
@pytest.mark.parametrize(
    "option, value",
    [("regularization", "x"), ("explore", "x"), ("hill_valley", "no")],
)
def test_a_bad_option_is_refused_naming_it(variant, option, value):
    make = Dipole if variant == "dipole" else Dipole.paper
    with pytest.raises(ValueError, match=option):
        make(torch.zeros(2, dtype=F64), 1.0, **{option: value})


META_CASES = [
    ("theta0", lambda: (torch.zeros(2, device="meta"), 1.0)),
    ("sigma_start", lambda: (torch.zeros(2, dtype=F64), torch.ones(2, device="meta"))),
    ("sigma_start", lambda: (torch.zeros(2, dtype=F64), torch.eye(2, device="meta"))),
]


@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
@pytest.mark.parametrize("name, args", META_CASES)
def test_a_meta_tensor_is_refused_naming_the_argument(kind, name, args):
    make = {"dipole": Dipole, "paper": Dipole.paper, "power": Power}[kind]
    with pytest.raises(ValueError, match=f"{name} is a meta tensor"):
        make(*args())


@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
def test_bad_rewards_are_refused_naming_them_and_change_nothing(kind):
    opt = build(kind, reward_range=(-10.0, 2.0))
    theta = opt.ask()
    before = opt.state_dict()
    with pytest.raises(ValueError, match="rewards is a meta tensor"):
        opt.tell(theta, torch.zeros(theta.shape[0], device="meta"))
    with pytest.raises(TypeError, match="rewards must be"):
        opt.tell(theta, "abc")
    assert same_state(opt.state_dict(), before)
    opt.tell(theta, quadratic(theta))
    assert opt.trials == theta.shape[0]


@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
def test_a_told_meta_theta_is_refused_naming_it(kind):
    opt = build(kind, reward_range=(-10.0, 2.0))
    theta = opt.ask()
    before = opt.state_dict()
    with pytest.raises(ValueError, match="theta is a meta tensor"):
        opt.tell(torch.empty_like(theta, device="meta"), quadratic(theta))
    assert same_state(opt.state_dict(), before)


@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
def test_a_row_that_was_not_asked_is_refused_and_changes_nothing(kind):
    opt = build(kind, reward_range=(-10.0, 2.0))
    for _ in range(2):  # the first batch and a later one
        theta = opt.ask()
        before = opt.state_dict()
        moved = theta.clone()
        moved[-1, 0] += 1e-3
        with pytest.raises(ValueError, match=f"row {theta.shape[0] - 1} is not the row asked"):
            opt.tell(moved, quadratic(moved))
        assert same_state(opt.state_dict(), before)
        opt.tell(theta, quadratic(theta))


@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
def test_asking_twice_warns_and_tell_takes_the_second_ask(kind):
    opt = build(kind, reward_range=(-10.0, 2.0))
    first = opt.ask()
    with pytest.warns(UserWarning, match="ask\\(\\) again before tell\\(\\)"):
        second = opt.ask()
    assert not torch.equal(first, second)
    with pytest.raises(ValueError, match="not the row asked"):
        opt.tell(first, quadratic(first))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        opt.tell(second, quadratic(second))
        opt.tell(opt.ask(), torch.zeros(opt.batch_size, dtype=F64))


@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
@pytest.mark.parametrize("bad", ["abc", "longer", "nan"])
def test_bad_returns_to_reevaluate_are_refused_naming_them(kind, bad):
    opt = build(kind, reward_range=(-10.0, 2.0))
    theta = opt.ask()
    opt.tell(theta, quadratic(theta))
    k = opt.num_policies
    returns = {
        "abc": "abc",
        "longer": torch.zeros(k + 1, dtype=F64),
        "nan": torch.full((k,), math.nan, dtype=F64),
    }[bad]
    before = opt.state_dict()
    with pytest.raises((ValueError, TypeError), match="returns"):
        opt.reevaluate(returns)
    assert same_state(opt.state_dict(), before)


# ---------------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("kind", ["dipole", "paper", "power"])
@pytest.mark.parametrize("started", [False, True])
def test_a_state_of_another_dimension_is_refused_naming_both(kind, started):
    """It was refused naming an internal key (``state_dict['thetas'] must have shape
    [N, 2]``)."""
    other = build(kind, reward_range=(-10.0, 2.0), dim=3)
    if started:
        for _ in range(3):
            theta = other.ask()
            other.tell(theta, torch.zeros(theta.shape[0], dtype=F64))
    opt = build(kind, reward_range=(-10.0, 2.0))
    theta = opt.ask()
    opt.tell(theta, quadratic(theta))
    before = opt.state_dict()
    for strict in (True, False):
        with pytest.raises(
            ValueError, match=r"of dimension D = 3; this one has D = 2 \(its theta0"
        ):
            opt.load_state_dict(other.state_dict(), strict=strict)
    assert same_state(opt.state_dict(), before)
    for _ in range(3):  # still usable
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    assert opt.trials > before["trials"] and finite_policies(opt)


@pytest.mark.parametrize("kind", ["dipole", "power"])
def test_a_refused_state_changes_nothing(kind):
    opt = build(kind)
    for _ in range(2):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    before = opt.state_dict()
    state = opt.state_dict()
    state["thetas"], state["rewards"], state["owner"] = (
        state["thetas"][:1],
        state["rewards"][:1],
        state["owner"][:1],
    )
    state["policy_means"] = torch.zeros(1, 3, dtype=F64)
    with pytest.raises(ValueError, match="policy_means"):
        opt.load_state_dict(state)
    assert same_state(opt.state_dict(), before)


@pytest.mark.parametrize(
    "kind, other, named",
    [
        ("dipole", lambda: Dipole(torch.zeros(2, dtype=F64), 1.0, max_sampled=None),
         r"max_sampled: 4 saved, None here"),
        ("dipole", lambda: Dipole.paper(torch.zeros(2, dtype=F64), 1.0),
         r"importance: 'policy' saved, 'global' here"),
        ("dipole", lambda: Dipole(torch.zeros(2, dtype=F64), 2.0),
         r"sigma_start \(as a covariance\): \[\[1.0, 0.0\], \[0.0, 1.0\]\] saved, "
         r"\[\[4.0, 0.0\], \[0.0, 4.0\]\] here"),
        ("dipole", lambda: Dipole(torch.tensor([0.0, 1.0], dtype=F64), 1.0),
         r"theta0: \[0.0, 0.0\] saved, \[0.0, 1.0\] here"),
        ("dipole", lambda: Dipole(torch.zeros(2, dtype=F64), 1.0, bounds=(-3, 3)),
         r"bounds: None saved"),
        ("power", lambda: Power(torch.zeros(2, dtype=F64), 1.0, exploration_decay=0.9),
         r"exploration_decay: 1.0 saved, 0.9 here"),
        ("power", lambda: Power(torch.zeros(2, dtype=F64), 1.0, min_exploration=0.5),
         r"min_exploration: 0.01 saved, 0.5 here"),
        # Too large to show whole (a tensor of shape [3, 3] saved, and one here, it said):
        # where the two differ most.
        ("dipole3", lambda: Dipole(torch.zeros(3, dtype=F64), [1.0, 1.0, 3.0]),
         r"sigma_start \(as a covariance\): \[3, 3\] tensors that differ most at \[2, 2\]: "
         r"1 saved, 9 here"),
        ("dipole3", lambda: Dipole(torch.zeros(3, dtype=F64), 1.0, bounds=(-3, 3)),
         r"bounds: None saved, a tensor of shape \[2, 3\] here"),
    ],
)  # fmt: skip
def test_a_state_saved_with_other_settings_is_refused_naming_them(kind, other, named):
    """A state holds the run, not the settings its optimizer was built with: loaded into one
    built otherwise, the run went on silently under the other options, Σ_start or θ0."""
    dim = 3 if kind.endswith("3") else 2
    saved = build(kind.rstrip("3"), dim=dim)
    reward = quadratic if dim == 2 else lambda theta: -theta.square().sum(-1)
    for _ in range(3):
        theta = saved.ask()
        saved.tell(theta, reward(theta))
    state = saved.state_dict()
    opt = other()
    before = opt.state_dict()
    with pytest.raises(ValueError, match=named):
        opt.load_state_dict(state)
    assert same_state(opt.state_dict(), before)
    opt.load_state_dict(state, strict=False)  # a deliberate change: the run goes on
    assert torch.equal(opt.ask(), saved.ask())


def test_a_power_state_saved_with_other_best_evaluations_is_refused_naming_them():
    # (Not in the table above: loaded with strict=False, the run goes on with repeat rows,
    # so its next ask is not the saved one's.)
    saved = build("power")
    for _ in range(3):
        theta = saved.ask()
        saved.tell(theta, quadratic(theta))
    opt = Power(torch.zeros(2, dtype=F64), 1.0, best_evaluations=3)
    with pytest.raises(ValueError, match=r"best_evaluations: 1 saved, 3 here"):
        opt.load_state_dict(saved.state_dict())


def test_settings_that_differ_by_rounding_alone_still_load():
    # A task's θ0 computed on another device or engine may differ in its last bits.
    theta0 = torch.tensor([0.3, -0.7], dtype=F64)
    saved = Dipole(theta0, 1.0, generator=torch.Generator().manual_seed(0))
    theta = saved.ask()
    saved.tell(theta, quadratic(theta))
    state = saved.state_dict()
    opt = Dipole(theta0 + 1e-9, 1.0 + 1e-12)
    opt.load_state_dict(state)
    assert torch.equal(opt.ask(), saved.ask())
    with pytest.raises(ValueError, match="theta0: "):  # 1e-4 is no rounding
        Dipole(theta0 + 1e-4, 1.0).load_state_dict(state)
    # A state saved before an option existed lacks it, one saved after an option was removed
    # has it: the others are compared.
    del state["settings"]["coverage_from"]
    state["settings"]["an_option_since_removed"] = 1
    Dipole(theta0, 1.0, coverage_from=None).load_state_dict(state)
    with pytest.raises(ValueError, match="max_sampled: 4 saved, 2 here"):
        Dipole(theta0, 1.0, max_sampled=2).load_state_dict(state)
    del state["settings"]  # a state saved before settings were kept loads as before
    Dipole(torch.ones(2, dtype=F64), 1.0).load_state_dict(state)


def test_a_state_saved_with_a_box_open_on_every_side_loads_into_the_same_optimizer():
    # The box [2, D] is then all ±inf: no finite entry to compare, and equal.
    def make():
        return Dipole(torch.zeros(2, dtype=F64), 1.0, bounds=(-math.inf, math.inf),
                      generator=torch.Generator().manual_seed(0))  # fmt: skip

    saved = make()
    theta = saved.ask()
    saved.tell(theta, quadratic(theta))
    opt = make()
    opt.load_state_dict(saved.state_dict())
    assert torch.equal(opt.ask(), saved.ask())


def test_settings_are_compared_as_they_take_effect_not_as_given():
    # n0 left to its default 2M = 10 and n0=10 given are one optimizer; n0=12 is another.
    saved = Dipole(torch.zeros(2, dtype=F64), 1.0, generator=torch.Generator().manual_seed(0))
    theta = saved.ask()
    saved.tell(theta, quadratic(theta))
    state = saved.state_dict()
    Dipole(torch.zeros(2, dtype=F64), 1.0, n0=10).load_state_dict(state)
    with pytest.raises(ValueError, match="n0: 10 saved, 12 here"):
        Dipole(torch.zeros(2, dtype=F64), 1.0, n0=12).load_state_dict(state)


def test_a_state_without_a_dipole_key_is_refused_naming_it():
    opt = build("dipole")
    theta = opt.ask()
    opt.tell(theta, quadratic(theta))
    state = opt.state_dict()
    del state["initial_prior"]
    fresh = build("dipole")
    with pytest.raises(ValueError, match=r"state_dict has no 'initial_prior' \(not a Dipole's\)"):
        fresh.load_state_dict(state)


def test_a_checkpoint_round_trip_continues_identically():
    # (The refusals above must not cost the plain case: load, then the same draws.)
    opt = build("dipole")
    for _ in range(4):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    assert_resumes_identically(opt, build("dipole", seed=99), quadratic, 4)
    assert math.isfinite(opt.best()[1])


@pytest.fixture
def lone_policies_clustered(monkeypatch):
    """Every clustering runs, also one that sees a lone policy's samples alone (the default
    skips it: ``OverlapMatching.clustered_rows``). The states the two tests below need, a
    prior drawn from a converged lone policy's samples, arise from those clusterings."""
    from dipole_torch.mechanisms.matching import OverlapMatching, policy_and_scout_rows

    def every_clustering(self, search):
        return policy_and_scout_rows(search.archive.owner, search.clustered_policies)

    monkeypatch.setattr(OverlapMatching, "clustered_rows", every_clustering)


def test_a_run_whose_chain_drew_a_nearly_singular_prior_resumes_from_its_checkpoint(
    lone_policies_clustered,
):
    """A long successful run without regularisation or retirement: its policies converge
    on the optimum, their covariances shrink, and the DP prior that H's Gibbs update draws
    from them is closer to singular than a prior a user may pass (correlation eigenvalue
    below 1e-10, here by trial ~760). Its checkpoint must load and continue the same run.
    (The run with Igel et al.'s success target 2/11, the default when it was found.)"""
    from dipole_torch.prior import NormalInverseWishartPrior
    from dipole_torch.validation import check_well_conditioned

    def make(seed):
        return Dipole(torch.full((3,), -0.2, dtype=F64), torch.eye(3, dtype=F64),
                      regularization=0.0, retire_std=0.0, success_target=2.0 / 11.0,
                      generator=torch.Generator().manual_seed(seed))  # fmt: skip

    opt = make(0)
    run_to(opt, offset_sphere, 800)
    prior = opt.dp_state.prior
    with pytest.raises(ValueError, match="too close to singular"):
        check_well_conditioned(prior.scale, "scale")  # what a user-given prior must pass
    assert_resumes_identically(opt, make(99), offset_sphere, 10)
    # Restoring still refuses what is malformed, naming it.
    state = prior.state_dict()
    with pytest.raises(ValueError, match="scale"):
        NormalInverseWishartPrior.from_state_dict({**state, "scale": -state["scale"]})
    with pytest.raises(ValueError, match="holds"):
        NormalInverseWishartPrior.from_state_dict({k: v for k, v in state.items() if k != "df"})


def test_a_gibbs_update_that_rounds_h_off_positive_definite_fails_its_sweep_not_the_chain(
    monkeypatch, lone_policies_clustered
):
    """Without regularisation, on returns that are a function of θ, a converged policy's
    components are nearly singular along the curve (θ, r(θ)), and H's Gibbs update can draw
    a scale Ψ0 that is positive definite only in exact arithmetic. That sweep fails and the
    clustering is skipped; the chain never keeps such an H (which would fail every later
    clustering and every checkpoint load). This option set and seed reach it by trial 905."""
    from dipole_torch.prior import NormalInverseWishartPrior

    update, refused = NormalInverseWishartPrior.updated, []

    def counting_update(self, *args, **kwargs):
        try:
            return update(self, *args, **kwargs)
        except torch.linalg.LinAlgError:
            refused.append(True)
            raise

    monkeypatch.setattr(NormalInverseWishartPrior, "updated", counting_update)

    def make(seed):
        return Dipole(torch.full((1,), 0.38, dtype=F64), torch.eye(1, dtype=F64),
                      importance="global", explore=0.0, hill_valley=False, max_policies=2,
                      max_sampled=1, retire_std=0.0, merge_radius=0.0, settle=3, alpha=0.01,
                      m=1, regularization=0.0, reward_weighted=False,
                      generator=torch.Generator().manual_seed(seed))  # fmt: skip

    def h_factorises():
        for name in ("scale", "mean_covariance"):
            _, info = torch.linalg.cholesky_ex(getattr(opt.dp_state.prior, name))
            assert int(info) == 0, f"the chain kept an H whose {name} does not factorise"

    opt = make(703)
    run_to(opt, offset_sphere, 1000, after_tell=h_factorises)
    assert refused, "the run no longer reaches a refused update of H: choose another seed"
    assert opt.clusterings_skipped > 0
    assert_resumes_identically(opt, make(99), offset_sphere, 5)


def test_the_papers_variant_without_regularisation_runs_on_once_its_samples_coincide():
    """The paper's variant explores with its components' posterior covariances. Without
    regularisation, once a policy's M kept samples are one point (its exploration collapsed
    on a cone's slope), its component's scatter is zero and H's update draws a scale Ψ0
    singular to rounding: the estimate's covariance had a correlation of 1 − 1e-16 (or a
    negative eigenvalue), its mean lay off the data, and the next ask failed to factorise it
    (found by ``tests/fuzz_long_runs.py``, seed 12287). Such an estimate is refused and the
    clustering skipped: every policy keeps an exploration that factorises and a mean near
    its samples."""
    centre = torch.tensor([-1.8, -2.91], dtype=F64)

    def cone(theta: Tensor) -> Tensor:
        return 1.0 - (theta - centre).norm(dim=-1).sqrt()

    opt = Dipole.paper(torch.full((2,), 0.4757, dtype=F64), 1e-3 * torch.eye(2, dtype=F64),
                       M=10, alpha=0.01, m=1, regularization=0.0, settle=None, reward_range=None,
                       generator=torch.Generator().manual_seed(12287))  # fmt: skip

    def sound():
        _, info = torch.linalg.cholesky_ex(opt.policy_covariances)
        assert not info.any(), "a policy's exploration does not factorise"
        gone = (opt.policy_means[:, None] - opt.archive.thetas).norm(dim=-1).amin(-1).max()
        assert gone < 0.1, "a policy's mean left its samples"

    run_to(opt, cone, 2200, after_tell=sound)
    assert opt.clusterings_skipped > 0, "the run no longer reaches a refused estimate"


def test_global_importance_with_only_scouts_among_the_kept_samples_runs_on():
    """``importance="global"`` keeps the best K·M samples of all; with M = 1 and many scouts
    they can all be scouts', so that no policy owns a sample. The policies then take no
    step (their importance sets are empty) and the run goes on."""
    from dipole_torch.power import importance_rows

    owner = torch.tensor([-1, -1, -1])
    kept, rows, valid = importance_rows(owner, torch.tensor([0.3, 0.1, 0.2], dtype=F64), 2, 3)
    assert kept.tolist() == [0, 1, 2] and not valid.any() and rows.shape == (2, 3)

    # Two peaks, the second narrow; this seed's first iteration kept only scouts' samples.
    def peaks(theta: Tensor) -> Tensor:
        return torch.exp(-(theta - 1).square().sum(-1)) + 0.8 * torch.exp(
            -(theta + 2).square().sum(-1) / 0.01
        )

    opt = Dipole(torch.zeros(5), torch.eye(5), bounds=(-5.0, 5.0), importance="global",
                 explore=0.5, M=1, generator=torch.Generator().manual_seed(1))  # fmt: skip
    run_to(opt, peaks, 300)
    assert torch.isfinite(opt.policy_means).all() and opt.num_policies >= 1


# ------------------------------------------------------------------ what a caller holds
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("kind", ["dipole", "power"])
def test_editing_what_ask_and_result_return_leaves_the_run_be(kind, dtype):
    """ask's rows, best(), result and policies are the caller's copies: editing them in place
    changes nothing in the optimizer (a float64 ask once returned its pending rows, so rows
    scaled in place were told past the checks of the box and of the rows asked)."""
    opt = (
        Dipole(torch.zeros(2, dtype=dtype), 1.0, bounds=(-1.0, 1.0))
        if kind == "dipole"
        else (Power(torch.zeros(2, dtype=dtype), 1.0, bounds=(-1.0, 1.0)))
    )
    for _ in range(3):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta.double()))
    theta = opt.ask()
    theta.mul_(50.0)
    with pytest.raises(ValueError, match="outside bounds|not the row asked"):
        opt.tell(theta, quadratic(theta.double()))
    means, best = opt.policy_means.clone(), opt.best()[0].clone()
    result = opt.result
    result.means.add_(5.0)
    result.covariances.mul_(2.0)
    result.best_theta.add_(1.0)
    opt.best()[0].add_(1e6)
    opt.policies.means.add_(3.0)
    assert torch.equal(opt.policy_means, means) and torch.equal(opt.best()[0], best)


@pytest.mark.parametrize("kind", ["dipole", "power"])
def test_editing_what_the_caller_passed_in_leaves_the_run_be(kind):
    """θ0, Σ_start and the bounds given to the constructor, and the returns told, are taken
    as copies: the caller editing those tensors in place afterwards (a reused buffer) changes
    neither the settings nor the run (float64 θ0 and Σ_start were once kept as the caller's
    tensors, and the first tell's returns as ``last_rewards``)."""
    cls = Dipole if kind == "dipole" else Power

    def make(theta0, sigma, lower):
        return cls(theta0, sigma, generator=torch.Generator().manual_seed(0), bounds=(lower, 2.0))

    theta0, sigma = torch.zeros(2, dtype=F64), 0.25 * torch.eye(2, dtype=F64)
    lower = torch.full((2,), -2.0, dtype=F64)
    opt, twin = make(theta0, sigma, lower), make(theta0.clone(), sigma.clone(), lower.clone())
    theta0.add_(1.0), sigma.mul_(100.0), lower.add_(1.5)
    assert torch.equal(opt.theta0, twin.theta0) and torch.equal(opt.sigma_start, twin.sigma_start)
    assert torch.equal(opt.box[0], twin.box[0])
    theta = opt.ask()
    assert torch.equal(theta, twin.ask())
    rewards = quadratic(theta)
    opt.tell(theta, rewards)
    twin.tell(theta.clone(), rewards.clone())
    rewards.fill_(7.0)
    theta.fill_(1.5)
    assert torch.equal(opt.last_rewards, twin.last_rewards)
    assert torch.equal(opt.thetas, twin.thetas) and torch.equal(opt.rewards, twin.rewards)
    assert torch.equal(opt.best()[0], twin.best()[0])
    twin.load_state_dict(opt.state_dict())  # the settings compared are still equal


@pytest.mark.parametrize("kind", ["dipole", "power"])
def test_editing_the_rows_and_returns_told_leaves_the_run_be(kind):
    """The rows and returns told are taken as copies: the caller editing its tensors in place
    after ``tell`` changes neither ``best()`` nor ``last_rewards`` (with no box, a float64
    row told is the caller's own until copied; the first tell's returns were once kept as
    ``last_rewards`` itself)."""
    opt = build(kind)
    for shift in (0.0, 10.0):  # the first batch, then a batch holding a new best
        theta = opt.ask()
        rewards = quadratic(theta) + shift
        opt.tell(theta, rewards)
        (best_theta, best_reward), last = opt.best(), opt.last_rewards.clone()
        assert best_reward == float(rewards.max())
        theta.add_(1.0)
        rewards.fill_(-7.0)
        assert torch.equal(opt.best()[0], best_theta) and torch.equal(opt.last_rewards, last)


@pytest.mark.parametrize("kind", ["dipole", "power"])
def test_a_copy_or_a_pickle_of_an_optimizer_goes_on_as_the_original(kind):
    import copy
    import pickle

    opt = build(kind)
    for _ in range(5):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    twins = copy.deepcopy(opt), pickle.loads(pickle.dumps(opt))
    for _ in range(5):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
        for twin in twins:
            asked = twin.ask()
            assert torch.equal(asked, theta)
            twin.tell(asked, quadratic(asked))


def test_rows_told_back_in_another_float_dtype_are_the_rows_asked():
    """A float32 optimizer's rows told as float64 (or a float64 one's as float32) are the
    rows asked: compared in the narrower dtype (float64 rows of float32 ones were refused)."""
    for dtype, told in ((torch.float32, torch.float64), (torch.float64, torch.float32)):
        opt = Dipole(torch.zeros(2, dtype=dtype), 0.5)
        theta = opt.ask()
        opt.tell(theta.to(told), quadratic(theta.double()))
        theta = opt.ask()
        with pytest.raises(ValueError, match="theta row 0 is not the row asked"):
            opt.tell((theta + 1e-3).to(told), quadratic(theta.double()))


@pytest.mark.parametrize("std", [1e151, 1e200, 1e-151, 1e-200])
@pytest.mark.parametrize("cls", [Dipole, Power])
def test_a_start_whose_variances_leave_float64_is_refused(cls, std):
    with pytest.raises(ValueError, match="sigma_start's variances must lie between 1e-300"):
        cls([0.0, 0.0], std)
    if std in (1e151, 1e-151):  # as a covariance too (1e±400 is no float64: inf or 0)
        with pytest.raises(ValueError, match="sigma_start's variances must lie between"):
            cls([0.0, 0.0], torch.diag(torch.tensor([1.0, std**2], dtype=F64)))


@pytest.mark.parametrize("std", [1e150, 1e-150])
def test_a_start_at_the_edge_of_the_range_runs(std):
    opt = Dipole([0.0, 0.0], std, generator=torch.Generator().manual_seed(0))
    for _ in range(40):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta / std))
    assert opt.trials > 40 and math.isfinite(opt.best()[1])


# ------------------------------------------------------------------ states that do not fit
def _bad(state, key, value):
    state = {**state}
    if isinstance(key, tuple):
        state[key[0]] = {**state[key[0]], key[1]: value}
    else:
        state[key] = value
    return state


@pytest.mark.parametrize(
    "key, edit, message",
    [
        ("rewards", lambda v: v.fill_(math.nan), r"state_dict\['rewards'\] contains"),
        ("thetas", lambda v: v.fill_(math.inf), r"state_dict\['thetas'\] contains"),
        ("policy_means", lambda v: v.fill_(math.nan), r"state_dict\['policy_means'\] contains"),
        (
            "policy_covariances",
            lambda v: v.neg_(),
            "policy_covariances'] is not positive semi-definite",
        ),
        ("best_reward", lambda v: math.nan, r"state_dict\['best_reward'\] must be a return"),
        ("best_theta", lambda v: v[:1], r"state_dict\['best_theta'\] must have shape \[2\]"),
        (("dp_state", "labels"), lambda v: v + 100, r"dp_state'\].labels must lie in \[0, "),
        (("dp_state", "means"), lambda v: v[:, :2], r"dp_state'\].means must have shape \[K, 3\]"),
        (("dp_state", "covariances"), lambda v: -v, "dp_state'].covariances is not positive"),
        (
            "initial_prior",  # (replaced by H over [θ, w] of a D = 3 run)
            lambda v: NormalInverseWishartPrior.from_exploration(
                torch.zeros(4, dtype=F64), torch.eye(4, dtype=F64)
            ).state_dict(),
            r"state_dict\['initial_prior'\] is over 4 dimensions, not D \+ 1 = 3",
        ),
    ],
)
def test_a_state_with_values_that_cannot_be_a_runs_is_refused(key, edit, message):
    opt = build("dipole")
    for _ in range(8):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    state = opt.state_dict()
    if isinstance(key, tuple):
        value = edit(state[key[0]][key[1]].clone())
    else:
        value = state[key]
        value = edit(value.clone() if isinstance(value, Tensor) else value)
    fresh = build("dipole")
    fresh_state = fresh.state_dict()
    with pytest.raises(ValueError, match=message):
        fresh.load_state_dict(_bad(state, key, value))
    for k, v in fresh.state_dict().items():  # left as it was
        if isinstance(v, Tensor):
            assert torch.equal(v, fresh_state[k]), k


def test_a_retired_policys_exploration_rounded_to_zero_restores_from_a_checkpoint():
    """A run can leave a retired policy's covariance singular (found by the fuzz of long
    runs: a policy started at a spread that underflowed to zero, seed 31039): its checkpoint
    was refused as "not positive definite". Retired, it loads and the run goes on; active
    (it would be sampled), it is refused, naming the policy."""
    opt = build("dipole")
    for _ in range(8):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    state = opt.state_dict()
    assert state["policy_covariances"].shape[0] >= 2
    state["policy_covariances"] = state["policy_covariances"].clone()
    state["policy_covariances"][0] = 0.0
    state["active"] = state["active"].clone()
    state["active"][0] = True
    fresh = build("dipole", seed=1)
    with pytest.raises(ValueError, match=r"not positive definite for the active policies \[0\]"):
        fresh.load_state_dict(state)
    state["active"][0] = False
    fresh.load_state_dict(state)
    assert torch.equal(fresh.policy_covariances[0], torch.zeros(2, 2, dtype=F64))
    for _ in range(30):
        theta = fresh.ask()
        assert torch.isfinite(theta).all()
        fresh.tell(theta, quadratic(theta))
    assert math.isfinite(fresh.best()[1]) and not bool(fresh.active[0])


def test_the_dp_sampler_refuses_what_would_corrupt_a_chain():
    from dipole_torch import DPMixtureState, DPSampler, NormalInverseWishartPrior

    prior = NormalInverseWishartPrior.from_exploration(torch.zeros(2, dtype=F64), torch.eye(2))
    with pytest.raises(ValueError, match="alpha must be a positive finite number"):
        DPSampler(prior, alpha=math.inf)
    with pytest.raises(ValueError, match="df must be a real number, got '5'"):
        NormalInverseWishartPrior(
            prior.mean_loc, prior.mean_covariance, "5", prior.scale, prior.regularization
        )
    with pytest.raises(ValueError, match="df must be finite"):
        NormalInverseWishartPrior.from_exploration(
            torch.zeros(2, dtype=F64), torch.eye(2), df=math.inf
        )
    with pytest.raises(ValueError, match="regularization must be symmetric positive semi"):
        NormalInverseWishartPrior.from_exploration(
            torch.zeros(2, dtype=F64), torch.eye(2), regularization=-1.0
        )
    y = torch.randn(6, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    sampler = DPSampler(prior, alpha=1.0)
    state = sampler.fit(y, num_sweeps=2, generator=torch.Generator().manual_seed(1))
    k = state.num_components  # (a label k is one too many)
    for changes, message in (
        ({"labels": state.labels.double()}, "state.labels must be \\[N\\] integers"),
        ({"labels": state.labels + 5}, "state.labels must lie in"),
        ({"labels": torch.full_like(state.labels, k)}, "state.labels must lie in \\[0, "),
        ({"means": state.means[:, :1]}, "state.means must have shape \\[K, 2\\]"),
        ({"covariances": state.covariances[:, :1]}, "state.covariances must have shape"),
    ):
        bad = DPMixtureState(**{**vars(state), **changes})
        with pytest.raises(ValueError, match=message):
            sampler.fit(y, num_sweeps=1, state=bad)
    with pytest.raises(ValueError, match="labels must have shape \\[N\\] for y \\[N, D\\]"):
        DPMixtureState.from_labels(y, torch.zeros(0, dtype=torch.long), prior)
    with pytest.raises(ValueError, match="labels must be an integer tensor"):
        DPMixtureState.from_labels(y, torch.zeros(6), prior)


@pytest.mark.parametrize("method", ["neal8", "slice"])
def test_a_chain_may_start_with_a_component_that_holds_no_point(method):
    """The paper's clustering starts from every policy's component, and a policy may own
    none of the points clustered: the start's check refused that chain (the fuzz of long
    runs, seed 31522, a ``ValueError`` at 3000 trials); the sampler gives the component no
    point, as before the check, and the partition goes on from the occupied ones."""
    from dipole_torch import DPMixtureState, DPSampler, NormalInverseWishartPrior

    prior = NormalInverseWishartPrior.from_exploration(torch.zeros(2, dtype=F64), torch.eye(2))
    y = torch.randn(12, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    occupied = DPMixtureState.from_labels(y, torch.tensor([0] * 6 + [1] * 6), prior)
    start = DPMixtureState(
        labels=occupied.labels,
        means=torch.cat((occupied.means, torch.full((1, 2), 50.0, dtype=F64))),
        covariances=torch.cat((occupied.covariances, 1e-4 * torch.eye(2, dtype=F64)[None])),
        prior=prior,
    )
    with pytest.raises(ValueError, match="every component of means must hold a point"):
        start.check(2, 12)  # a state to load or to score still needs every component
    state = DPSampler(prior, method=method).fit(
        y, num_sweeps=3, generator=torch.Generator().manual_seed(1), state=start
    )
    assert (state.counts > 0).all() and state.counts.sum() == 12
    assert bool((state.means - 50.0).abs().gt(10.0).all())  # the empty one was dropped


def test_small_inputs_of_the_wrong_kind_get_a_clear_error_or_are_taken_as_meant():
    import numpy as np

    from dipole_torch.gaussian_mixture import GaussianMixture

    mixture = GaussianMixture(torch.ones(2), torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3))
    for dims in ([0.5], [True]):
        with pytest.raises(ValueError, match="dims must be integers"):
            mixture.condition(dims, torch.zeros(1))
    mixture.condition([np.int64(0)], torch.zeros(1))  # numpy integers are integers
    with pytest.raises(ValueError, match="reward_range must be None, \\(low, high\\)"):
        Power([0.0, 0.0], 1.0, reward_range=np.array([0.0, 1.0]))
    with pytest.raises(TypeError, match="options must be a DipoleOptions, got dict"):
        Dipole([0.0, 0.0], 1.0, options={"M": 3})
    boxed = Dipole(np.zeros(2), 1.0, bounds=(np.full(2, -1.0), np.ones(2)))
    assert bool((boxed.ask().abs() <= 1.0).all())


def test_numpy_numbers_are_taken_as_options_and_counts_and_saved_as_python_numbers():
    import io

    import numpy as np

    opt = Dipole([0.0, 0.0], 1.0, M=np.int64(3), alpha=np.float32(1.0), n0=np.int64(6))
    assert type(opt.options.M) is int and type(opt.options.alpha) is float
    theta = opt.ask(max_rows=np.int64(4))
    assert theta.shape == (4, 2)
    opt.tell(theta, quadratic(theta))
    buffer = io.BytesIO()
    torch.save(opt.state_dict(), buffer)  # loads without numpy's globals (a checkpoint's way)
    buffer.seek(0)
    build("dipole").load_state_dict(torch.load(buffer, weights_only=True), strict=False)


def test_a_dp_state_missing_a_part_is_refused_naming_it():
    opt = build("dipole")
    for _ in range(8):
        theta = opt.ask()
        opt.tell(theta, quadratic(theta))
    state = opt.state_dict()
    state["dp_state"] = {k: v for k, v in state["dp_state"].items() if k != "labels"}
    with pytest.raises(ValueError, match=r"a DP mixture state's dict lacks \['labels'\]"):
        build("dipole").load_state_dict(state)


@pytest.mark.parametrize("kind", ["dipole", "power"])
@pytest.mark.parametrize("length", [1, 3])
def test_stds_of_another_length_than_theta0_are_refused(kind, length):
    """``[D]`` stds of another length are refused naming the shapes, a single one in a
    list too (it is not taken as one std for every axis)."""
    cls = Dipole if kind == "dipole" else Power
    with pytest.raises(ValueError, match=r"sigma_start must have shape \[2, 2\]"):
        cls(torch.zeros(2, dtype=F64), torch.ones(length, dtype=F64))


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_a_matrix_is_symmetric_to_1e_6_of_its_largest_variance_at_any_scale(scale):
    """A covariance whose two off-diagonal entries differ by 1e-7 of its largest variance
    passes (rounding); by 5e-6 of it, it is refused, naming it, whatever its units."""
    from dipole_torch.validation import check_positive_definite

    def matrix(asymmetry):
        return torch.tensor([[2.0, 0.5], [0.5 + 2.0 * asymmetry, 1.0]], dtype=F64) * scale

    check_positive_definite(matrix(1e-7), "sigma_start")
    with pytest.raises(ValueError, match="sigma_start is not symmetric"):
        check_positive_definite(matrix(5e-6), "sigma_start")


def test_a_non_finite_value_is_named_by_its_first_index():
    from dipole_torch.validation import check_finite

    values = torch.tensor([[0.0, 1.0, math.nan], [math.inf, 0.0, -math.inf]], dtype=F64)
    with pytest.raises(
        ValueError, match=r"rewards contains non-finite values \(first at index \(0, 2\)\)"
    ):
        check_finite(values, "rewards")


def test_a_tensor_with_more_dimensions_than_its_shape_is_refused_naming_it():
    # [N, 1] rewards (a column) broadcast against [N] ones into an [N, N] mess.
    from dipole_torch.validation import check_matrix_shape

    check_matrix_shape(torch.zeros(3), (-1,), "rewards")
    with pytest.raises(ValueError, match=r"rewards must have shape \[N\], got \[3, 1\]"):
        check_matrix_shape(torch.zeros(3, 1), (-1,), "rewards")
    with pytest.raises(ValueError, match=r"theta must have shape \[N, 2\], got \[2\]"):
        check_matrix_shape(torch.zeros(2), (-1, 2), "theta")


def test_semi_definiteness_allows_rounding_relative_to_the_largest_variance():
    """A negative eigenvalue within 1e-9 of the largest variance is rounding (a covariance
    shrunk to rank one, restored from a checkpoint); beyond it, the matrix is refused."""
    from dipole_torch.validation import check_positive_semidefinite

    def matrix(scale, negative):
        return torch.diag(torch.tensor([scale, -negative * scale], dtype=F64))

    for scale in (1e-6, 1.0, 1e6):
        check_positive_semidefinite(matrix(scale, 1e-10), "covariances")
        with pytest.raises(ValueError, match="covariances is not positive semi-definite"):
            check_positive_semidefinite(matrix(scale, 1e-8), "covariances")
