"""DIPOLE's options (dipole_torch.options): one validated object; every combination of the
switches runs or is refused at construction naming the conflict."""

import dataclasses
import itertools
import math
import typing

import pytest
import torch

from dipole_torch import Dipole, DipoleOptions
from dipole_torch.archive import PROBE
from dipole_torch.options import PAPER, PAPER_INERT

F64 = torch.float64
OPTIMA = torch.tensor([[1.5, 0.0], [-1.5, 0.0]], dtype=F64)


def two_optima(theta: torch.Tensor) -> torch.Tensor:
    """``[B]`` two Gaussian bumps of height 1 at (±1.5, 0) on a floor of 0.05: positive."""
    d2 = (theta[:, None, :] - OPTIMA).square().sum(-1)
    return 0.05 + (-d2 / 0.5).exp().amax(-1)


SWITCHES = list(
    itertools.product(
        ("policy", "global"),  # importance
        ("success", "clustering"),  # exploration
        (0.0, 0.2),  # explore
        (False, True),  # hill_valley
        (None, 4),  # max_sampled
        (None, "positive"),  # reward_range
    )
)


@pytest.mark.parametrize(
    "importance, exploration, explore, hill_valley, max_sampled, rewards", SWITCHES
)
def test_every_combination_of_the_switches_runs(
    importance, exploration, explore, hill_valley, max_sampled, rewards
):
    def run(seed):
        opt = Dipole(
            torch.zeros(2, dtype=F64),
            1.0,
            importance=importance,
            exploration=exploration,
            explore=explore,
            hill_valley=hill_valley,
            max_sampled=max_sampled,
            reward_range=rewards,
            generator=torch.Generator().manual_seed(seed),
        )
        probes = 0
        while opt.trials < 200:
            theta = opt.ask(max_rows=200 - opt.trials)
            probes += int((opt.asked_owner[: theta.shape[0]] == PROBE).sum())
            opt.tell(theta, two_optima(theta))
        assert opt.trials == 200
        assert torch.isfinite(opt.policy_means).all()
        assert torch.isfinite(opt.policy_covariances).all()
        assert opt.best()[1] > 0.95  # a policy found a top (the first batch's best: ~0.5)
        return probes

    probes = [run(0)]
    # The switch does what it says, in either variant: never a probe without it; with it,
    # probes once there is a candidate to vet or a pair of policies within each other's
    # reach (in one of five runs: without scouts, two policies on the two tops of 200
    # trials are rarely within reach of each other).
    while hill_valley and probes[-1] == 0 and len(probes) < 5:
        probes.append(run(len(probes)))
    assert (probes[-1] > 0) == hill_valley, probes


@pytest.mark.parametrize("matching", ["overlap", "replace"])
def test_the_papers_variant_with_one_mechanism_more_runs(matching):
    # Formerly crashing or silently ignored: scouts and hill-valley probes in the paper's
    # variant (the scouts are warm-started as singletons). Probes are asked in one of four
    # runs (pairs are probed only within each other's reach).
    def run(seed):
        opt = Dipole.paper(
            torch.zeros(2, dtype=F64), 1.0, explore=0.2, hill_valley=True, matching=matching,
            generator=torch.Generator().manual_seed(seed),
        )  # fmt: skip
        owners = set()
        while opt.trials < 200:
            theta = opt.ask(max_rows=200 - opt.trials)
            owners |= set(opt.asked_owner[: theta.shape[0]].tolist())
            opt.tell(theta, two_optima(theta))
        assert opt.best()[1] > 0.95
        return owners

    owners = [run(1)]
    while PROBE not in owners[-1] and len(owners) < 4:
        owners.append(run(len(owners) + 1))
    assert {-1, PROBE} <= owners[-1]  # scouts and probes were asked


def test_a_combination_that_cannot_run_is_refused_naming_the_conflict():
    with pytest.raises(ValueError, match=r"retire_std=0.001 needs matching='overlap'"):
        DipoleOptions(matching="replace")
    with pytest.raises(ValueError, match="retire_std"):
        Dipole.paper(torch.zeros(2), 1.0, retire_std=1e-3)
    assert DipoleOptions(matching="replace", retire_std=0.0).matching == "replace"


@pytest.mark.parametrize(
    "changes, error, message",
    [
        ({"regularization": "x"}, ValueError, "regularization must be a real number, got 'x'"),
        ({"explore": "x"}, ValueError, "explore must be a real number, got 'x'"),
        ({"explore": 1.5}, ValueError, r"explore must lie in \[0, 1\], got 1.5"),
        ({"hill_valley": "no"}, ValueError, "hill_valley must be True or False, got 'no'"),
        ({"reward_weighted": 1}, ValueError, "reward_weighted must be True or False"),
        ({"importance": "best"}, ValueError, "importance must be 'policy' or 'global'"),
        ({"matching": None}, ValueError, "matching must be 'overlap' or 'replace'"),
        ({"alpha": math.nan}, ValueError, r"alpha \(DP concentration\) must be positive"),
        ({"alpha": 0.0}, ValueError, r"alpha \(DP concentration\) must be positive"),
        ({"m": 2.5}, ValueError, r"m \(auxiliary components\) must be a positive integer"),
        ({"reward_floor": 1.0}, ValueError, r"reward_floor must lie in \(0, 1\)"),
        ({"reward_range": (1.0, "a")}, ValueError, "reward_range must be None, .low, high."),
        ({"sweeps": 0}, ValueError, "sweeps must be a positive integer"),
        ({"refine": 1.0}, ValueError, r"refine must lie in \[0, 1\), got 1.0"),
        ({"refine": -0.1}, ValueError, r"refine must lie in \[0, 1\), got -0.1"),
        ({"refine_share": 0.0}, ValueError, r"refine_share must lie in \(0, 1\)"),
        ({"refine_gate": 1.5}, ValueError, r"refine_gate must lie in \[0, 1\], got 1.5"),
        ({"success_target": 1.0}, ValueError, r"success_target must lie in \(0, 1\), got 1.0"),
        ({"success_target": 0.0}, ValueError, r"success_target must lie in \(0, 1\)"),
        ({"refine_gate": math.nan}, ValueError, r"refine_gate must lie in \[0, 1\]"),
        ({"wake_while_active": "yes"}, ValueError, "wake_while_active must be True or False"),
        ({"start_cap": -0.25}, ValueError, "start_cap must be non-negative and finite"),
        ({"start_cap": math.inf}, ValueError, "start_cap must be non-negative and finite"),
        ({"retire_spread": 1.5}, ValueError, r"retire_spread must lie in \[0, 1\], got 1.5"),
        ({"retire_spread": -1e-4}, ValueError, r"retire_spread must lie in \[0, 1\]"),
        ({"retire_spread": math.inf}, ValueError, r"retire_spread must lie in \[0, 1\]"),
        ({"unjudged_share": 0.5}, ValueError, "unjudged_share=0.5 needs accept_unjudged=True"),
        (
            {"unjudged_share": 0.0, "accept_unjudged": True},
            ValueError,
            r"unjudged_share must lie in \(0, 1\] or be None, got 0.0",
        ),
        (
            {"unjudged_share": math.nan, "accept_unjudged": True},
            ValueError,
            r"unjudged_share must lie in \(0, 1\]",
        ),
        ({"unjudged_share": "half"}, ValueError, "unjudged_share must be a real number"),
        ({"alhpa": 2.0}, TypeError, "unknown DIPOLE option.*'alhpa'"),
    ],
)
def test_each_option_is_checked_once_naming_it(changes, error, message):
    with pytest.raises(error, match=message):
        DipoleOptions().replace(**changes)
    with pytest.raises(error, match=message):
        Dipole(torch.zeros(2), 1.0, **changes)


def test_prior_df_must_exceed_d_plus_2_which_the_optimizer_checks_knowing_d():
    # (D + 2 itself is refused: the weakest inverse-Wishart prior with a finite mean has
    # ν0 > p + 1 for the p = D + 1 dimensions of [θ, w].)
    with pytest.raises(ValueError, match=r"prior_df must exceed D \+ 2 = 4, got 4.0"):
        Dipole(torch.zeros(2), 1.0, prior_df=4.0)
    assert Dipole(torch.zeros(2), 1.0, prior_df=4.001).prior_df == 4.001


@pytest.mark.parametrize(
    "changes",
    [
        {"unjudged_share": 1.0, "accept_unjudged": True, "hill_valley": True},
        {"explore": 0.0},
        {"explore": 1.0},
        {"refine": 0.0},
        {"retire_spread": 0.0},
        {"refine_gate": 1.0},
        {"regularization": 0.0},
        {"retire_std": 0.0},
        {"merge_radius": 0.0},
        {"start_cap": 0.0},
        {"prior_df": 5.5},
        {"reward_floor": 0.5, "refine_share": 0.999},
    ],
)
def test_the_closed_end_of_each_range_is_accepted(changes):
    """The closed end of each option's documented range (``[0, 1]``, ``(0, 1]``,
    ``[0, inf)``; a ν0 that is no whole number) is accepted, not refused by a check one
    step too strict: the refused values are pinned by the test above."""
    options = DipoleOptions().replace(**changes)
    assert all(getattr(options, name) == value for name, value in changes.items())
    Dipole(torch.zeros(2), 1.0, **changes)


@pytest.mark.parametrize("way", [{"accept_unjudged": True}, {"coverage_from": 3}])
def test_unjudged_share_takes_either_way_of_accepting_unjudged(way):
    """``unjudged_share`` needs policies accepted unjudged, by ``accept_unjudged`` or by
    ``coverage_from``: either one alone is enough (the refusal is pinned above)."""
    options = DipoleOptions(hill_valley=True, unjudged_share=0.5, **way)
    assert options.unjudged_share == 0.5 and options.marks_unjudged


def test_both_variants_take_the_papers_constants():
    # The paper's α = 1, m = 10 auxiliary components and M = 5 importance samples, written
    # out here (not read from the library's own table), in the default and the paper's set.
    for options in (DipoleOptions(), DipoleOptions.paper()):
        assert (options.alpha, options.m, options.M) == (1.0, 10, 5)
    assert Dipole(torch.zeros(2), 1.0).n0 == 10  # 2M first samples


def test_the_defaults_that_follow_d_and_m_are_the_documented_ones():
    # ν0 = D + 3 (the weakest inverse-Wishart prior on [θ, w] with a finite mean) and a
    # clustering every M iterations, for both variants; an option given overrides each.
    for make in (Dipole, Dipole.paper):
        opt = make(torch.zeros(3), 1.0, M=4)
        assert (opt.prior_df, opt.cluster_every, opt.n0) == (6.0, 4, 8)
    opt = Dipole(torch.zeros(3), 1.0, prior_df=7.5, cluster_every=2)
    assert (opt.prior_df, opt.cluster_every) == (7.5, 2)


def test_the_papers_set_and_a_checked_copy():
    paper = DipoleOptions.paper()
    assert all(getattr(paper, key) == value for key, value in PAPER.items())
    assert Dipole.paper(torch.zeros(2), 1.0, alpha=2.0).options == DipoleOptions.paper(alpha=2.0)
    options = DipoleOptions()
    copy = options.replace(explore=0.1)
    assert copy.explore == 0.1 and options.explore == 0.05  # frozen: a new object
    with pytest.raises(AttributeError):
        options.explore = 0.3  # type: ignore[misc]
    mixed = Dipole(torch.zeros(2), 1.0, options=paper, M=3).options
    assert mixed == paper.replace(M=3)
    # DipoleOptions' own error ("unexpected keyword argument 'options'") named no way out.
    with pytest.raises(TypeError, match=r"Dipole.paper sets the options itself .*Dipole\(theta0"):
        Dipole.paper(torch.zeros(2), 1.0, options=DipoleOptions())


# A value other than each option's default.
INERT_VALUES = {
    "restarts": "start",
    "refine_share": 0.6,
    "refine_gate": 1.0,
    "success_target": 2.0 / 11.0,
    "wake_while_active": True,
    "start_cap": 0.25,
    "pair_points": 4,
    "accept_unjudged": True,
    "unjudged_share": 0.5,
    "coverage_from": 40,
    "coverage_max_policies": 10,
}


@pytest.mark.parametrize("name", PAPER_INERT)
def test_the_options_the_papers_algorithm_leaves_inert_change_nothing_or_are_refused(name):
    """``algo=dipole_paper`` leaves these out of its schema: under ``Dipole.paper`` they
    act on nothing (or are refused), so a user setting one would be misled."""
    assert getattr(DipoleOptions(), name) != INERT_VALUES[name]

    def run(**changes):
        g = torch.Generator().manual_seed(3)
        opt = Dipole.paper(torch.zeros(2), 2.0, bounds=(-5.0, 5.0), generator=g, **changes)
        while opt.trials < 150:
            theta = opt.ask()
            opt.tell(theta, torch.exp(-(theta - 1.0).square().sum(-1)) + 0.1)
        return opt.policy_means

    try:
        changed = run(**{name: INERT_VALUES[name]})
    except ValueError as error:
        assert "needs hill_valley=True" in str(error) or "needs accept_unjudged" in str(error)
        return
    assert torch.equal(changed, run())


def test_the_papers_command_line_schema_leaves_the_inert_options_out():
    from dipole_torch.training.config import algo_schemas

    schema = algo_schemas()["dipole_paper"]
    optimizer = {f.name for f in dataclasses.fields(typing.get_type_hints(schema)["optimizer"])}
    assert not optimizer & set(PAPER_INERT) and not optimizer & set(PAPER)
    assert {"alpha", "m", "M"} <= optimizer


EDGES = {
    "fewest samples kept, every sample a scout's chance": dict(M=1, m=1, explore=1.0),
    "one policy, one sweep": dict(
        max_policies=1, max_sampled=1, sweeps=1, initial_sweeps=1, settle=None
    ),  # fmt: skip
    "no regularisation, a clustering every iteration": dict(
        regularization=0.0, reward_floor=0.999, cluster_every=1
    ),
    "early retirement, wide merging": dict(
        retire_std=0.5, refine=0.9, merge_radius=10.0, pair_points=5
    ),  # fmt: skip
    "retirement on any spread, by the std never": dict(retire_spread=1.0, retire_std=1e-300),
    "a success rule that almost never shrinks": dict(success_target=1e-3),
}


@pytest.mark.parametrize("importance", ["policy", "global"])
@pytest.mark.parametrize("edge", list(EDGES))
def test_options_at_the_edges_of_their_ranges_run_long(importance, edge):
    """Each option at an end of its range, in 5-D, for 400 trials: the run goes on, finite.
    (``importance="global"`` with M = 1 and many scouts once raised at the first iteration:
    every one of the K·M samples kept was a scout's.)"""
    centres = torch.zeros(2, 5, dtype=F64)
    centres[:, 0] = torch.tensor([1.5, -1.5], dtype=F64)

    def bumps(theta: torch.Tensor) -> torch.Tensor:
        return 0.05 + (-(theta[:, None, :] - centres).square().sum(-1) / 0.5).exp().amax(-1)

    opt = Dipole(torch.zeros(5), torch.eye(5), bounds=(-5.0, 5.0), importance=importance,
                 generator=torch.Generator().manual_seed(1), **EDGES[edge])  # fmt: skip
    while opt.trials < 400:
        theta = opt.ask()
        opt.tell(theta, bumps(theta))
    assert torch.isfinite(opt.policy_means).all()
    assert torch.isfinite(opt.policy_covariances).all()
    assert opt.best()[1] > 0.5  # above the first batch's (about 0.1 in 5-D)


@pytest.mark.parametrize("target", [1e-6, 0.999999])
def test_a_success_target_at_either_end_runs_long(target):
    """A success rule whose exploration grows at almost every sample, or shrinks at almost
    every one (a poor search, yet a run): 600 trials in 5-D stay finite, every exploration
    covariance positive definite and within Σ_start's scale."""
    opt = Dipole(torch.zeros(5), torch.eye(5), bounds=(-5.0, 5.0), success_target=target,
                 generator=torch.Generator().manual_seed(2))  # fmt: skip
    while opt.trials < 600:
        theta = opt.ask()
        opt.tell(theta, two_optima(theta[:, :2]))  # the first two axes hold the optima
    assert torch.isfinite(opt.policy_means).all()
    assert bool((torch.linalg.eigvalsh(opt.policy_covariances) > 0).all())
    assert bool((opt.relative_std() <= 1.0 + 1e-12).all())


def test_numpy_bools_and_numbers_are_taken_as_flags_and_values():
    # A value read from a numpy array (a sweep's grid) is a numpy scalar, not a Python one.
    import numpy as np

    options = DipoleOptions(hill_valley=np.bool_(False), M=np.int64(6), alpha=np.float64(2.0))
    assert (options.hill_valley, options.M, options.alpha) == (False, 6, 2.0)
