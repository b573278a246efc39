"""DIPOLE's options as one validated object; ``DipoleOptions.paper`` is the paper's set."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from dipole_torch.reward import RewardRange, check_reward_range
from dipole_torch.validation import check_choice, check_count, check_flag, check_real

__all__ = ["DipoleOptions"]


@dataclass(frozen=True)
class DipoleOptions:
    """Every option of ``Dipole``, with its default (the library's variant).

    Each option is checked when the object is built, with a message naming it; combinations
    that cannot run together are refused there too, naming the conflict. ``replace(**changes)``
    gives a checked copy. ``paper`` is the paper's set.

    =========================  ==============================  ===================================
    option                     default                         the paper (``paper``)
    =========================  ==============================  ===================================
    ``reward_range``           ``None``: min–max of the kept   ``"positive"`` (returns used as
                               returns (any units)             they are), or a fixed range
    ``importance``             ``"policy"``: every policy      ``"global"``: the best K·M samples
                               keeps its own best M            overall
    ``exploration``            ``"success"``: the success      ``"clustering"``: the θ-block of
                               rule scales each policy's       the policy's DP component's
                               covariance                      posterior covariance
    ``success_target``         0.25: the success rule's        (no success rule)
                               target rate
    ``matching``               ``"overlap"``: a component      ``"replace"``: every clustering's
                               continues the policy owning     components replace the policies
                               most of its samples
    ``explore``                0.05 scouts per policy sample   0
    ``hill_valley``            probe new and neighbouring      no
                               policies
    ``accept_unjudged``        no: a candidate the probe       no
                               cannot judge is forgotten
    ``unjudged_share``         ``None`` (with                  ``None``
                               ``accept_unjudged``: no cap)
    ``coverage_from``          ``None``: never                 ``None``
    ``coverage_max_policies``  ``None``: ``max_policies``      ``None``
                               from ``coverage_from`` on too
    ``max_policies``           8 active policies at most       no limit
                               (refining wakes on top)
    ``max_sampled``            4 policies sampled in an        no limit
                               iteration (the others wait)
    ``retire_std``             1e-3: stop sampling a           0 (never)
                               converged policy
    ``retire_spread``          1e-4: stop sampling a policy    0
                               whose kept returns agree to
                               1e-4 of the returns' range
    ``refine``                 0.1: wake retired policies      0 (never)
                               for a 10× finer threshold
                               once none is active
    ``refine_gate``            0.05: the policies near the     (no wakes)
                               best return are woken first
    ``wake_while_active``      no: wakes once no policy is     (no wakes)
                               active
    ``start_cap``              0: a new policy starts at its   (components replace the
                               component's spread              policies)
    ``merge_radius``           1: drop duplicate policies      0 (never)
    ``auxiliary``              ``"auto"``                      ``"fresh"`` (Algorithm 8)
    ``settle``                 1: a warm-started clustering    ``None``: every clustering runs
                               ends once a sweep leaves its    its ``sweeps``
                               partition unchanged
    ``scout_sweeps``           1: a clustering of scouts       ``None`` (the paper has no
                               alone runs one sweep            scouts)
    =========================  ==============================  ===================================

    Attributes:
        alpha: DP concentration α > 0 (paper: 1).
        m: auxiliary components of Neal's Algorithm 8 (paper: 10).
        M: importance-set size of PoWER (paper: 5).
        n0: initial samples from N(θ0, Σ_start); None: 2·M.
        cluster_every: iterations between DP clusterings (paper: "every M steps"); None: M.
        sweeps: Gibbs sweeps per clustering, warm-started.
        settle: end a warm-started clustering early, once this many sweeps in a row left
            the partition unchanged (None: always ``sweeps``; paper: None); see
            ``DPSampler.fit``.
        initial_sweeps: Gibbs sweeps of the first clustering (from one component).
        scout_sweeps: Gibbs sweeps of a clustering that sees scouts alone (every policy
            retired or woken to refine, ``matching="overlap"``), which starts from one
            component per scout and whose components are only candidates for the hill-valley
            probes (None: ``sweeps``, ended by ``settle`` as any warm start); see
            ``Dipole._sweeps``.
        reward_range: None (the kept returns' min–max, any units), (low, high) (a fixed map)
            or "positive" (positive returns used as weights); see dipole_torch.RewardScale.
        reward_floor: smallest reward weight, in (0, 1).
        regularization: DP component covariance floor, a fraction of diag(Σ_start).
        reward_weighted: eq. 6 (True) or plain eq. 5 (False, an ablation).
        prior_df: ν0 of the inverse-Wishart prior, > D + 2; None: D + 3.
        importance: "policy" (each policy's own best M) or "global" (the best K·M overall).
        exploration: "success" (success rule per policy) or "clustering" (DP posterior).
        success_target: the success rule's target rate p_t, in (0, 1): a policy's exploration
            shrinks while a smaller share of its samples than this beat its best kept one.
            0.25, above Igel et al.'s 2/11 for the (1+1)-CMA-ES: a policy's mean is eq. 7's
            average of its best samples, not the best one, and with the higher target the
            policies converge in fewer trials (see mechanisms.exploration.SuccessRule).
        matching: "overlap" (a component continues the policy owning most of its samples; the
            others become new policies) or "replace" (the components replace the policies).
        explore: scouts from N(θ0, Σ_start) per policy sample, in [0, 1].
        restarts: where a restart's scouts come from (every policy retired): "box" (default)
            uniform in the box when ``bounds`` are finite on every side, else N(θ0,
            Σ_start); "start" always N(θ0, Σ_start). See mechanisms.scouting.
        hill_valley: vet new policies and neighbouring ones by probes between them.
        pair_points: probes between two neighbouring policies (1: the midpoint).
        accept_unjudged: with ``hill_valley``, a candidate whose probe shows no valley but
            that lies beyond reach of the policy it was probed against (neither explores
            within ``PAIR_REACH`` stds of the other's best sample, where a probe above the
            worse one may show a ridge between two hills) becomes a policy instead of being
            forgotten. For covering alternatives rather than converging on each (with
            ``max_sampled=None``, every new policy sampled): the new policies take trials
            that a lone converging one needs, so early precision in higher dimensions
            drops (docs: Precision and coverage).
        unjudged_share: with ``accept_unjudged``, the policies it accepted draw samples
            only while they have drawn less than this share of the policy samples so far,
            in (0, 1] (None: no cap); the others are sampled meanwhile. The policies that
            passed the test keep the trials they converge with (see
            mechanisms.scouting).
        coverage_from: for the batches asked from this trial on, cover alternatives:
            ``accept_unjudged`` and every active policy sampled (``max_sampled=None``),
            whatever those two are set to (None: never); a run that stops at this trial is
            the run without it. Converge first, then cover: the policies held by then have
            had the trials to converge, and the new ones accepted after it take the rest
            (with ``unjudged_share``, at most that share of the policy samples).
        coverage_max_policies: with ``coverage_from``, the active policies at most for the
            batches asked from that trial on (None: ``max_policies`` throughout; without
            ``coverage_from`` there is no such batch, and it changes nothing, so that
            ``coverage_from=None`` alone turns a task's covering off). On a task where no
            policy retires while it covers, the cap binds for good once reached, and the
            alternatives found later wait for a place (docs: Precision and coverage).
        max_policies: active policies at most that a clustering or the hill-valley test
            adds (None: no limit); a retired policy woken to refine (``refine``) comes on
            top of them, as it adds no policy and no region.
        max_sampled: policies sampled in one iteration at most, the best ones (None: all).
        retire_std: retire a policy once its exploration std is below this times Σ_start's
            (0: no policy is ever retired).
        retire_spread: also retire a policy exploring below a tenth of Σ_start's std once
            its M kept returns spread less than this fraction of the range of every return
            told (a few returns far below or above the rest left out: a crash, a glitch), in
            [0, 1] (0: the std alone); lowered with ``retire_std`` at each wake. A
            broad optimum's returns flatten long before its exploration is small: its trials
            go to finding others, and a wake refines it later (see
            mechanisms.retirement).
        refine: once no policy is active, retired ones are woken with their threshold times
            this, in [0, 1) (0: never woken); see mechanisms.waking.Waking.
        refine_share: a wake starts only while woken policies have taken less than this
            share of the trials since every policy first retired, in (0, 1); restarts
            (scouts) take the rest. A woken policy runs on to its next threshold, so the
            share taken can exceed it (see mechanisms.waking.Waking).
        refine_gate: a wake for a gain to show takes the retired policies whose best
            kept return is within this fraction of the returns' range of the best one's, in
            [0, 1] (1: every one); those further below are woken once these show no gain
            left. The best optima are refined first: on a landscape of many local optima
            (CEC 2013's Shubert), waking all of them a level at a time spent the wakes'
            trials on the local ones.
        wake_while_active: a wake may start while policies found after the first
            convergence are active (they take turns as ``max_sampled`` says); False: only
            once none is. Where new policies keep being found (with ``start_cap``), wakes
            that wait for none to be active hardly come.
        start_cap: a new policy (or hill-valley candidate) starts exploring no wider than
            this fraction of its distance to the nearest policy, both on Σ_start's scale
            (0: its component's spread, up to Σ_start's); see
            mechanisms.matching.capped_start. For landscapes whose optima are all equally
            good: with ``start_cap=0.25, wake_while_active=True`` more of CEC 2013's Vincent
            optima are found, but on a landscape of many local optima (Shubert) the new
            policies stay on the local ones (docs: Niching).
        merge_radius: drop a policy within this many exploration stds of another (0: never).
        best_evaluations: evaluations a sampled policy's best kept sample gets, one more at
            each ask (its return the mean of them), before it is trusted (1: every return as
            told; paper: 1). For noisy returns (a stochastic environment): the best of many
            noisy returns is mostly the luckiest, and a policy judged against it converges
            where the luck was (docs: Reliability, noisy returns). Once 3 repeats in a row
            return the returns they repeat (to 1e-6 of them: ``DETERMINISTIC_REPEATS``,
            ``REPEAT_RTOL``), the returns are taken to be deterministic and none is repeated
            again. How many: a mean of n returns of noise std s has std s/√n, so n ≈ (s/ε)²
            for a precision ε; more only spend trials (4 is a fair start: measured on the
            Reliability page). ``best()`` then reports the best such mean.
        auxiliary: "fresh" (Algorithm 8's m draws per point), "reuse" (Favaro & Teh's re-used
            draws, exact too, CPU), or "auto" (reuse on the CPU once D + 1 >= 32).
    """

    alpha: float = 1.0
    m: int = 10
    M: int = 5
    n0: int | None = None
    cluster_every: int | None = None
    sweeps: int = 5
    settle: int | None = 1
    initial_sweeps: int = 20
    scout_sweeps: int | None = 1
    reward_range: RewardRange = None
    reward_floor: float = 1e-3
    regularization: float = 1e-2
    reward_weighted: bool = True
    prior_df: float | None = None
    importance: str = "policy"
    exploration: str = "success"
    success_target: float = 0.25
    matching: str = "overlap"
    explore: float = 0.05
    restarts: str = "box"
    hill_valley: bool = True
    pair_points: int = 1
    accept_unjudged: bool = False
    unjudged_share: float | None = None
    coverage_from: int | None = None
    coverage_max_policies: int | None = None
    max_policies: int | None = 8
    max_sampled: int | None = 4
    retire_std: float = 1e-3
    retire_spread: float = 1e-4
    refine: float = 0.1
    refine_share: float = 0.2
    refine_gate: float = 0.05
    wake_while_active: bool = False
    start_cap: float = 0.0
    merge_radius: float = 1.0
    best_evaluations: int = 1
    auxiliary: str = "auto"

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):  # numpy numbers (a grid of options) as Python's
            value = getattr(self, field.name)
            if isinstance(value, np.integer | np.floating):
                object.__setattr__(self, field.name, value.item())
        for name, check in _CHECKS.items():
            check(getattr(self, name), _NAMES.get(name, name))
        if self.reward_range is not None and not isinstance(self.reward_range, str | tuple):
            # (a config's list: the pair it stands for)
            object.__setattr__(self, "reward_range", tuple(float(v) for v in self.reward_range))
        if self.accept_unjudged and not self.hill_valley:
            raise ValueError(
                "accept_unjudged=True needs hill_valley=True: without the hill-valley test "
                "no candidate is judged"
            )
        if self.coverage_from is not None and not self.hill_valley:
            raise ValueError(
                f"coverage_from={self.coverage_from} needs hill_valley=True: it accepts the "
                "candidates that the hill-valley test cannot judge"
            )
        if self.unjudged_share is not None and not self.marks_unjudged:
            raise ValueError(
                f"unjudged_share={self.unjudged_share} needs accept_unjudged=True or "
                "coverage_from: it caps the samples of the policies accepted unjudged"
            )
        if self.matching == "replace" and self.retire_std > 0:
            raise ValueError(
                f"retire_std={self.retire_std} needs matching='overlap': with "
                "matching='replace' every clustering makes each component a new, active "
                "policy, so a retired policy would be sampled again (use retire_std=0)"
            )

    @property
    def marks_unjudged(self) -> bool:
        """Whether policies may be accepted unjudged in the run (``accept_unjudged``, or
        from ``coverage_from`` on): the policy field that marks them is kept."""
        return self.accept_unjudged or self.coverage_from is not None

    @classmethod
    def paper(cls, **changes: Any) -> DipoleOptions:
        """The paper's DIPOLE (Algorithm 2): the best K·M samples kept overall, exploration
        from the DP posterior, the components as the policies, no scouts, no retirement, no
        merging, positive returns used as weights (``reward_range="positive"``), then
        ``changes``."""
        return cls(**(PAPER | changes))

    def replace(self, **changes: Any) -> DipoleOptions:
        """A checked copy with ``changes``; an unknown name raises ``TypeError`` naming it."""
        unknown = sorted(set(changes) - {f.name for f in fields(self)})
        if unknown:
            raise TypeError(f"unknown DIPOLE option(s) {', '.join(map(repr, unknown))}")
        return dataclasses.replace(self, **changes)


PAPER: dict[str, Any] = dict(
    importance="global",
    exploration="clustering",
    matching="replace",
    explore=0.0,
    max_policies=None,
    max_sampled=None,
    retire_std=0.0,
    retire_spread=0.0,
    refine=0.0,
    merge_radius=0.0,
    hill_valley=False,
    auxiliary="fresh",
    reward_range="positive",
    settle=None,
    scout_sweeps=None,
)


# The options that act only through mechanisms PAPER turns off: with PAPER's values, the
# success rule's target needs ``exploration="success"`` (``success_target``), a
# restart needs retirement (``restarts``), a wake needs ``refine`` (``refine_share``,
# ``refine_gate``, ``wake_while_active``), a new policy between clusterings needs
# ``matching="overlap"`` (``start_cap``), and the rest need the hill-valley test; set alone
# they change nothing or are refused. The command line's ``algo=dipole_paper`` leaves them
# out.
PAPER_INERT: tuple[str, ...] = (
    "success_target",
    "restarts",
    "refine_share",
    "refine_gate",
    "wake_while_active",
    "start_cap",
    "pair_points",
    "accept_unjudged",
    "unjudged_share",
    "coverage_from",
    "coverage_max_policies",
)


def _positive_real(value, name: str) -> None:
    check_real(value, name)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")


def _non_negative(value, name: str) -> None:
    check_real(value, name)
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be non-negative and finite, got {value!r}")


def _unit_interval(value, name: str) -> None:
    check_real(value, name)
    if not (math.isfinite(value) and 0 <= value <= 1):
        raise ValueError(f"{name} must lie in [0, 1], got {value!r}")


def _fraction(value, name: str) -> None:
    check_real(value, name)
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{name} must lie in [0, 1), got {value!r}")


def _floor(value, name: str) -> None:
    check_real(value, name)
    if not 0.0 < value < 1.0:
        raise ValueError(f"{name} must lie in (0, 1), got {value!r}")


def _optional_share(value, name: str) -> None:
    if value is None:
        return
    check_real(value, name)
    if not 0.0 < value <= 1.0:
        raise ValueError(f"{name} must lie in (0, 1] or be None, got {value!r}")


def _optional_count(value, name: str) -> None:
    check_count(value, name, optional=True)


def _optional_real(value, name: str) -> None:
    if value is not None:
        _positive_real(value, name)


def _choice(*choices: str):
    return lambda value, name: check_choice(value, choices, name)


# How an error names an option whose letter alone says little.
_NAMES = {
    "alpha": "alpha (DP concentration)",
    "m": "m (auxiliary components)",
    "M": "M (importance-set size)",
    "n0": "n0 (initial samples)",
}

_CHECKS = {
    "alpha": _positive_real,
    "m": check_count,
    "M": check_count,
    "n0": _optional_count,
    "cluster_every": _optional_count,
    "sweeps": check_count,
    "settle": _optional_count,
    "initial_sweeps": check_count,
    "scout_sweeps": _optional_count,
    "reward_range": check_reward_range,
    "reward_floor": _floor,
    "regularization": _non_negative,
    "reward_weighted": check_flag,
    "prior_df": _optional_real,
    "importance": _choice("policy", "global"),
    "exploration": _choice("success", "clustering"),
    "success_target": _floor,
    "matching": _choice("overlap", "replace"),
    "explore": _unit_interval,
    "restarts": _choice("box", "start"),
    "hill_valley": check_flag,
    "pair_points": check_count,
    "accept_unjudged": check_flag,
    "unjudged_share": _optional_share,
    "coverage_from": _optional_count,
    "coverage_max_policies": _optional_count,
    "max_policies": _optional_count,
    "max_sampled": _optional_count,
    "retire_std": _non_negative,
    "retire_spread": _unit_interval,
    "refine": _fraction,
    "refine_share": _floor,
    "refine_gate": _unit_interval,
    "wake_while_active": check_flag,
    "start_cap": _non_negative,
    "merge_radius": _non_negative,
    "best_evaluations": check_count,
    "auxiliary": _choice("auto", "fresh", "reuse"),
}
