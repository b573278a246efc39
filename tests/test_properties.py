"""Property-based tests of the ask/tell interface of Dipole, Dipole.paper and Power.

Random sequences of ask / tell (all rows or the first n) / reevaluate / state_dict /
load_state_dict, with valid and invalid inputs: every call either works, or raises
``ValueError``/``TypeError`` naming the argument (``RuntimeError`` for a call out of order),
and a refused call leaves the optimizer's state exactly as it was; a run can always go on.

Hypothesis runs a fixed, derandomised set of examples (no database), at D = 1 to 3.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torch import Tensor

from dipole_torch import Dipole, Power

F64 = torch.float64

PROFILE = settings(
    derandomize=True,
    database=None,
    max_examples=50,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

# name -> (builder, the returns it accepts: None (any finite), "positive" or (low, high))
LOW, HIGH = -5.0, 5.0
CONFIGS = {
    "dipole": (lambda t0, s, g: Dipole(t0, s, generator=g), None),
    "dipole-range": (
        lambda t0, s, g: Dipole(t0, s, generator=g, reward_range=(LOW, HIGH)),
        (
            LOW,
            HIGH,
        ),
    ),
    "paper": (lambda t0, s, g: Dipole.paper(t0, s, generator=g), "positive"),
    "paper-range": (
        lambda t0, s, g: Dipole.paper(t0, s, generator=g, reward_range=(LOW, HIGH)),
        (LOW, HIGH),
    ),
    "power": (lambda t0, s, g: Power(t0, s, generator=g), None),
    "power-positive": (
        lambda t0, s, g: Power(t0, s, generator=g, reward_range="positive"),
        "positive",
    ),
}


# ---------------------------------------------------------------------- helpers
def same_state(a, b) -> bool:
    """Equality of nested state dicts (tensors by value, shape and dtype)."""
    if isinstance(a, Tensor):
        return (
            isinstance(b, Tensor)
            and a.shape == b.shape
            and a.dtype == b.dtype
            and bool(torch.equal(a, b))
        )
    if isinstance(a, dict):
        return (
            isinstance(b, dict) and a.keys() == b.keys() and all(same_state(a[k], b[k]) for k in a)
        )
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return type(a) is type(b) and a == b


def bowl(theta: Tensor) -> Tensor:
    """A return in [-1, 1], 1 at θ = 1."""
    theta = theta.detach().to(F64)
    return (1.0 - 0.5 * (theta - 1.0).pow(2).sum(-1)).clamp(-1.0, 1.0)


def valid_rewards(data, accepted, theta: Tensor, first: bool = False) -> Tensor:
    """Returns the optimizer must accept for ``theta [n, D]`` (``first``: as the run's first
    batch): a smooth function at some offset and scale, a flat batch, or any floats of the
    accepted kind."""
    n = theta.shape[0]
    shape = bowl(theta)
    mode = data.draw(st.sampled_from(["function", "flat", "floats"]), label="rewards mode")
    if accepted is None:
        if mode == "function":
            offset = data.draw(st.sampled_from([0.0, -0.5, 1000.0, -1e300, 1e-300]))
            scale = data.draw(st.sampled_from([1.0, 1e-9, 1e9, 1e300]))
            return offset + scale * shape
        if mode == "flat":
            value = data.draw(st.sampled_from([0.0, 1000.0, -0.5, 1e300, -1e-300, 1.5e308]))
            return torch.full((n,), value, dtype=F64)
        values = st.floats(allow_nan=False, allow_infinity=False)
    elif accepted == "positive":
        # Weights in (0, 1e150], the first batch's largest at least 1e-150 (their squares
        # are the DP mixture's variances).
        if mode == "function":
            scale = data.draw(st.sampled_from([1.0, 1e-9, 1e9, 1e100, 3e-150]))
            return scale * (1.5 + shape)
        if mode == "flat":
            smallest = [1e-150] if first else [1e-150, 1e-300, 5e-324]
            value = data.draw(st.sampled_from([1.0, 1000.0, 1e150, *smallest]))
            return torch.full((n,), value, dtype=F64)
        drawn = data.draw(
            st.lists(st.floats(min_value=5e-324, max_value=1e150), min_size=n, max_size=n),
            label="rewards",
        )
        if first and max(drawn) < 1e-150:
            drawn[0] = 1.0
        return torch.tensor(drawn, dtype=F64)
    else:
        low, high = accepted
        if mode == "function":
            return 0.5 * (low + high) + 0.5 * (high - low) * shape
        if mode == "flat":
            value = data.draw(st.sampled_from([low, high, 0.5 * (low + high)]))
            return torch.full((n,), value, dtype=F64)
        values = st.floats(min_value=low, max_value=high)
    drawn = data.draw(st.lists(values, min_size=n, max_size=n), label="rewards")
    return torch.tensor(drawn, dtype=F64)


def bad_rewards(data, accepted, n: int, first: bool = False):
    """Returns for n rows that must be refused (``first``: as the run's first batch)."""
    kinds = ["longer", "shorter", "2-d", "nan", "inf", "bool", "uint8", "complex", "string"]
    kinds += ["objects", "none", "meta"]
    if accepted == "positive":
        kinds += ["zero", "negative", "above 1e150"] + (["too small a first batch"] * first)
    elif accepted is not None:
        kinds += ["below range", "above range"]
    kind = data.draw(st.sampled_from(kinds), label="bad rewards")
    ok = torch.ones(n, dtype=F64)
    if kind == "longer":
        return torch.ones(n + 1, dtype=F64)
    if kind == "shorter":
        return torch.ones(n - 1, dtype=F64) if n > 1 else torch.ones((), dtype=F64)
    if kind == "2-d":
        return ok[:, None]
    if kind in ("nan", "inf"):
        bad = ok.clone()
        bad[data.draw(st.integers(0, n - 1))] = math.nan if kind == "nan" else -math.inf
        return bad
    if kind == "bool":
        return torch.ones(n, dtype=torch.bool)
    if kind == "uint8":
        return torch.ones(n, dtype=torch.uint8)
    if kind == "complex":
        return torch.ones(n, dtype=torch.complex128)
    if kind == "string":
        return data.draw(st.sampled_from(["abc", ["a"] * n, np.array(["1.0"] * n)]))
    if kind == "objects":
        return data.draw(st.sampled_from([object(), {}, np.array([None] * n)]))
    if kind == "none":
        return None
    if kind == "meta":
        return torch.ones(n, device="meta")
    if kind == "too small a first batch":
        return torch.full((n,), 1e-151, dtype=F64)
    bad = ok.clone()
    row = data.draw(st.integers(0, n - 1))
    if kind == "zero":
        bad[row] = 0.0
    elif kind == "negative":
        bad[row] = -1.0
    elif kind == "above 1e150":
        bad[row] = 1e151
    elif kind == "below range":
        bad[:] = 0.5 * (LOW + HIGH)
        bad[row] = LOW - 0.1 * (HIGH - LOW)
    else:
        bad[:] = 0.5 * (LOW + HIGH)
        bad[row] = HIGH + 0.1 * (HIGH - LOW)
    return bad


def bad_theta(data, asked: Tensor):
    """A θ that must be refused in place of the rows ``asked [n, D]`` (well-formed rewards)."""
    n, d = asked.shape
    kinds = ["1-d", "3-d", "no rows", "extra row", "wrong D", "nan", "inf", "list"]
    kinds += ["numpy integers", "numpy not asked"]  # (the asked rows as numpy are told)
    kinds += ["complex", "meta", "integers", "bools", "not asked"]
    kind = data.draw(st.sampled_from(kinds), label="bad theta")
    if kind == "1-d":
        return asked[0], 1
    if kind == "3-d":
        return asked[None], n
    if kind == "no rows":
        return asked[:0], 0
    if kind == "extra row":
        return torch.cat((asked, asked[:1])), n + 1
    if kind == "wrong D":
        wider = torch.cat((asked, asked[:, :1]), dim=1)
        return (wider if d == 1 else asked[:, :-1]), n
    if kind in ("nan", "inf"):
        bad = asked.clone()
        bad[data.draw(st.integers(0, n - 1)), data.draw(st.integers(0, d - 1))] = (
            math.nan if kind == "nan" else math.inf
        )
        return bad, n
    if kind == "list":
        return asked.tolist(), n
    if kind == "numpy integers":
        return asked.numpy().astype(np.int64), n
    if kind == "numpy not asked":
        return asked.numpy() + 1.0, n
    if kind == "complex":
        return asked.to(torch.complex128), n
    if kind == "meta":
        return torch.empty_like(asked, device="meta"), n
    if kind in ("integers", "bools"):
        return asked.to(torch.long if kind == "integers" else torch.bool), n
    moved = asked.clone()
    row, axis = data.draw(st.integers(0, n - 1)), data.draw(st.integers(0, d - 1))
    moved[row, axis] += 1e-2 * (1.0 + abs(float(moved[row, axis])))
    return moved, n


def refused(opt, call, args: tuple, exception, pattern: str) -> None:
    """``call(*args)`` raises ``exception`` matching ``pattern`` and changes nothing."""
    before = opt.state_dict()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(exception, match=pattern):
            call(*args)
    assert same_state(opt.state_dict(), before)


def same_views(a, b) -> None:
    """Two optimizers that stand at the same point of the same run."""
    assert (a.trials, a.iteration, a.policy_samples) == (b.trials, b.iteration, b.policy_samples)
    assert a.num_policies == b.num_policies and a.batch_size == b.batch_size
    assert torch.equal(a.policy_means, b.policy_means)
    assert torch.equal(a.policy_covariances, b.policy_covariances)
    assert torch.equal(a.active, b.active) and torch.equal(a.last_rewards, b.last_rewards)
    assert torch.equal(a.thetas, b.thetas) and torch.equal(a.rewards, b.rewards)
    assert torch.equal(a.best()[0], b.best()[0]) and a.best()[1] == b.best()[1]
    owners = a.asked_owner, b.asked_owner
    assert (owners[0] is None) == (owners[1] is None)
    assert owners[0] is None or torch.equal(*owners)


def sound(opt) -> None:
    """What must hold after every call that worked."""
    assert bool(opt.policy_means.isfinite().all())
    assert bool(opt.policy_covariances.isfinite().all())
    assert opt.trials >= 0 and opt.num_policies >= 1
    if opt.started:
        assert math.isfinite(opt.best()[1])


def other_optimizer(name: str, dim: int, started: bool):
    """A state that does not fit: another kind (same D) or another dimension."""
    builder = CONFIGS["power" if name.startswith(("dipole", "paper")) else "dipole"][0]
    if started is None:  # another dimension, same kind
        builder = CONFIGS[name][0]
        dim = dim + 1
    opt = builder(torch.zeros(dim, dtype=F64), 1.0, torch.Generator().manual_seed(1))
    if started:
        theta = opt.ask()
        opt.tell(theta, 1.5 + bowl(theta))
    return opt


# ---------------------------------------------------------------------- the property
@pytest.mark.parametrize("name", list(CONFIGS))
@PROFILE
@given(data=st.data())
def test_any_sequence_of_calls_works_or_is_refused_cleanly(name, data):
    builder, accepted = CONFIGS[name]
    dim = data.draw(st.integers(1, 3), label="D")
    dtype = data.draw(st.sampled_from([F64, torch.float32]), label="dtype")
    sigma_kind = data.draw(st.sampled_from(["std", "stds", "covariance"]), label="sigma")
    sigma = {
        "std": 0.8,
        "stds": torch.linspace(0.5, 1.0, dim, dtype=dtype),
        "covariance": 0.6 * torch.eye(dim, dtype=dtype) + 0.2,
    }[sigma_kind]
    seed = data.draw(st.integers(0, 2**16), label="seed")
    opt = builder(torch.zeros(dim, dtype=dtype), sigma, torch.Generator().manual_seed(seed))
    asked: Tensor | None = None  # the rows the last ask returned, while it is pending
    saved: list[tuple[dict, Tensor | None]] = []

    # A few plain iterations first, so that the calls below also meet started runs with
    # clusterings behind them.
    for _ in range(data.draw(st.integers(0, 6), label="plain iterations")):
        theta = opt.ask()
        opt.tell(theta, valid_rewards(data, accepted, theta, not opt.started))
        sound(opt)

    ops = ["ask", "ask", "ask cut", "ask bad", "tell", "tell", "tell first", "tell bad theta"]
    ops += ["tell bad rewards", "reevaluate", "reevaluate bad", "save", "load", "load bad"]
    steps = data.draw(st.integers(1, 9), label="steps")
    for _ in range(steps):
        op = data.draw(st.sampled_from(ops), label="op")
        assert (opt.asked_owner is None) == (asked is None)
        if op in ("ask", "ask cut"):
            cut = data.draw(st.integers(1, 4)) if op == "ask cut" else None
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                expected_rows = min(opt.batch_size, cut or opt.batch_size)
                theta = opt.ask(cut)
            warned = [w for w in caught if issubclass(w.category, UserWarning)]
            assert bool(warned) == (asked is not None)
            assert theta.shape == (expected_rows, dim) and theta.dtype == dtype
            assert bool(theta.isfinite().all())
            asked = theta
        elif op == "ask bad":
            bad = data.draw(st.sampled_from([0, -1, 1.5, "x", True, math.nan, math.inf]))
            refused(opt, opt.ask, (bad,), ValueError, "max_rows")
        elif op in ("tell", "tell first"):
            if asked is None and data.draw(st.booleans(), label="tell without an ask"):
                theta = torch.zeros(1, dim, dtype=dtype)
                refused(opt, opt.tell, (theta, torch.ones(1)), RuntimeError, "ask")
                continue
            asked = opt.ask() if asked is None else asked
            n = asked.shape[0]
            if op == "tell first":
                n = data.draw(st.integers(1, n))
            theta = asked[:n]
            rewards = valid_rewards(data, accepted, theta, not opt.started)
            trials = opt.trials
            opt.tell(theta, rewards)
            assert opt.trials == trials + n
            asked = None
            sound(opt)
        elif op == "tell bad theta":
            asked = opt.ask() if asked is None else asked
            theta, rows = bad_theta(data, asked)
            rewards = torch.ones(rows, dtype=F64) + (1.0 if accepted == "positive" else 0.0)
            refused(opt, opt.tell, (theta, rewards), (ValueError, TypeError), "theta")
        elif op == "tell bad rewards":
            asked = opt.ask() if asked is None else asked
            rewards = bad_rewards(data, accepted, asked.shape[0], not opt.started)
            refused(
                opt,
                opt.tell,
                (asked, rewards),
                (ValueError, TypeError),
                "rewards|reward_range",
            )
        elif op == "reevaluate":
            if not opt.started:
                ones = torch.ones(opt.num_policies, dtype=F64)
                refused(opt, opt.reevaluate, (ones,), RuntimeError, "reevaluate")
                continue
            returns = valid_rewards(data, accepted, opt.policy_means)
            trials, k = opt.trials, opt.num_policies
            opt.reevaluate(returns)
            assert opt.trials == trials + k
            asked = None  # a pending ask is discarded
            sound(opt)
        elif op == "reevaluate bad":
            if not opt.started:
                continue
            returns = bad_rewards(data, accepted, opt.num_policies)
            refused(
                opt,
                opt.reevaluate,
                (returns,),
                (ValueError, TypeError),
                "rewards|returns|reward_range",
            )
        elif op == "save":
            state = opt.state_dict()
            saved.append((state, asked, opt.trials, opt.best()))
            # A fresh optimizer loaded from the state is this one: the same views, and the
            # same next ask and tell.
            fresh = builder(
                torch.zeros(dim, dtype=dtype), sigma, torch.Generator().manual_seed(seed + 1)
            )
            fresh.load_state_dict(state)
            same_views(fresh, opt)
            rows = fresh.ask() if asked is None else asked
            if asked is None:
                assert torch.equal(opt.ask(), rows)
            rewards = valid_rewards(data, accepted, rows, not opt.started)
            opt.tell(rows, rewards)
            fresh.tell(rows, rewards)
            same_views(fresh, opt)
            assert same_state(fresh.state_dict(), opt.state_dict())
            asked = None
        elif op == "load":
            if not saved:
                continue
            state, rows, trials, best = saved[data.draw(st.integers(0, len(saved) - 1))]
            opt.load_state_dict(state)
            assert same_state(opt.state_dict(), state)
            assert opt.trials == trials
            assert torch.equal(opt.best()[0], best[0]) and opt.best()[1] == best[1]
            asked = rows
        else:  # "load bad"
            kind = data.draw(st.sampled_from(["not a dict", "another kind", "another D"]))
            if kind == "not a dict":
                bad = data.draw(st.sampled_from([None, "state", [1, 2]]))
            elif kind == "another kind":
                bad = other_optimizer(name, dim, data.draw(st.booleans())).state_dict()
            else:
                bad = other_optimizer(name, dim, None).state_dict()
            refused(opt, opt.load_state_dict, (bad,), ValueError, "state_dict")

    # The run goes on.
    for _ in range(2):
        if asked is None:
            asked = opt.ask()
        opt.tell(asked, valid_rewards(data, accepted, asked, not opt.started))
        asked = None
        sound(opt)


# ---------------------------------------------------------------------- told θ's dtype
@pytest.mark.parametrize("name", ["dipole", "paper", "power"])
@pytest.mark.parametrize("cast", [torch.long, torch.int8, torch.bool])
def test_a_told_theta_of_integers_or_bools_is_refused(name, cast):
    builder, accepted = CONFIGS[name]
    opt = builder(torch.zeros(2, dtype=F64), 2.0, torch.Generator().manual_seed(0))
    theta = opt.ask()
    rewards = 1.5 + bowl(theta)  # valid for every configuration here
    refused(opt, opt.tell, (theta.to(cast), rewards), (ValueError, TypeError), "theta")
