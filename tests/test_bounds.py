"""Box bounds on the parameters (``bounds=(lower, upper)``): every asked row and policy mean
stays in the box, optima on its boundary are reached exactly, told rows outside it and bad
boxes raise."""

import pytest
import torch

from dipole_torch import Dipole, Power

DTYPE = torch.float64
LOWER = torch.tensor([-1.0, 0.0], dtype=DTYPE)
UPPER = torch.tensor([2.0, 0.5], dtype=DTYPE)

BUILDERS = {"dipole": Dipole, "dipole_paper": Dipole.paper, "power": Power}


def make(name: str, **kwargs):
    theta0 = torch.tensor([0.5, 0.25], dtype=DTYPE)
    g = torch.Generator().manual_seed(3)
    return BUILDERS[name](theta0, torch.eye(2, dtype=DTYPE), bounds=(LOWER, UPPER), generator=g,
                          **kwargs)  # fmt: skip


def uphill(theta: torch.Tensor) -> torch.Tensor:
    """Positive and increasing along both axes: its maximum in the box is the upper corner,
    and beyond the box it keeps rising."""
    return 1.0 + (theta - LOWER).sum(-1)


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_asked_rows_and_policy_means_stay_in_the_box(name):
    opt = make(name)
    clipped = 0
    while opt.trials < 400:
        theta = opt.ask()
        assert ((theta >= LOWER) & (theta <= UPPER)).all()
        clipped += int(((theta == LOWER) | (theta == UPPER)).any(-1).sum())
        opt.tell(theta, uphill(theta))
        assert ((opt.policy_means >= LOWER) & (opt.policy_means <= UPPER)).all()
    # The box was in the way (exploration std 1 against widths 3 and 0.5). (DIPOLE retires
    # its policy soon after it reaches the corner: the clipped samples' returns are equal.)
    assert clipped > 20
    if name != "dipole_paper":  # (the paper's variant never shrinks its exploration)
        assert torch.allclose(opt.best()[0], UPPER, atol=1e-3)


def test_optima_on_both_ends_of_the_box_are_found_exactly():
    # Two global optima on the box's ends (as in a joint-limit task, or the five-uneven-peak
    # trap); the function rises beyond them, so without the box the policies would leave.
    def trap(theta):
        return (theta[:, 0] - 15.0).abs()

    opt = Dipole(
        torch.tensor([15.0], dtype=DTYPE),
        torch.tensor([[7.5**2]], dtype=DTYPE),
        bounds=(0.0, 30.0),
        generator=torch.Generator().manual_seed(0),
    )
    while opt.trials < 600:
        theta = opt.ask()
        opt.tell(theta, trap(theta))
    means = opt.policy_means[:, 0]
    assert ((means >= 0.0) & (means <= 30.0)).all()
    assert bool((means == 0.0).any()) and bool((means - 30.0).abs().min() < 1e-9)


def test_a_told_row_outside_the_box_raises_and_changes_nothing():
    opt = make("dipole")
    theta = opt.ask()
    opt.tell(theta, uphill(theta))
    theta = opt.ask()
    bad = theta.clone()
    row = theta.shape[0] - 1  # (a policy's sample, or a scout or probe)
    bad[row, 1] = 0.75
    before = opt.state_dict()
    message = rf"theta row {row} lies outside bounds on axis 1: 0.75"
    with pytest.raises(ValueError, match=message):
        opt.tell(bad, uphill(theta))
    after = opt.state_dict()
    assert after["trials"] == before["trials"]
    assert torch.equal(after["thetas"], before["thetas"])
    opt.tell(theta, uphill(theta))  # the same ask can still be told


def test_float32_rows_clipped_to_a_bound_are_told_back_without_error():
    # 0.1 and 0.7 are not float32 numbers: the clipped float64 row, rounded to float32,
    # must still count as inside.
    opt = Dipole(
        torch.tensor([0.4], dtype=torch.float32),
        torch.tensor([[1.0]], dtype=torch.float32),
        bounds=(0.1, 0.7),
        generator=torch.Generator().manual_seed(1),
    )
    while opt.trials < 100:
        theta = opt.ask()
        assert theta.dtype == torch.float32
        opt.tell(theta, -(theta[:, 0] - 0.4).square())
    assert ((opt.policy_means >= 0.1) & (opt.policy_means <= 0.7)).all()


def test_bounds_as_lists_of_numbers():
    opt = Dipole(torch.zeros(2, dtype=DTYPE), torch.eye(2, dtype=DTYPE), bounds=([-1, -2], [1, 2]))
    assert opt.box[0].tolist() == [-1.0, -2.0] and opt.box[1].tolist() == [1.0, 2.0]
    with pytest.raises(TypeError, match="bounds' upper must be a number"):
        Dipole(torch.zeros(2, dtype=DTYPE), torch.eye(2, dtype=DTYPE), bounds=(0.0, ["1", 2]))


def test_an_open_side_and_scalar_bounds():
    opt = Dipole(
        torch.zeros(2, dtype=DTYPE),
        torch.eye(2, dtype=DTYPE),
        bounds=(torch.tensor([0.0, -float("inf")], dtype=DTYPE), float("inf")),
        generator=torch.Generator().manual_seed(2),
    )
    theta = opt.ask()
    assert (theta[:, 0] >= 0.0).all() and (theta[:, 1] < 0.0).any()


@pytest.mark.parametrize(
    ("bounds", "error", "match"),
    [
        ((1.0, 1.0), ValueError, r"lower < upper on every axis; axis 0 has \[1.0, 1.0\]"),
        ((0.0, torch.tensor([1.0, -1.0])), ValueError, r"axis 1 has \[0.0, -1.0\]"),
        ((0.5, 1.0), ValueError, r"theta0 must lie inside bounds; axis 0: 0.0"),
        ((torch.zeros(3), 1.0), ValueError, r"bounds' lower"),
        ((float("nan"), 1.0), ValueError, r"bounds' lower contains NaN"),
        ((None, 1.0), TypeError, r"bounds. lower must be a number, a list of D numbers"),
        ((True, 1.0), TypeError, r"bounds' lower must be a number"),
        ((0.0,), ValueError, r"bounds must be None or \(lower, upper\)"),
        (1.0, ValueError, r"bounds must be None or \(lower, upper\)"),
    ],
)
@pytest.mark.parametrize("name", ["dipole", "power"])
def test_bad_bounds_raise_naming_what_is_wrong(name, bounds, error, match):
    with pytest.raises(error, match=match):
        BUILDERS[name](torch.zeros(2, dtype=DTYPE), torch.eye(2, dtype=DTYPE), bounds=bounds)


@pytest.mark.parametrize("name", ["dipole", "power"])
def test_pending_rows_loaded_from_another_box_are_checked_against_this_one(name):
    """Rows pending in a loaded state were projected onto another optimizer's box: told as
    they were asked, they are still checked against this one's (``strict=False`` with other
    bounds), not taken as inside it because they are the rows asked."""

    def build(bound):
        generator = torch.Generator().manual_seed(0)
        return BUILDERS[name]([0.0, 0.0], 1.0, bounds=(-bound, bound), generator=generator)

    wide, narrow = build(10.0), build(0.5)
    theta = wide.ask()
    assert (theta.abs() > 0.5).any()  # rows outside the narrow box
    narrow.load_state_dict(wide.state_dict(), strict=False)
    with pytest.raises(ValueError, match="outside bounds"):
        narrow.tell(theta, -theta.square().sum(-1))
