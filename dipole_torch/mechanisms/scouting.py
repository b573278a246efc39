"""Which rows an ask holds after the first batch: the policies whose turn it is, and scouts.

* Turn-taking (``max_sampled``): with more active policies than that, only the ones with the
  best kept returns draw a sample; the others wait (still among the policies, their
  exploration unchanged) until a policy ahead of them retires or is dropped, or a clustering
  reshapes the policies. Spread over every policy at once, a budget of a few hundred trials
  converged none of them on most 5-D landscapes with 8 optima; in turn, the first ones
  converge and the later ones still get theirs.
* A share for the policies accepted unjudged (``unjudged_share``, with the hill-valley
  test's ``accept_unjudged``): they draw samples only while they have drawn less than that
  share of the policy samples so far (then all of them at once); meanwhile only the others
  are sampled. In 10-D a policy converging on its optimum needs nearly every early trial,
  which half a dozen new policies beyond the probe's reach would otherwise share; the cap
  keeps it its trials and still gives the new ones theirs (docs: Precision and coverage).
* Scouts (``explore``): draws from N(θ0, Σ_start) that belong to no policy yet, ``explore``
  per policy sample on average; the clustering puts a scout that lies on another hill in a
  component of its own, a candidate policy. When every policy has retired, the next ask is
  a fresh n0 of them: a restart (an empty ask would end the run).
* Restarts (``restarts``): with ``"box"`` (the default) and a box finite on every side, a
  restart's scouts are drawn uniformly in the box, as NMMSO's and HillVallEA's new samples
  are: the optima a run has not found yet are often where N(θ0, Σ_start) rarely reaches (on
  Vincent's function, the narrow basins near the box's edge), and the held ones keep their
  policies. Without such a box, or with ``"start"``, they come from N(θ0, Σ_start). The first
  batch is always N(θ0, Σ_start) (Algorithm 2).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.archive import NO_POLICY
from dipole_torch.sampling import draw_gaussian, uniforms

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch
    from dipole_torch.tell_batch import TellBatch

__all__ = ["Scouting"]


class Scouting:
    """Turn-taking among the active policies and scouts from the start distribution.

    Args:
        explore: scouts per policy sample, in [0, 1] (0: none).
        max_sampled: policies sampled in one ask at most (``None``: every active one).
        restarts: ``"box"`` (a restart's scouts uniform in a finite box) or ``"start"``
            (from N(θ0, Σ_start)).
        unjudged_share: the share of the policy samples that the policies accepted unjudged
            (the policy field ``unjudged``, which the hill-valley test keeps) may draw, in
            (0, 1] (``None``: no cap).

    Attributes:
        unjudged_samples: the policy samples drawn so far by policies accepted unjudged
            (counted with ``unjudged_share`` only; kept in checkpoints).
    """

    def __init__(
        self,
        explore: float,
        max_sampled: int | None,
        restarts: str,
        unjudged_share: float | None = None,
    ):
        self.explore = float(explore)
        self.max_sampled = None if max_sampled is None else int(max_sampled)
        self.restarts = restarts
        self.unjudged_share = None if unjudged_share is None else float(unjudged_share)
        self.unjudged_samples = 0

    def sampled_policies(self, search: PolicySearch) -> Tensor:
        """``[K_sampled]`` the active policies that draw a sample at the next ask: all of
        them, or the ``max_sampled`` with the best kept returns (ties: the lower index); with
        ``unjudged_share`` reached, only those not accepted unjudged (while any is active)."""
        index = self._may_draw(search).nonzero().squeeze(-1)
        if self.max_sampled is None or index.numel() <= self.max_sampled:
            return index
        best = search.policy_best_rewards[index]
        ahead = torch.argsort(best, descending=True, stable=True)[: self.max_sampled]
        return index[ahead].sort().values

    def _may_draw(self, search: PolicySearch) -> Tensor:
        """``[K]`` the active policies, less those accepted unjudged once they have drawn
        their share of the policy samples and another active policy can draw instead.
        (``unjudged_share`` needs ``accept_unjudged``, which registers the field.)"""
        active = search.active
        share = self.unjudged_share
        if share is None or self.unjudged_samples < share * search.policy_samples:
            return active
        others = active & ~search.policy_set.unjudged
        return others if bool(others.any()) else active

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """Count the told samples of policies accepted unjudged (policies numbered as
        asked)."""
        if self.unjudged_share is None:
            return
        owner = batch.owner[: batch.policy_rows]
        if owner.numel():
            self.unjudged_samples += int(search.policy_set.unjudged[owner].sum())

    def state_dict(self) -> dict[str, int]:
        return {"unjudged_samples": self.unjudged_samples}

    def load_state_dict(self, state: dict) -> None:
        """(A checkpoint from before the share: none counted.)"""
        self.unjudged_samples = int(state.get("unjudged_samples", 0))

    def scouts(self, search: PolicySearch, sampled: int) -> int:
        """Scouts in the next ask, whose ``sampled`` policies draw a sample each: ``explore``
        per policy sample on average (the running count of policy samples decides, so the
        fraction holds over the run); a fresh ``n0`` when no policy is active."""
        if not search.policy_set.any_active():
            return search.n0
        before = search.policy_samples
        return math.floor(self.explore * (before + sampled)) - math.floor(self.explore * before)

    def draw_scouts(self, search: PolicySearch, count: int) -> tuple[Tensor, Tensor]:
        """``count`` scouts: ``([count, D], owner [count])``, from N(θ0, Σ_start), or
        uniform in the box for a restart (no policy active) with ``restarts="box"`` and a
        box finite on every side."""
        box = search.box
        if (
            self.restarts == "box"
            and box is not None
            and not search.policy_set.any_active()
            and bool(torch.isfinite(box[0]).all() & torch.isfinite(box[1]).all())
        ):
            lower, upper = box
            # (Drawn on the generator's device and moved, as every draw of the library.)
            u = uniforms(count * search.dim, search.generator, lower.device)
            theta = lower + (upper - lower) * u.reshape(count, search.dim)
        else:
            theta = draw_gaussian(search.theta0, search.sigma_start, (count,), search.generator)
        return theta, torch.full_like(theta[:, 0], NO_POLICY, dtype=torch.long)
