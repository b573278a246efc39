"""Ask/tell policy-search optimizers: DIPOLE (Algorithm 2) and its baseline PoWER
(Algorithm 3).

Both follow pycma's interface: ``ask()`` proposes policy parameters, the caller evaluates
them however it likes (batched simulator, gymnasium env, real robot) and ``tell()`` reports
the returns. Neither ever calls the task, and neither needs the range of the returns.

>>> opt = Dipole(torch.zeros(2), 0.5 * torch.eye(2), generator=torch.Generator().manual_seed(0))
>>> while opt.trials < 300:
...     theta = opt.ask()
...     opt.tell(theta, -100.0 * (theta - 1.0).pow(2).sum(-1))  # any units, no range
>>> bool(opt.best()[1] > -1e-3)
True
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dipole_torch.dp_mixture import (
    DTYPE,
    DPMixtureState,
    fit_dp_mixture,
    posterior_point_estimate,
)
from dipole_torch.gaussian_mixture import GaussianMixture
from dipole_torch.power import importance_sets, power_update
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.reward import RewardScale, check_rewards
from dipole_torch.sampling import draw_gaussian
from dipole_torch.validation import (
    check_count,
    check_finite,
    check_generator,
    check_matrix_shape,
    check_positive_definite,
    check_real,
    check_real_tensor,
)

RewardRange = tuple[float, float] | str | None
PROBE = -2  # owner of a hill-valley probe row (a scout is −1)


def make_reward_scale(reward_range: RewardRange, floor: float) -> RewardScale:
    """``None``: adaptive (the kept returns' min–max); ``(low, high)``: fixed;
    ``"positive"``: positive returns used as they are."""
    if reward_range is None:
        return RewardScale(floor=floor)
    if isinstance(reward_range, str):
        if reward_range != "positive":
            raise ValueError(
                f"reward_range must be None, (low, high) or 'positive', got {reward_range!r}"
            )
        return RewardScale(floor=floor, positive=True)
    try:
        low, high = reward_range
    except (TypeError, ValueError):
        raise ValueError(
            f"reward_range must be None, (low, high) or 'positive', got {reward_range!r}"
        ) from None
    return RewardScale(low, high, floor)


Bounds = tuple[float | list[float] | Tensor, float | list[float] | Tensor] | None


def make_box(bounds: Bounds, theta0: Tensor) -> tuple[Tensor, Tensor] | None:
    """``(lower [D], upper [D])`` in float64 on ``theta0``'s device from ``bounds`` =
    ``(lower, upper)``, each a number, a list of D numbers or a ``[D]`` tensor (±inf: that
    side is open), or ``None`` (no box). Raises ``ValueError`` unless lower < upper on every
    axis and θ0 lies inside."""
    if bounds is None:
        return None
    try:
        low, high = bounds
    except (TypeError, ValueError):
        raise ValueError(f"bounds must be None or (lower, upper), got {bounds!r}") from None
    d = theta0.shape[0]
    box = []
    for name, value in (("lower", low), ("upper", high)):
        numbers = isinstance(value, list | tuple) and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value
        )
        if isinstance(value, bool) or not (isinstance(value, int | float | Tensor) or numbers):
            raise TypeError(
                f"bounds' {name} must be a number, a list of D numbers or a [D] tensor, "
                f"got {value!r}"
            )
        edge = torch.as_tensor(value, dtype=DTYPE, device=theta0.device)
        if edge.dim() == 0:
            edge = edge.expand(d)
        check_matrix_shape(edge, (d,), f"bounds' {name}")
        if bool(edge.isnan().any()):
            raise ValueError(f"bounds' {name} contains NaN")
        box.append(edge.clone())
    lower, upper = box
    if not bool((lower < upper).all()):
        axis = int((lower >= upper).nonzero()[0])
        raise ValueError(
            f"bounds must have lower < upper on every axis; axis {axis} has "
            f"[{float(lower[axis])}, {float(upper[axis])}]"
        )
    outside = (theta0 < lower) | (theta0 > upper)
    if bool(outside.any()):
        axis = int(outside.nonzero()[0])
        raise ValueError(
            f"theta0 must lie inside bounds; axis {axis}: {float(theta0[axis])} is outside "
            f"[{float(lower[axis])}, {float(upper[axis])}]"
        )
    return lower, upper


class PolicySearch:
    """What DIPOLE and PoWER share: data, importance sets, the PoWER step, ask/tell
    bookkeeping, best-so-far and checkpoints.

    Internal maths run in float64 on ``theta0``'s device; ``ask`` returns ``theta0``'s dtype.

    ``tell`` is transactional: if it raises, the optimizer is exactly as before the call.

    With ``bounds = (lower, upper)`` every asked row is projected onto the box (each
    coordinate clipped), a told row outside it raises, and the policy means stay inside
    (eq. 7 averages samples in the box; the paper variant's posterior means are clipped).
    Clipping, not resampling or reflection, so that an optimum on the boundary (a joint
    limit) is sampled exactly; θ0 must lie in the box. Without ``bounds`` nothing changes.

    Attributes:
        trials: number of reward evaluations told so far (the x-axis of the paper's plots).
        iteration: number of tells after the initial batch.
        last_rewards: ``[K]`` each policy's latest return: the returns of the latest told
            batch's policy samples (the whole batch after the first tell), then, for each
            policy that drew no sample in it (DIPOLE's retired policies, and those waiting
            their turn, see ``max_sampled``), the mean return of its kept samples.
            Exploration samples that belong to no policy (DIPOLE's scouts and probes) are
            not in it.
        thetas, rewards, owner: ``[N, D]``, ``[N]``, ``[N]`` the kept samples, their returns
            and the policy owning each (−1: a scout that belongs to no policy yet).
        active: ``[K]`` which policies are still sampled (DIPOLE retires converged ones).
    """

    def __init__(
        self,
        theta0: Tensor,
        sigma_start: Tensor,
        M: int = 5,
        n0: int | None = None,
        reward_range: RewardRange = None,
        reward_floor: float = 1e-3,
        generator: torch.Generator | None = None,
        bounds: Bounds = None,
    ):
        check_real_tensor(theta0, "theta0")
        check_real_tensor(sigma_start, "sigma_start")
        check_count(M, "M (importance-set size)")
        check_count(n0, "n0 (initial samples)", optional=True)
        check_real(reward_floor, "reward_floor")
        check_generator(generator)
        for name, value in (("theta0", theta0), ("sigma_start", sigma_start)):
            if not isinstance(value, Tensor) or not value.is_floating_point():
                raise TypeError(
                    f"{name} must be a floating-point torch.Tensor, got "
                    f"{getattr(value, 'dtype', type(value).__name__)}"
                )
        check_matrix_shape(theta0, (-1,), "theta0")
        check_finite(theta0, "theta0")
        d = theta0.shape[0]
        if d < 1:
            raise ValueError("theta0 must have at least one parameter, got shape [0]")
        check_matrix_shape(sigma_start, (d, d), "sigma_start")
        check_positive_definite(sigma_start.to(DTYPE), "sigma_start")
        if int(M) != M or M < 1:
            raise ValueError(f"M (importance-set size) must be a positive integer, got {M}")
        n0 = int(M) if n0 is None else n0
        if int(n0) != n0 or n0 < 1:
            raise ValueError(f"n0 (initial samples) must be a positive integer, got {n0}")
        self.dtype = theta0.dtype
        self.device = theta0.device
        self.theta0 = theta0.to(DTYPE)
        self.sigma_start = sigma_start.to(DTYPE)
        self.box = make_box(bounds, self.theta0)
        self.M = int(M)
        self.n0 = int(n0)
        self.reward_scale = make_reward_scale(reward_range, reward_floor)
        if generator is None:
            # Like torch's own samplers, an optimizer without a generator follows
            # torch.manual_seed: it seeds its own generator from the global one.
            generator = torch.Generator(self.device)
            generator.manual_seed(int(torch.randint(0, 2**62, (1,))))
        self.generator = generator
        # Samples kept so far (the union of the importance sets) and their owners.
        self.thetas = torch.empty(0, d, dtype=DTYPE, device=self.device)
        self.rewards = torch.empty(0, dtype=DTYPE, device=self.device)
        self.owner = torch.empty(0, dtype=torch.long, device=self.device)
        self.policy_means = self.theta0[None].clone()
        self.policy_covariances = self.sigma_start[None].clone()
        self.active = torch.ones(1, dtype=torch.bool, device=self.device)
        self.trials = 0
        self.iteration = 0
        self.policy_samples = 0  # trials spent on policy samples after the first batch
        self.last_rewards = torch.empty(0, dtype=DTYPE, device=self.device)
        self._best_theta = self.theta0.clone()
        self._best_reward = -math.inf
        self._pending: Tensor | None = None
        self._pending_owner: Tensor | None = None
        self.probe_rewards = torch.empty(0, dtype=DTYPE, device=self.device)
        # Candidate policies waiting for their hill-valley probe (DIPOLE's default variant).
        self.candidate_means = torch.empty(0, d, dtype=DTYPE, device=self.device)
        self.candidate_covariances = torch.empty(0, d, d, dtype=DTYPE, device=self.device)
        self.candidate_probes = torch.empty(0, d, dtype=DTYPE, device=self.device)
        self.candidate_thresholds = torch.empty(0, dtype=DTYPE, device=self.device)
        self.candidate_partners = torch.empty(0, dtype=torch.long, device=self.device)
        self.candidate_samples = torch.empty(0, d, dtype=DTYPE, device=self.device)
        self.candidate_rewards = torch.empty(0, dtype=DTYPE, device=self.device)
        self.pair_index = torch.empty(0, 2, dtype=torch.long, device=self.device)
        self.pair_probes = torch.empty(0, d, dtype=DTYPE, device=self.device)

    # ------------------------------------------------------------------ ask / tell
    @property
    def dim(self) -> int:
        return int(self.theta0.shape[0])

    @property
    def num_policies(self) -> int:
        return int(self.policy_means.shape[0])

    @property
    def started(self) -> bool:
        return self.trials > 0

    def ask(self) -> Tensor:
        """Policy parameters to evaluate next.

        Returns:
            ``[n0, D]`` draws from N(θ0, Σ_start) on the first call; afterwards ``[B, D]``:
            one row per sampled policy (every active one; DIPOLE's default at most
            ``max_sampled``), drawn from its Gaussian, then any exploration rows
            (see :attr:`asked_owner`). Asking again before telling discards the previous
            proposal.
        """
        if not self.started:
            theta = draw_gaussian(self.theta0, self.sigma_start, (self.n0,), self.generator)
            owner = torch.zeros(self.n0, dtype=torch.long, device=self.device)
        else:
            theta, owner = self._propose()
        theta = self._into_box(theta)
        self._pending, self._pending_owner = theta, owner
        return theta.to(self.dtype)

    def _check_in_box(self, theta: Tensor) -> None:
        """Raise ``ValueError`` naming the first told row outside the box (compared in the
        told dtype, so an asked row rounded to float32 still counts as inside)."""
        if self.box is None:
            return
        lower, upper = (edge.to(device=theta.device, dtype=theta.dtype) for edge in self.box)
        outside = (theta < lower) | (theta > upper)
        if bool(outside.any()):
            row, axis = (int(i) for i in outside.nonzero()[0])
            raise ValueError(
                f"theta row {row} lies outside bounds on axis {axis}: "
                f"{float(theta[row, axis])} not in [{float(lower[axis])}, {float(upper[axis])}]"
            )

    def _into_box(self, theta: Tensor) -> Tensor:
        """``theta [..., D]`` projected onto the box (each coordinate clipped to its
        bounds); unchanged without ``bounds``."""
        if self.box is None:
            return theta
        return torch.minimum(torch.maximum(theta, self.box[0]), self.box[1])

    @property
    def asked_owner(self) -> Tensor | None:
        """``[B]`` the policy each row of the pending ask belongs to (−1: exploration)."""
        return self._pending_owner

    def _propose(self) -> tuple[Tensor, Tensor]:
        """One sample per sampled policy: ``([K_sampled, D], owners [K_sampled])``."""
        index = self._sampled_policies()
        if index.numel() == self.num_policies:
            means, covs = self.policy_means, self.policy_covariances
        else:
            means, covs = self.policy_means[index], self.policy_covariances[index]
        return draw_gaussian(means, covs, (), self.generator), index

    def _sampled_policies(self) -> Tensor:
        """``[K_sampled]`` the policies that draw a sample at the next ask: the active ones."""
        return self.active.nonzero().squeeze(-1)

    def tell(self, theta: Tensor, rewards: Tensor) -> None:
        """Report the returns of the parameters from the last :meth:`ask`.

        Args:
            theta: ``[B, D]`` the asked parameters (row i as asked), or only the first
                ``n < B`` rows of the ask (e.g. to end a run exactly at a trial budget; any
                hill-valley tests still queued are then forgotten, and ``last_rewards`` holds
                the told policies' returns only).
            rewards: ``[B]`` (or ``[n]``) their returns; all finite (a NaN or inf raises
                before anything changes), inside ``reward_range`` when a fixed one was given.

        If anything raises, the optimizer is left exactly as it was before the call.
        """
        if self._pending is None:
            raise RuntimeError("tell() called without a preceding ask()")
        asked, d = self._pending.shape
        check_matrix_shape(theta, (-1, d), "theta")
        if not 1 <= theta.shape[0] <= asked:
            raise ValueError(
                f"theta has {theta.shape[0]} rows: tell() takes the {asked} rows of the last "
                f"ask, or its first n (1 <= n <= {asked})"
            )
        check_finite(theta, "theta")
        self._check_in_box(theta)
        rewards = check_rewards(torch.as_tensor(rewards), theta.shape[0]).to(self.device)
        self.reward_scale.validate(rewards)  # before any state changes
        snapshot = self.state_dict()
        try:
            self._tell(self._into_box(theta.to(device=self.device, dtype=DTYPE)), rewards)
            if self.box is not None:
                # Eq. 7's means are convex combinations of samples in the box, but the
                # paper variant's posterior means weigh them by matrices.
                self.policy_means = self._into_box(self.policy_means)
        except BaseException:
            self.load_state_dict(snapshot)
            raise

    def _tell(self, theta: Tensor, rewards: Tensor) -> None:
        first = not self.started
        owner = self._pending_owner[: theta.shape[0]]
        if owner.shape[0] < self._pending_owner.shape[0]:
            self._forget_probes()  # a test whose probe was not told cannot be judged
        self._pending = self._pending_owner = None
        self._before_append(owner, theta, rewards)
        policy_rows = owner >= 0
        self.policy_samples += int(policy_rows.sum()) if not first else 0
        probe = owner == PROBE
        self.probe_rewards = rewards[probe]
        self.thetas = torch.cat((self.thetas, theta[~probe]))
        self.rewards = torch.cat((self.rewards, rewards[~probe]))
        self.owner = torch.cat((self.owner, owner[~probe]))
        self.trials += theta.shape[0]
        if first:
            self.last_rewards = rewards
        else:
            # Each policy's latest return: the sampled ones' new returns; a policy that drew
            # no sample (retired, or waiting its turn) keeps the mean return of its kept
            # samples.
            held = self._unsampled_rewards(owner[policy_rows])
            self.last_rewards = torch.cat((rewards[policy_rows], held))
        best = int(rewards.argmax())
        if float(rewards[best]) > self._best_reward:
            self._best_reward = float(rewards[best])
            self._best_theta = theta[best].clone()
        if first:
            self._after_initial_batch()
        else:
            self.iteration += 1
            self._power_step()
            self._after_iteration()

    def reevaluate(self, returns: Tensor) -> None:
        """Tell the optimizer that the world changed: ``returns`` are the returns of its
        stored policies measured after the change.

        Every return the optimizer kept was measured before the change and is forgotten:
        each policy keeps one sample, its mean, with its new return, and the best so far
        (:meth:`best`) becomes the best policy mean. A policy whose new return is below every
        return it had kept was hurt by the change: it is sampled again (a retired one too)
        from its mean with Σ_start's exploration, so it searches for a way around. The others
        go on as before. The next ``ask``/``tell`` continue the run; the trial count grows by
        K (one evaluation per stored policy, no relearning)::

            theta = opt.policy_means.to(dtype)        # [K, D], retired policies included
            opt.reevaluate(evaluate(theta))           # [K] returns in the changed world
            best_policy = opt.policy_means[opt.last_rewards.argmax()]   # switch to it

        Args:
            returns: ``[K]`` the return of each row of :attr:`policy_means`, finite (and inside
                ``reward_range`` when a fixed one was given).

        A pending ``ask`` is discarded. If anything raises, the optimizer is unchanged.
        """
        if not self.started:
            raise RuntimeError("reevaluate() needs a started run: tell() the first batch first")
        returns = check_rewards(torch.as_tensor(returns), self.num_policies).to(self.device)
        self.reward_scale.validate(returns)
        snapshot = self.state_dict()
        try:
            self._reevaluate(returns.to(DTYPE))
        except BaseException:
            self.load_state_dict(snapshot)
            raise

    def _reevaluate(self, returns: Tensor) -> None:
        k = self.num_policies
        hurt = returns < self._per_policy_rewards("amin")  # no kept samples: +inf, hurt
        self.thetas = self.policy_means.clone()
        self.rewards = returns.clone()
        self.owner = torch.arange(k, device=self.device)
        self.trials += k
        self.last_rewards = returns.clone()
        best = int(returns.argmax())
        self._best_theta = self.policy_means[best].clone()
        self._best_reward = float(returns[best])
        self._pending = self._pending_owner = None
        self._forget_probes()  # queued hill-valley tests compare returns of the old world
        self._after_reevaluation(hurt)

    def _forget_probes(self) -> None:
        """Empty the queues of hill-valley tests (candidates and pairs) and their probes."""
        for name in self._TENSORS:
            if name.startswith(("candidate_", "pair_", "probe_")):
                setattr(self, name, getattr(self, name)[:0])

    def _after_reevaluation(self, hurt: Tensor) -> None:
        """Restart the policies ``hurt`` ``[K]`` by the change (see :meth:`reevaluate`)."""
        self.active = self.active | hurt
        self.policy_covariances = torch.where(
            hurt[:, None, None], self.sigma_start, self.policy_covariances
        )

    def _unsampled_rewards(self, sampled: Tensor) -> Tensor:
        """``[K − S]`` the mean kept return of each policy not among the ``sampled [S]``
        (retired, or waiting its turn), in policy order."""
        unsampled = torch.ones(self.num_policies, dtype=torch.bool, device=self.device)
        unsampled[sampled] = False
        held = unsampled.nonzero().squeeze(-1)
        if held.numel() == 0:
            return self.rewards[:0]
        owned = self.owner >= 0
        k = self.num_policies
        total = torch.zeros(k, dtype=DTYPE, device=self.device).index_add_(
            0, self.owner[owned], self.rewards[owned]
        )
        count = torch.bincount(self.owner[owned], minlength=k).clamp_min(1)
        return (total / count)[held]

    def best(self) -> tuple[Tensor, float]:
        """The best parameters evaluated so far and their return: ``([D], float)``."""
        return self._best_theta.to(self.dtype), self._best_reward

    # ------------------------------------------------------------------ the PoWER step
    def _weights(self, rewards: Tensor) -> Tensor:
        """Reward weights in [floor, 1]; an adaptive scale spans the kept returns."""
        return self.reward_scale.weights(rewards, reference=self.rewards)

    def _power_step(self) -> None:
        """Keep the best K·M samples overall, then eq. 7 for every policy on its best M."""
        # "keeping a fixed number of elements K·M at every iteration": a policy whose samples
        # all fall out of the best K·M owns no data at the next clustering and disappears.
        overall = torch.zeros_like(self.rewards, dtype=torch.bool)
        top = min(self.num_policies * self.M, self.rewards.numel())
        overall[torch.topk(self.rewards, top).indices] = True
        self._keep(overall)
        self._power_update_all()

    def _power_update_all(self) -> None:
        """Eq. 7 for every active policy on its best M samples; drops the other samples
        that policies own (scouts, owner −1, are kept)."""
        owned = (self.owner >= 0).nonzero().squeeze(-1)
        keep, index, valid = importance_sets(
            self.owner[owned], self.rewards[owned], self.num_policies, self.M
        )
        index = owned[index.clamp_min(0)]  # slots -> rows of the kept samples
        slot_weights = self._slot_weights(index, valid)
        means = power_update(self.policy_means, self.thetas[index], slot_weights)
        self.policy_means = torch.where(self.active[:, None], means, self.policy_means)
        mask = self.owner < 0
        mask[owned[keep]] = True
        self._keep(mask)

    def _slot_weights(self, index: Tensor, valid: Tensor) -> Tensor:
        """``[K, M]`` eq. 7's weights of the importance-set slots ``index`` (``valid``
        marks filled ones): the reward weights of the kept returns."""
        return self._weights(self.rewards)[index] * valid

    def _keep(self, mask: Tensor) -> None:
        self.thetas, self.rewards, self.owner = (
            self.thetas[mask],
            self.rewards[mask],
            self.owner[mask],
        )

    def _before_append(self, owner: Tensor, theta: Tensor, rewards: Tensor) -> None:
        pass

    def _after_initial_batch(self) -> None:
        keep, _, _ = importance_sets(self.owner, self.rewards, 1, self.M)
        self._keep(keep)

    def _after_iteration(self) -> None:
        pass

    # ------------------------------------------------------------------ the policies
    @property
    def policies(self) -> GaussianMixture:
        """The current policies as a mixture over θ: component k is N(θ_k, Σ_k), weighted by
        the number of kept samples it owns, in ``theta0``'s dtype.

        The covariances are factorised in float64 before the cast: a converged policy's
        exploration (stds 1e-3 of Σ_start's, shaped by the rank-one updates) can be too
        ill-conditioned for a float32 Cholesky."""
        mixture = GaussianMixture(
            self._policy_weights(), self.policy_means, self.policy_covariances, validate_args=False
        )
        if self.dtype != DTYPE:
            mixture.scale_tril  # noqa: B018 (factorised here, carried by .to())
        return mixture.to(self.dtype)

    def _policy_weights(self) -> Tensor:
        """``[K]`` number of kept samples each policy owns (at least 1)."""
        owned = self.owner[self.owner >= 0]
        return torch.bincount(owned, minlength=self.num_policies).to(DTYPE).clamp_min(1.0)

    @property
    def policy_best_rewards(self) -> Tensor:
        """``[K]`` the best return among each policy's kept samples (−inf: none)."""
        return self._per_policy_rewards("amax")

    def _per_policy_rewards(self, reduce: str) -> Tensor:
        """``[K]`` the ``"amax"`` or ``"amin"`` of each policy's kept returns (∓inf: none)."""
        empty = -math.inf if reduce == "amax" else math.inf
        start = torch.full((self.num_policies,), empty, dtype=DTYPE, device=self.device)
        owned = self.owner >= 0
        return start.scatter_reduce(0, self.owner[owned], self.rewards[owned], reduce)

    # ------------------------------------------------------------------ checkpoints
    _TENSORS = (
        "thetas",
        "rewards",
        "owner",
        "policy_means",
        "policy_covariances",
        "active",
        "last_rewards",
        "probe_rewards",
        "candidate_means",
        "candidate_covariances",
        "candidate_probes",
        "candidate_thresholds",
        "candidate_partners",
        "candidate_samples",
        "candidate_rewards",
        "pair_index",
        "pair_probes",
    )

    def state_dict(self) -> dict:
        """Everything needed to continue the run exactly, generator state included."""
        state = {name: getattr(self, name).clone() for name in self._TENSORS}
        state.update(
            trials=self.trials,
            iteration=self.iteration,
            policy_samples=self.policy_samples,
            best_theta=self._best_theta.clone(),
            best_reward=self._best_reward,
            pending=None if self._pending is None else self._pending.clone(),
            pending_owner=None if self._pending_owner is None else self._pending_owner.clone(),
            generator=self.generator.get_state(),
            kind=type(self).__name__,
        )
        return state

    def load_state_dict(self, state: dict) -> None:
        if state.get("kind") != type(self).__name__:
            raise ValueError(
                f"state_dict is from a {state.get('kind')}, not a {type(self).__name__}"
            )
        for name in self._TENSORS:
            setattr(self, name, state[name].to(self.device))
        self.trials = int(state["trials"])
        self.iteration = int(state["iteration"])
        self.policy_samples = int(state["policy_samples"])
        self._best_theta = state["best_theta"].to(self.device)
        self._best_reward = float(state["best_reward"])
        self._pending = None if state["pending"] is None else state["pending"].to(self.device)
        owner = state["pending_owner"]
        self._pending_owner = None if owner is None else owner.to(self.device)
        self.generator.set_state(state["generator"])


class Power(PolicySearch):
    """PoWER, the paper's baseline: one policy with exploration covariance Σ_start.

    Algorithm 3: ``n0`` initial samples (default M) from N(θ0, Σ_start), then one sample
    per iteration; after each, θ moves by eq. 7 towards the reward-weighted average of the
    best M samples so far.

    The paper "manually reduced" PoWER's exploration covariance once cart-pole converged;
    ``exploration_decay`` < 1 is a reproducible stand-in: after iteration t the covariance is
    Σ_start · max(decay^t, min_exploration). The default 1.0 keeps Σ_start fixed.

    Args:
        theta0: ``[D]`` initial policy θ^(0).
        sigma_start: ``[D, D]`` exploration covariance Σ.
        M: importance-set size (paper: 5).
        n0: initial samples (default M).
        reward_range: ``None`` (default): returns mapped to weights in [floor, 1] by the
            min–max of the kept returns; ``(low, high)``: a fixed map; ``"positive"``:
            positive returns used as weights (see :class:`dipole_torch.RewardScale`).
        reward_floor: smallest reward weight.
        exploration_decay: per-iteration factor on the covariance, in (0, 1].
        min_exploration: floor of that factor, in (0, 1].
        generator: ``torch.Generator`` for every draw (default: seeded from torch's global
            generator).
        bounds: ``(lower, upper)`` box of the parameters (numbers, lists of D numbers or
            ``[D]`` tensors; ±inf leaves a side open), or ``None``; see
            :class:`PolicySearch`.
    """

    def __init__(
        self,
        theta0: Tensor,
        sigma_start: Tensor,
        M: int = 5,
        n0: int | None = None,
        reward_range: RewardRange = None,
        reward_floor: float = 1e-3,
        exploration_decay: float = 1.0,
        min_exploration: float = 1e-2,
        generator: torch.Generator | None = None,
        bounds: Bounds = None,
    ):
        check_real(exploration_decay, "exploration_decay")
        check_real(min_exploration, "min_exploration")
        super().__init__(theta0, sigma_start, M, n0, reward_range, reward_floor, generator, bounds)
        if not 0.0 < exploration_decay <= 1.0:
            raise ValueError(f"exploration_decay must lie in (0, 1], got {exploration_decay}")
        if not 0.0 < min_exploration <= 1.0:
            raise ValueError(f"min_exploration must lie in (0, 1], got {min_exploration}")
        self.exploration_decay = float(exploration_decay)
        self.min_exploration = float(min_exploration)

    def _after_iteration(self) -> None:
        if self.exploration_decay < 1.0:
            factor = max(self.exploration_decay**self.iteration, self.min_exploration)
            self.policy_covariances = factor * self.sigma_start[None]


class Dipole(PolicySearch):
    """DIPOLE (Algorithm 2): PoWER on every component of a reward-weighted DP mixture.

    * ``ask()``: first ``n0`` samples from N(θ0, Σ_start); then one sample per active policy
      (the ``max_sampled`` best at most) from its exploration Gaussian, ``explore`` scouts
      per policy sample (on average) from N(θ0, Σ_start) that belong to no policy yet, and
      any hill-valley probes (see below);
      :attr:`asked_owner` says which row is which.
    * ``tell()``: a PoWER step (eq. 7) per policy on its best M samples; after the initial
      batch and every ``cluster_every`` iterations, a weighted DP clustering (eq. 6, Neal's
      Algorithm 8) of the kept samples, augmented with their reward weights y = [θ, w],
      redefines the policies.

    Two variants share this class (``Dipole.paper(...)`` builds the paper's):

    ============================  ==========================  ==============================
    option                        default                     the paper (``Dipole.paper``)
    ============================  ==========================  ==============================
    ``reward_range``              ``None``: min–max of the    a fixed ``(low, high)``
                                  kept returns (any units)
    ``importance``                ``"policy"``: every policy  ``"global"``: the best K·M
                                  keeps its own best M        samples overall
    ``exploration``               ``"success"``: each policy  ``"clustering"``: the θ-block
                                  scales its covariance by    of its DP component's
                                  its success rate            posterior covariance
    ``explore``                   scouts per policy sample    0
    ``hill_valley``               probe new and neighbouring  no
                                  policies
    ``max_policies``              active policies at most     no limit
    ``max_sampled``               policies sampled in an      no limit
                                  iteration at most (the best
                                  4; the others wait)
    ``retire_std``                stop sampling a converged   0 (never)
                                  policy
    ``merge_radius``              drop duplicate policies     0 (never)
    ============================  ==========================  ==============================

    Why the default differs (numbers in the README, ``benchmarks/bench_multioptima.py``):

    * With ``importance="global"`` a policy on an optimum as good as the others' disappears
      as soon as its latest samples are a little worse than theirs; per-policy importance
      sets keep every optimum found. Eq. 7 then weighs each policy's M samples by the
      min–max of its own returns (see :meth:`_slot_weights`).
    * With ``exploration="clustering"`` a component's covariance is the posterior mean
      (Ψ0 + S)/(ν0 + n − p − 1) of a handful of points: Ψ0 keeps it near Σ_start and the
      policies never converge. ``"success"`` keeps a policy's covariance from clustering to
      clustering and multiplies it after every sample by exp((p̄ − p_t) / (d (1 − p_t)))²,
      where p̄ is the policy's running rate of samples that beat its best kept sample (the
      1/5th success rule of the (1+1)-CMA-ES, Igel, Suttorp & Hansen 2006: p_t = 2/11,
      smoothing 1/12, damping d = 1 + D/2), and adds that method's rank-one update along
      the evolution path of its successful steps (c_c = 2/(D + 2), c_cov = 2/(D² + 6)), so
      the covariance learns the optimum's shape. Exploration then shrinks geometrically near
      an optimum and grows on a slope (never beyond Σ_start). A new policy starts with
      Σ_start's shape at its component's spread (:meth:`_starting_exploration`), and a
      policy whose best sample lies far outside its exploration restarts from that sample
      (:meth:`_recentre_straddlers`).
    * Scouts let the clustering find optima after the first n0 samples: a scout that the
      DP puts in a component of its own is a candidate. With ``hill_valley`` the midpoint
      between its best sample and the nearest policy's best sample is evaluated at the next
      ask (the hill-valley test, Ursem 1999): only a candidate with a valley between them
      becomes a policy (while fewer than ``max_policies`` are active). Every fourth
      clustering, each active policy is probed against its nearest neighbour
      (``pair_points`` probes along the way), and of two on one hill the worse goes.
      Policies whose samples the DP merges become one.
    * A policy whose exploration std has shrunk below ``retire_std`` times Σ_start's is
      retired: it stays among :attr:`policies` but is no longer sampled, so its trials go to
      the others. An active policy closer than ``merge_radius`` exploration stds to another
      (both ways) or to a retired one, and to no third policy, is a duplicate and is
      dropped (one whose exploration covers two or more is left to the hill-valley probes).
    * A candidate starts exploring at most half the way to the policy it was told apart
      from; one that replaces a retired policy starts from its better sample.
    * With more than ``max_sampled`` active policies, only the ``max_sampled`` with the best
      kept returns draw a sample in an iteration; the others wait (still among
      :attr:`policies`, their exploration unchanged, their means eq. 7's average of the
      samples they keep) until a policy ahead of them retires or is dropped. Spread over
      every policy at once, a budget of a few hundred trials converged none of them on
      most 5-D landscapes with 8 optima; in turn, the first ones converge and the later
      ones still get their turn (see :meth:`_sampled_policies`).

    Args:
        theta0: ``[D]`` initial policy.
        sigma_start: ``[D, D]`` initial exploration covariance Σ_start.
        alpha: DP concentration α (paper: 1).
        m: auxiliary components in Algorithm 8 (paper: 10).
        M: importance-set size (paper: 5).
        n0: initial samples (default 2·M).
        cluster_every: iterations between clusterings (paper: "every M steps"; default M).
        sweeps: Gibbs sweeps per clustering, warm-started from the current policies.
        initial_sweeps: Gibbs sweeps of the first clustering (from one component).
        reward_range: ``None``, ``(low, high)`` or ``"positive"``; see
            :class:`dipole_torch.RewardScale`.
        reward_floor: smallest reward weight.
        regularization: covariance regularisation of the DP components, as a fraction of the
            diagonal of Σ_start (default 0.01).
        reward_weighted: use eq. 6 (``True``) or plain eq. 5 (an ablation).
        prior_df: ν0 of the inverse-Wishart prior (see below).
        importance: ``"policy"`` or ``"global"`` (see the table).
        exploration: ``"success"`` or ``"clustering"``.
        explore: scouts per policy sample, in [0, 1] (0: none).
        max_policies: most active policies, or ``None`` for no limit.
        max_sampled: most policies sampled in one iteration (those with the best kept
            returns), or ``None`` for every active policy (the paper's).
        retire_std: relative exploration std below which a policy is retired (0: never).
        merge_radius: duplicate distance in exploration stds (0: never merge).
        hill_valley: vet candidates and neighbouring policies with midpoint probes.
        pair_points: probes between two neighbouring policies, at i/(pair_points + 1) of
            the way (1: the midpoint; 3: Ursem's 1/4, 1/2, 3/4, which keeps routes whose
            valley lies off the middle, at the price of slower convergence; see
            :meth:`_probe_pairs` and the README).
        auxiliary: the auxiliary components of the clusterings' label draws: ``"fresh"``,
            Algorithm 8's m fresh draws from H for every point (the paper's sampler);
            ``"reuse"``, one set of m per sweep, a slot redrawn when a point takes it (Favaro
            & Teh 2013's exact re-use of Algorithm 8's draws: m + (slots taken) draws a
            sweep instead of N·m; CPU only); ``"auto"`` (default): ``"reuse"`` on the CPU
            once p = D + 1 ≥ 32, where the N·m inverse-Wishart draws of p × p are most of
            a clustering (the first one at D = 200: 1.3–2.2 s instead of 7–9 s), else
            ``"fresh"``, so nothing changes for D ≤ 30. ``Dipole.paper``: ``"fresh"``.
        generator: ``torch.Generator`` for every draw (default: seeded from torch's global
            generator).
        bounds: ``(lower, upper)`` box of the parameters (numbers, lists of D numbers or
            ``[D]`` tensors; ±inf leaves a side open), or ``None``; see
            :class:`PolicySearch`.

    Choices where the paper is silent:
        * The prior H is built at the first clustering from the exploration distribution:
          μ0 = [θ0, mean w], Σ0 = E[Σ] = blockdiag(Σ_start, var w) (var w floored at 1 % of
          the largest weight squared), ν0 = ``prior_df`` (default D + 3 = p + 2 for the
          p = D + 1 dimensions of y: the weakest inverse-Wishart prior with a finite mean).
          It is carried from clustering to clustering, updated after every sweep
          (:meth:`NormalInverseWishartPrior.updated`).
        * A clustering ends with the conditional posterior means of the last Gibbs state
          (:func:`dipole_torch.dp_mixture.posterior_point_estimate`); in the paper's variant
          its θ-means become the policies and its θ-block covariances their exploration
          noise. In the default variant a component that holds most of an existing policy's
          samples continues that policy (its mean and exploration); other components become
          new policies at the eq. 7 average of their samples with the posterior covariance.
        * r_c in eq. 6 is E[w | θ = μ_c^θ] under the mixture at the start of each sweep.
    """

    # (1+1)-CMA-ES success rule (Igel, Suttorp & Hansen 2006).
    TARGET_SUCCESS = 2.0 / 11.0
    SUCCESS_SMOOTHING = 1.0 / 12.0
    # auxiliary="auto" re-uses auxiliary draws from this dimension p = D + 1 of [θ, r] on.
    REUSE_AUXILIARY_DIM = 32

    def __init__(
        self,
        theta0: Tensor,
        sigma_start: Tensor,
        alpha: float = 1.0,
        m: int = 10,
        M: int = 5,
        n0: int | None = None,
        cluster_every: int | None = None,
        sweeps: int = 5,
        initial_sweeps: int = 20,
        reward_range: RewardRange = None,
        reward_floor: float = 1e-3,
        regularization: float = 1e-2,
        reward_weighted: bool = True,
        prior_df: float | None = None,
        importance: str = "policy",
        exploration: str = "success",
        explore: float = 0.05,
        max_policies: int | None = 8,
        max_sampled: int | None = 4,
        retire_std: float = 1e-3,
        merge_radius: float = 1.0,
        hill_valley: bool = True,
        pair_points: int = 1,
        auxiliary: str = "auto",
        generator: torch.Generator | None = None,
        bounds: Bounds = None,
    ):
        check_real(alpha, "alpha (DP concentration)")
        check_count(m, "m (auxiliary components)")
        check_count(cluster_every, "cluster_every", optional=True)
        check_count(sweeps, "sweeps")
        check_count(initial_sweeps, "initial_sweeps")
        check_count(max_policies, "max_policies", optional=True)
        check_count(max_sampled, "max_sampled", optional=True)
        check_count(pair_points, "pair_points")
        check_real(prior_df, "prior_df", optional=True)
        super().__init__(
            theta0,
            sigma_start,
            M,
            2 * M if n0 is None else n0,
            reward_range,
            reward_floor,
            generator,
            bounds,
        )
        if not (isinstance(alpha, int | float) and math.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha (DP concentration) must be positive and finite, got {alpha}")
        if int(m) != m or m < 1:
            raise ValueError(f"m (auxiliary components) must be a positive integer, got {m}")
        cluster_every = self.M if cluster_every is None else cluster_every
        for name, value in (
            ("cluster_every", cluster_every),
            ("sweeps", sweeps),
            ("initial_sweeps", initial_sweeps),
        ):
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value}")
        if not (math.isfinite(regularization) and regularization >= 0):
            raise ValueError(f"regularization must be non-negative, got {regularization}")
        if importance not in ("policy", "global"):
            raise ValueError(f"importance must be 'policy' or 'global', got {importance!r}")
        if auxiliary not in ("auto", "fresh", "reuse"):
            raise ValueError(f"auxiliary must be 'auto', 'fresh' or 'reuse', got {auxiliary!r}")
        if auxiliary == "reuse" and self.device.type != "cpu":
            raise ValueError(
                f"auxiliary='reuse' runs on the CPU only; on {self.device} use 'fresh' or 'auto'"
            )
        if exploration not in ("success", "clustering"):
            raise ValueError(f"exploration must be 'success' or 'clustering', got {exploration!r}")
        if not (math.isfinite(explore) and 0 <= explore <= 1):
            raise ValueError(f"explore must lie in [0, 1], got {explore}")
        if max_policies is not None and (int(max_policies) != max_policies or max_policies < 1):
            raise ValueError(f"max_policies must be a positive integer or None, got {max_policies}")
        for name, value in (("retire_std", retire_std), ("merge_radius", merge_radius)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be non-negative and finite, got {value}")
        self.alpha = float(alpha)
        self.m = int(m)
        self.cluster_every = int(cluster_every)
        self.sweeps = int(sweeps)
        self.initial_sweeps = int(initial_sweeps)
        self.regularization = float(regularization)
        self.reward_weighted = bool(reward_weighted)
        self.prior_df = float(self.dim + 3 if prior_df is None else prior_df)
        if not self.prior_df > self.dim + 2:
            raise ValueError(f"prior_df must exceed D + 2 = {self.dim + 2}, got {prior_df}")
        self.importance = importance
        self.exploration = exploration
        self.explore = float(explore)
        self.max_policies = None if max_policies is None else int(max_policies)
        self.max_sampled = None if max_sampled is None else int(max_sampled)
        self.retire_std = float(retire_std)
        self.merge_radius = float(merge_radius)
        self.hill_valley = bool(hill_valley)
        self.pair_points = int(pair_points)
        self.auxiliary = auxiliary
        # auto: the re-used draws where the N·m fresh inverse-Wishart draws of p × p
        # (p = D + 1) are most of a sweep's cost, and on the CPU, where they run.
        self.reuse_auxiliary = auxiliary == "reuse" or (
            auxiliary == "auto"
            and self.dim + 1 >= self.REUSE_AUXILIARY_DIM
            and self.device.type == "cpu"
        )
        self.success = torch.full((1,), self.TARGET_SUCCESS, dtype=DTYPE, device=self.device)
        self.paths = torch.zeros(1, self.dim, dtype=DTYPE, device=self.device)
        self.clusterings_skipped = 0  # clusterings that failed numerically (see _cluster)
        self._in_valley: Tensor | None = None  # within one tell (see _before_append)
        self.initial_prior: NormalInverseWishartPrior | None = None
        self.dp_state: DPMixtureState | None = None

    @classmethod
    def paper(
        cls,
        theta0: Tensor,
        sigma_start: Tensor,
        reward_range: RewardRange = "positive",
        **kwargs,
    ) -> Dipole:
        """DIPOLE exactly as in the paper: the best K·M samples kept overall, exploration from
        the DP posterior, no scouts, no retirement, no merging, a fixed reward range
        (``"positive"``: positive returns used as they are). Other options as ``Dipole``."""
        paper = dict(
            importance="global",
            exploration="clustering",
            explore=0,
            max_policies=None,
            max_sampled=None,
            retire_std=0.0,
            merge_radius=0.0,
            hill_valley=False,
            auxiliary="fresh",
        )
        return cls(theta0, sigma_start, reward_range=reward_range, **(paper | kwargs))

    @property
    def is_paper_variant(self) -> bool:
        return self.importance == "global" and self.exploration == "clustering"

    # ------------------------------------------------------------------ ask
    def _propose(self) -> tuple[Tensor, Tensor]:
        theta, owner = (
            super()._propose() if bool(self.active.any()) else (self.thetas[:0], self.owner[:0])
        )
        scouts = self._scouts_next(theta.shape[0])
        if scouts:
            extra = draw_gaussian(self.theta0, self.sigma_start, (scouts,), self.generator)
            theta = torch.cat((theta, extra))
            owner = torch.cat((owner, torch.full_like(extra[:, 0], -1, dtype=torch.long)))
        probes = torch.cat((self.candidate_probes, self.pair_probes))
        if probes.shape[0]:
            theta = torch.cat((theta, probes))
            owner = torch.cat((owner, torch.full_like(probes[:, 0], PROBE, dtype=torch.long)))
        return theta, owner

    def _sampled_policies(self) -> Tensor:
        """``[K_sampled]`` the active policies that draw a sample at the next ask: all of
        them, or the ``max_sampled`` with the best kept returns (ties: the lower index).

        A waiting policy's best return stays as it is while the sampled ones' only grow: it
        gets its turn when one ahead of it retires (converged) or is dropped, or when a
        clustering reshapes the policies."""
        index = super()._sampled_policies()
        if self.max_sampled is None or index.numel() <= self.max_sampled:
            return index
        best = self.policy_best_rewards[index]
        ahead = torch.argsort(best, descending=True, stable=True)[: self.max_sampled]
        return index[ahead].sort().values

    def _scouts_next(self, sampled: int) -> int:
        """Scouts in the next ask, whose ``sampled`` policies draw a sample each: ``explore``
        per policy sample on average; a fresh ``n0`` when every policy has been retired (a
        restart)."""
        if not bool(self.active.any()):
            # A restart, with or without scouts: an empty ask would end the run.
            return self.n0
        after = self.policy_samples + sampled
        return math.floor(self.explore * after) - math.floor(self.explore * self.policy_samples)

    # ------------------------------------------------------------------ tell
    def _before_append(self, owner: Tensor, theta: Tensor, rewards: Tensor) -> None:
        """Exploration that follows each policy's own samples, as in the (1+1)-CMA-ES
        (Igel, Suttorp & Hansen 2006): a sample succeeds when it beats its policy's best kept
        one. A success moves the policy's evolution path p towards the step x − μ and adds
        the rank-one term c_cov p pᵀ to its covariance; the success rate p̄ scales the
        covariance by exp((p̄ − p_t) / (d (1 − p_t)))²."""
        self._in_valley = None
        if self.exploration != "success" or not self.started:
            return
        rows = owner >= 0
        policy = owner[rows]
        succeeded = rewards[rows] > self.policy_best_rewards[policy]
        # A sample worse than every kept one of its policy (see _recentre_straddlers).
        worst = self._per_policy_rewards("amin")
        self._in_valley = torch.zeros(self.num_policies, dtype=torch.bool, device=self.device)
        self._in_valley[policy] = rewards[rows] < worst[policy]
        d = self.dim
        c_c, c_cov = 2.0 / (d + 2.0), 2.0 / (d * d + 6.0)
        step = theta[rows] - self.policy_means[policy]
        paths = self.paths[policy]
        paths = torch.where(
            succeeded[:, None], (1 - c_c) * paths + math.sqrt(c_c * (2 - c_c)) * step, paths
        )
        covs = self.policy_covariances[policy]
        rank_one = (1 - c_cov) * covs + c_cov * paths[:, :, None] * paths[:, None, :]
        covs = torch.where(succeeded[:, None, None], rank_one, covs)
        c = self.SUCCESS_SMOOTHING
        success = (1 - c) * self.success[policy] + c * succeeded.to(DTYPE)
        p_t = self.TARGET_SUCCESS
        factor = torch.exp((success - p_t) / ((1.0 + d / 2.0) * (1 - p_t)))
        # Never explore wider than Σ_start: a policy that keeps failing while it grows
        # would otherwise turn into random search.
        relative = self._relative_std(covs)
        factor = torch.minimum(factor, 1.0 / relative.clamp_min(1e-300))
        self.paths, self.success = self.paths.clone(), self.success.clone()
        self.policy_covariances = self.policy_covariances.clone()
        self.paths[policy] = paths
        self.success[policy] = success
        self.policy_covariances[policy] = covs * factor[:, None, None] ** 2

    def _after_reevaluation(self, hurt: Tensor) -> None:
        super()._after_reevaluation(hurt)
        self.success = torch.where(hurt, self.TARGET_SUCCESS, self.success)
        self.paths = torch.where(hurt[:, None], 0.0, self.paths)
        self._in_valley = None

    def _power_step(self) -> None:
        if self.importance == "global":
            super()._power_step()
        else:
            self._power_update_all()

    def _slot_weights(self, index: Tensor, valid: Tensor) -> Tensor:
        """With per-policy importance sets, each policy's weights are the min–max map of
        its own M returns (best 1, worst ``reward_floor``): a policy's step then depends on
        its own samples only, not on how bad a scout or another policy's samples were (with
        the kept returns' range, a policy near the top has M weights ≈ 1 and its mean is a
        plain average of its samples, which lags and can straddle two optima)."""
        if self.importance == "global":
            return super()._slot_weights(index, valid)
        returns = self.rewards[index]
        low = torch.where(valid, returns, math.inf).amin(-1, keepdim=True)
        high = torch.where(valid, returns, -math.inf).amax(-1, keepdim=True)
        spread = high - low
        tiny = torch.finfo(DTYPE).tiny
        mapped = ((returns - low) / spread.clamp_min(tiny)).clamp(self.reward_scale.floor, 1.0)
        # One sample, or M equal returns: equal weights.
        weights = torch.where(spread > 0, mapped, torch.ones_like(mapped))
        return weights * valid

    def _after_iteration(self) -> None:
        if self.is_paper_variant:
            if self.iteration % self.cluster_every == 0:
                self._cluster_paper()
            return
        # First, while the policies are numbered as in this tell's samples.
        self._recentre_straddlers(self._in_valley)
        self._judge_candidates()
        restart = not bool(self.active.any())
        clustered = restart or self.iteration % self.cluster_every == 0
        if clustered:
            self._cluster()
        self._retire_and_merge()
        self._probe_candidates()
        if clustered and self.hill_valley and (self.iteration // self.cluster_every) % 4 == 0:
            self._probe_pairs()

    # ------------------------------------------------------------------ clustering
    def _augmented(self, rows: Tensor | None = None) -> Tensor:
        """``[N, D + 1]`` the kept samples (or ``rows`` of them) as y = [θ, w]."""
        w = self._weights(self.rewards)
        if rows is not None:
            return torch.cat((self.thetas[rows], w[rows, None]), dim=1)
        return torch.cat((self.thetas, w[:, None]), dim=1)

    def _after_initial_batch(self) -> None:
        y = self._augmented()
        w = y[:, -1]
        var_w = float(w.var()) if w.numel() > 1 else 0.0
        mean = torch.cat((self.theta0, w.mean()[None]))
        # Floor the prior's reward variance relative to the weights' own scale (positive
        # returns used as weights may be of any order).
        floor = 1e-2 * float(w.abs().max()) ** 2
        reward_variance = torch.tensor([[max(var_w, floor)]], dtype=DTYPE, device=self.device)
        cov = torch.block_diag(self.sigma_start, reward_variance)
        self.initial_prior = NormalInverseWishartPrior.from_exploration(
            mean, cov, df=self.prior_df, regularization=self.regularization
        )
        try:
            state = self._fit(y, self.initial_sweeps)
        except torch.linalg.LinAlgError:
            # See _cluster: start from Algorithm 1's single component instead.
            self.clusterings_skipped += 1
            state = DPMixtureState.single_component(y, self.initial_prior)
        self._adopt(y, state)

    def _cluster_paper(self) -> None:
        """Weighted DP clustering of the kept samples, warm-started from the policies."""
        y = self._augmented()
        assert self.dp_state is not None and self.initial_prior is not None
        reward_means = self.dp_state.means[:, -1:]
        start = DPMixtureState(
            labels=self.owner.clone(),
            means=torch.cat((self.policy_means, reward_means), dim=1),
            covariances=self.dp_state.covariances,
            prior=self.dp_state.prior,
        )
        try:
            state = self._fit(y, self.sweeps, start)
        except torch.linalg.LinAlgError:
            self.clusterings_skipped += 1  # see _cluster: the policies go on unclustered
            return
        self._adopt(y, state)

    def _fit(self, y: Tensor, sweeps: int, start: DPMixtureState | None = None) -> DPMixtureState:
        """``sweeps`` Gibbs sweeps of the weighted DP mixture on ``y`` from ``start`` (or
        Algorithm 1's single component), anchored on the initial prior."""
        assert self.initial_prior is not None
        return fit_dp_mixture(
            y,
            self.initial_prior,
            sweeps,
            self.alpha,
            self.m,
            self.reward_weighted,
            self.generator,
            state=start,
            reuse_auxiliary=self.reuse_auxiliary,
        )

    def _adopt(self, y: Tensor, state: DPMixtureState) -> None:
        """Make the clustering's components the policies, and keep each one's best M."""
        state = posterior_point_estimate(y, state)
        self.dp_state = state
        d = self.dim
        self.policy_means = state.means[:, :d].clone()
        self.policy_covariances = self._starting_exploration(state.covariances[:, :d, :d])
        self.owner = state.labels.clone()
        k = state.num_components
        self.active = torch.ones(k, dtype=torch.bool, device=self.device)
        self.success = torch.full((k,), self.TARGET_SUCCESS, dtype=DTYPE, device=self.device)
        self.paths = torch.zeros(k, d, dtype=DTYPE, device=self.device)
        if not self.is_paper_variant and self.max_policies is not None:
            best = self.policy_best_rewards
            dropped = torch.argsort(best, descending=True, stable=True)[self.max_policies :]
            if dropped.numel():
                self._remove_policies(dropped)
        keep, _, _ = importance_sets(self.owner, self.rewards, self.num_policies, self.M)
        self._keep(keep)

    def _starting_exploration(self, covariances: Tensor) -> Tensor:
        """A new policy's exploration covariance from its DP component's posterior
        covariance ``[..., D, D]``: Σ_start's shape at the component's spread,
        tr(Σ_start⁻¹ Σ_c)/D · Σ_start (at most Σ_start), in the default variant; Σ_c itself
        in the paper's.

        A component of a few points in D dimensions has a badly conditioned posterior
        covariance (condition numbers of 30–50 seen at D = 10); the success rule's rank-one
        update needs hundreds of samples to unlearn it, which halved the policies' speed of
        convergence (see the README)."""
        if self.exploration != "success":
            return covariances.clone()
        whitened = torch.linalg.solve(self.sigma_start, covariances)
        spread = whitened.diagonal(dim1=-2, dim2=-1).mean(-1).clamp(max=1.0)
        return spread[..., None, None] * self.sigma_start

    def _cluster(self) -> None:
        """The default variant's clustering: the samples of the active policies and the
        scouts, warm-started with one component per active policy and one per scout.

        A component continues the old policy that owns most of its samples (matched
        greedily, largest overlap first); the others become new policies, the best first,
        while fewer than ``max_policies`` are active. Old policies left without a component
        were merged by the DP and are dropped.
        """
        assert self.dp_state is not None and self.initial_prior is not None
        rows = ((self.owner < 0) | self.active[self.owner.clamp_min(0)]).nonzero().squeeze(-1)
        if rows.numel() == 0:
            return
        y = self._augmented(rows)
        old = self.owner[rows]
        policies = self.active.nonzero().squeeze(-1)
        compact = torch.full((self.num_policies,), -1, dtype=torch.long, device=self.device)
        compact[policies] = torch.arange(policies.numel(), device=self.device)
        scouts = old < 0
        start_labels = compact[old.clamp_min(0)]
        start_labels[scouts] = policies.numel() + torch.arange(
            int(scouts.sum()), device=self.device
        )
        try:
            start = DPMixtureState.from_labels(y, start_labels, self.dp_state.prior)
            state = posterior_point_estimate(y, self._fit(y, self.sweeps, start))
        except torch.linalg.LinAlgError:
            # Converged policies' samples can make a component's covariance numerically
            # singular in float64. A run that goes well must not stop: skip this clustering
            # (the policies go on with their own exploration) and forget the scouts.
            self.clusterings_skipped += 1
            self._keep(self.owner >= 0)
            return
        self.dp_state = state
        labels = state.labels
        k_new = state.num_components
        # overlap[c, j]: samples of old active policy j in component c.
        overlap = torch.zeros(k_new, policies.numel(), dtype=torch.long, device=self.device)
        owned = ~scouts
        overlap.index_put_(
            (labels[owned], compact[old[owned]]),
            torch.ones_like(labels[owned]),
            accumulate=True,
        )
        continues = torch.full((k_new,), -1, dtype=torch.long, device=self.device)
        remaining = overlap.clone()
        while bool((remaining > 0).any()):
            flat = int(remaining.argmax())
            c, j = divmod(flat, remaining.shape[1])
            continues[c] = int(policies[j])
            remaining[c] = 0
            remaining[:, j] = 0
        # New components, best sample first, while there is room.
        fresh = (continues < 0).nonzero().squeeze(-1)
        component_best = torch.full((k_new,), -math.inf, dtype=DTYPE, device=self.device)
        component_best = component_best.scatter_reduce(0, labels, self.rewards[rows], "amax")
        fresh = fresh[torch.argsort(component_best[fresh], descending=True, stable=True)]
        retired = int((~self.active).sum())
        room = (
            fresh.numel()
            if self.max_policies is None
            else max(self.max_policies - int((continues >= 0).sum()), 0)
        )
        fresh = fresh[:room]
        # Assemble the policies: retired ones, continued ones, then new ones.
        keep_old = torch.cat(((~self.active).nonzero().squeeze(-1), continues[continues >= 0]))
        new_index = torch.full((self.num_policies,), -1, dtype=torch.long, device=self.device)
        new_index[keep_old] = torch.arange(keep_old.numel(), device=self.device)
        d = self.dim
        weights = y[:, -1]
        new_means, new_covs = [], []
        component_policy = torch.full((k_new,), -1, dtype=torch.long, device=self.device)
        component_policy[continues >= 0] = new_index[continues[continues >= 0]]
        vet = self.hill_valley and keep_old.numel() > 0
        candidates = []
        for c in fresh.tolist():
            members = labels == c
            w = weights[members]
            mean = (w[:, None] * y[members, :d]).sum(0) / w.sum()
            if vet:
                # Its best sample, to be compared with the nearest policy's (see
                # _probe_candidates); its samples leave the data meanwhile.
                best = int(torch.where(members, self.rewards[rows], -math.inf).argmax())
                candidates.append(
                    (
                        mean,
                        self._starting_exploration(state.covariances[c, :d, :d]),
                        y[best, :d],
                        self.rewards[rows][best],
                    )
                )
                continue
            component_policy[c] = keep_old.numel() + len(new_means)
            new_means.append(mean)
            new_covs.append(self._starting_exploration(state.covariances[c, :d, :d]))
        if candidates:
            self._add_candidates(candidates)
        means = self.policy_means[keep_old]
        covs = self.policy_covariances[keep_old]
        success = self.success[keep_old]
        paths = self.paths[keep_old]
        active = torch.cat(
            (
                torch.zeros(retired, dtype=torch.bool, device=self.device),
                torch.ones(
                    keep_old.numel() - retired + len(new_means),
                    dtype=torch.bool,
                    device=self.device,
                ),
            )
        )
        if new_means:
            means = torch.cat((means, torch.stack(new_means)))
            covs = torch.cat((covs, torch.stack(new_covs)))
            success = torch.cat(
                (
                    success,
                    torch.full(
                        (len(new_means),), self.TARGET_SUCCESS, dtype=DTYPE, device=self.device
                    ),
                )
            )
        # Re-own the samples: retired policies' stay, clustered ones follow their component
        # (a component that became no policy loses its samples).
        owner = new_index[self.owner.clamp_min(0)]
        owner[rows] = component_policy[labels]
        keep_rows = owner >= 0
        self.policy_means, self.policy_covariances = means, covs
        self.success, self.active = success, active
        self.paths = torch.cat((paths, paths.new_zeros(len(new_means), d)))
        self.owner = owner
        self._keep(keep_rows)
        keep, _, _ = importance_sets(self.owner, self.rewards, self.num_policies, self.M)
        self._keep(keep)

    # ------------------------------------------------------------------ new optima
    def _add_candidates(self, candidates: list[tuple[Tensor, Tensor, Tensor, Tensor]]) -> None:
        """Queue new components ``(mean [D], covariance [D, D], best sample [D], its return)``
        for the hill-valley test."""
        means, covs, samples, rewards = (torch.stack(x) for x in zip(*candidates, strict=True))
        self.candidate_means = torch.cat((self.candidate_means, means))
        self.candidate_covariances = torch.cat((self.candidate_covariances, covs))
        self.candidate_samples = torch.cat((self.candidate_samples, samples))
        self.candidate_rewards = torch.cat((self.candidate_rewards, rewards))

    def _policy_best_samples(self) -> Tensor:
        """``[K, D]`` each policy's best kept sample (its mean where it has none)."""
        best = self.policy_means.clone()
        owned = (self.owner >= 0).nonzero().squeeze(-1)
        order = owned[torch.argsort(self.rewards[owned], stable=True)]
        best[self.owner[order]] = self.thetas[order]  # ascending: the best is written last
        return best

    def _probe_candidates(self) -> None:
        """The hill-valley test (Ursem 1999; Maree et al. 2018) of each queued candidate
        against the policy nearest to it: the midpoint between the candidate's best sample
        and that policy's best sample is evaluated at the next ask. A midpoint worse than
        both ends shows a valley between them, so the candidate sits on another optimum."""
        c = self.candidate_means.shape[0]
        if c == 0:
            return
        if self.num_policies == 0:
            self._accept_candidates(torch.ones(c, dtype=torch.bool, device=self.device))
            return
        partners = self._policy_best_samples()
        distance = self._nearest(self.candidate_samples, partners)  # [C, K]
        nearest = distance.argmin(-1)
        self.candidate_probes = 0.5 * (self.candidate_samples + partners[nearest])
        self.candidate_thresholds = torch.minimum(
            self.candidate_rewards, self.policy_best_rewards[nearest]
        )
        self.candidate_partners = nearest

    def _probe_pairs(self) -> None:
        """Queue hill-valley probes between every active policy and the policy nearest to
        it (every fourth clustering): two policies on one hill are one optimum.

        Each pair's ``pair_points`` probes lie at i/(pair_points + 1) of the way between the
        two best samples (Ursem 1999's 1/4, 1/2 and 3/4 for 3): between two policies still
        far below their tops the valley lies nearer the worse one, where a midpoint misses it
        (seen on the viapoint task: two routes, returns 0.91 and 0.85, a midpoint at 0.86 and
        0.84 at three quarters; the midpoint test dropped the second route)."""
        if self.num_policies < 2 or not bool(self.active.any()):
            self._clear_pairs()
            return
        best = self._policy_best_samples()
        distance = self._nearest(best, best)
        distance.fill_diagonal_(math.inf)
        a = self.active.nonzero().squeeze(-1)
        b = distance[a].argmin(-1)
        pairs = torch.stack((torch.minimum(a, b), torch.maximum(a, b)), -1).unique(dim=0)
        self.pair_index = pairs
        n = self.pair_points
        t = torch.arange(1, n + 1, dtype=DTYPE, device=self.device) / (n + 1)
        start, end = best[pairs[:, 0], None, :], best[pairs[:, 1], None, :]
        # (1 − t)·a + t·b: for t = ½ bit for bit the midpoint ½(a + b) of pair_points = 1.
        probes = (1 - t)[:, None] * start + t[:, None] * end
        self.pair_probes = probes.reshape(-1, self.dim)  # [P * pair_points, D], pair-major

    def _clear_pairs(self) -> None:
        self.pair_index, self.pair_probes = self.pair_index[:0], self.pair_probes[:0]

    def _nearest(self, points: Tensor, others: Tensor) -> Tensor:
        """``[P, Q]`` distances between ``points: [P, D]`` and ``others: [Q, D]`` in units of
        Σ_start's per-axis std (the scale the hill-valley pairs are chosen in)."""
        scale = self.sigma_start.diagonal().sqrt()
        return torch.cdist(points / scale, others / scale)

    def _judge_pairs(self, probe_rewards: Tensor) -> None:
        """Drop the worse policy of each probed pair that shows no valley between them (no
        probe worse than both ends; a retired policy goes only for a strictly better active
        one: it claimed the top of the hill, which the active one refutes)."""
        if self.pair_index.shape[0] == 0:
            return
        best = self.policy_best_rewards
        a, b = self.pair_index[:, 0], self.pair_index[:, 1]
        lowest = probe_rewards.reshape(a.shape[0], -1).amin(-1)
        same_hill = lowest >= torch.minimum(best[a], best[b])
        # Ties go against the active one: the retired one's top stands.
        drop_b = torch.where(
            self.active[a] != self.active[b],
            torch.where(self.active[b], best[b] <= best[a], best[b] < best[a]),
            best[b] < best[a],
        )
        loser = torch.where(drop_b, b, a)[same_hill]
        self._clear_pairs()
        if loser.numel():
            self._remove_policies(loser.unique())

    def _judge_candidates(self) -> None:
        """Accept the candidates whose probe found a valley, and those on the hill of a
        retired policy with a better sample than its best (the retired policy stopped short
        of the top, e.g. its samples straddled two hills: it is replaced); forget the
        others. Then judge the probed pairs of policies."""
        n = self.candidate_probes.shape[0]
        pair_rewards = self.probe_rewards[n:]
        if n:
            partners = self.candidate_partners
            valley = self.probe_rewards[:n] < self.candidate_thresholds
            refutes = (
                ~valley
                & ~self.active[partners]
                & (self.candidate_rewards > self.policy_best_rewards[partners])
            )
            self._place_candidates(refutes)
            accepted = self._accept_candidates(valley | refutes)
            replaced = partners[accepted[refutes[accepted]]].unique()
            if replaced.numel():
                # Pair probes were chosen by index: they no longer apply.
                self._clear_pairs()
                pair_rewards = pair_rewards[:0]
                self._remove_policies(replaced)
        self._judge_pairs(pair_rewards)

    def _place_candidates(self, refutes: Tensor) -> None:
        """Where the judged candidates would start (``refutes [C]``: the candidates that
        replace their retired partner, the others being new hills).

        * A replacement starts from its refuting sample, the best point known on that hill,
          not from its component's mean, which may lie on the next hill (seen on the 1-D
          equal-maxima function: the replacement wandered off and the optimum was lost).
        * Each explores at most half the way to its partner, in Σ_start's per-axis stds:
          for a new hill a valley lies in between, so the hill is no wider, and a wider
          start spends its first samples on the neighbour's hill (new policies between
          converged ones then looked like duplicates of them). A replacement explores at
          least as widely as the policy it replaces."""
        self.candidate_means = torch.where(
            refutes[:, None], self.candidate_samples, self.candidate_means
        )
        scale = self.sigma_start.diagonal().sqrt()
        half_gap = ((self.candidate_probes - self.candidate_samples) / scale).norm(dim=-1)
        partner = self._relative_std()[self.candidate_partners]
        half_gap = torch.where(refutes, torch.maximum(half_gap, partner), half_gap)
        relative = self._relative_std(self.candidate_covariances)
        factor = (half_gap / relative.clamp_min(1e-300)).clamp(max=1.0).square()
        self.candidate_covariances = factor[:, None, None] * self.candidate_covariances

    def _accept_candidates(self, accept: Tensor) -> Tensor:
        """New policies from the ``accept``-ed candidates (within ``max_policies``); the
        candidate queue is emptied. Returns the indices of the candidates that became
        policies."""
        index = accept.nonzero().squeeze(-1)
        if self.max_policies is not None:
            room = max(self.max_policies - int(self.active.sum()), 0)
            index = index[torch.argsort(self.candidate_rewards[index], descending=True)][:room]
        n = index.numel()
        if n:
            k = self.num_policies
            self.policy_means = torch.cat((self.policy_means, self.candidate_means[index]))
            self.policy_covariances = torch.cat(
                (self.policy_covariances, self.candidate_covariances[index])
            )
            self.active = torch.cat((self.active, self.active.new_ones(n)))
            self.paths = torch.cat((self.paths, self.paths.new_zeros(n, self.dim)))
            self.success = torch.cat(
                (self.success, self.success.new_full((n,), self.TARGET_SUCCESS))
            )
            self.thetas = torch.cat((self.thetas, self.candidate_samples[index]))
            self.rewards = torch.cat((self.rewards, self.candidate_rewards[index]))
            self.owner = torch.cat((self.owner, k + torch.arange(n, device=self.device)))
        empty = self.candidate_means[:0]
        self.candidate_means, self.candidate_samples, self.candidate_probes = empty, empty, empty
        self.candidate_covariances = self.candidate_covariances[:0]
        self.candidate_rewards = self.candidate_rewards[:0]
        self.candidate_thresholds = self.candidate_thresholds[:0]
        self.candidate_partners = self.candidate_partners[:0]
        return index

    # ------------------------------------------------------------------ retire and merge
    def _relative_std(self, covariances: Tensor | None = None) -> Tensor:
        """``[K]`` each policy's largest exploration std relative to Σ_start's, per axis."""
        covs = self.policy_covariances if covariances is None else covariances
        ratio = covs.diagonal(dim1=-2, dim2=-1) / self.sigma_start.diagonal()
        return ratio.amax(-1).sqrt()

    def _exploration_distance(self, diff: Tensor) -> Tensor:
        """``[K, P]`` the Mahalanobis lengths of ``diff: [K, P, D]`` under each policy's
        exploration covariance (row k under policy k's); inf in the rows whose covariance
        has lost definiteness in float64."""
        chol, info = torch.linalg.cholesky_ex(self.policy_covariances)
        ok = info == 0
        eye = torch.eye(self.dim, dtype=DTYPE, device=self.device)
        chol = torch.where(ok[:, None, None], chol, eye)
        z = torch.linalg.solve_triangular(chol, diff.transpose(-1, -2), upper=False)
        return torch.where(ok[:, None], z.square().sum(-2).sqrt(), math.inf)

    def _recentre_straddlers(self, in_valley: Tensor | None) -> None:
        """Restart a policy from its best kept sample when that sample lies more than
        3 + √D exploration stds (Mahalanobis, under the policy's covariance) from its mean
        and the policy's latest sample (``in_valley [K]``) was worse than all its kept ones.

        Its kept samples then straddle two or more hills (the clustering gave it samples
        from both): eq. 7 puts the mean between them, in a valley, where no new sample beats
        the kept ones, and the success rule shrinks the exploration until the policy retires
        short of any top (seen on 2-D landscapes: means at 41 % of the height with the best
        sample at 98 %, 368 stds away). The policy keeps its best sample only, as a new
        policy would, and explores with Σ_start's shape at its old samples' spread around
        it. The second condition spares a policy on a plateau (cart-pole's 1000 steps): its
        exploration shrinks below its kept samples' spread too, but its samples tie with
        the kept ones."""
        if in_valley is None or not bool((in_valley & self.active).any()):
            return  # the usual case: no factorisation needed
        best = self._policy_best_samples()
        distance = self._exploration_distance((best - self.policy_means)[:, None, :])[:, 0]
        limit = 3.0 + math.sqrt(self.dim)
        # (A covariance that lost definiteness, distance inf, restarts nothing.)
        straddling = self.active & in_valley & distance.isfinite() & (distance > limit)
        if not bool(straddling.any()):
            return
        for j in straddling.nonzero().squeeze(-1).tolist():
            own = (self.owner == j).nonzero().squeeze(-1)
            centre = best[j]
            diff = self.thetas[own] - centre
            scatter = diff.T @ diff / max(own.numel() - 1, 1)
            self.policy_means[j] = centre
            self.policy_covariances[j] = self._starting_exploration(scatter)
            self.success[j] = self.TARGET_SUCCESS
            self.paths[j] = 0.0
            keep = torch.ones_like(self.owner, dtype=torch.bool)
            keep[own] = False
            keep[own[self.rewards[own].argmax()]] = True
            self._keep(keep)

    def _retire_and_merge(self) -> None:
        if self.retire_std > 0:
            self.active = self.active & (self._relative_std() >= self.retire_std)
        if self.merge_radius <= 0 or self.num_policies < 2:
            return
        # Mahalanobis distance of policy b's mean under policy a's exploration: [K, K]
        # (inf: a's covariance lost definiteness in float64 and judges no duplicates).
        diff = self.policy_means[None, :, :] - self.policy_means[:, None, :]
        distance = self._exploration_distance(diff)
        near = distance < self.merge_radius
        near.fill_diagonal_(False)
        # A policy whose exploration covers two or more others is judged by none of them:
        # exploring that widely (a new policy), it may well be on a hill of its own, which
        # only a hill-valley probe can tell (seen with many optima: new policies between
        # retired ones were dropped as duplicates, 90 of 103 on Vincent's 2-D function).
        judged = near.sum(-1) == 1
        best = self.policy_best_rewards
        drop = torch.zeros(self.num_policies, dtype=torch.bool, device=self.device)
        for a in (self.active & judged).nonzero().squeeze(-1).tolist():
            for b in range(self.num_policies):
                if a == b or drop[b] or drop[a]:
                    continue
                if not self.active[b]:
                    duplicate = bool(near[a, b])  # a explores a retired optimum...
                    if duplicate and best[a] > best[b]:
                        drop[b] = True  # ...which stopped short of the top: a goes on
                        continue
                else:
                    duplicate = bool(near[a, b] and near[b, a])
                    # Of two active duplicates the worse one goes.
                    if duplicate and best[a] > best[b]:
                        drop[b] = True
                        continue
                if duplicate:
                    drop[a] = True
        if drop.any():
            self._remove_policies(drop.nonzero().squeeze(-1))

    def _remove_policies(self, index: Tensor) -> None:
        """Drop policies ``index`` and their samples; renumber the others."""
        keep = torch.ones(self.num_policies, dtype=torch.bool, device=self.device)
        keep[index] = False
        new_index = torch.cumsum(keep.long(), 0) - 1
        rows = (self.owner < 0) | keep[self.owner.clamp_min(0)]
        self._keep(rows)
        self.owner = torch.where(self.owner >= 0, new_index[self.owner.clamp_min(0)], self.owner)
        self.policy_means = self.policy_means[keep]
        self.policy_covariances = self.policy_covariances[keep]
        self.active = self.active[keep]
        self.success = self.success[keep]
        self.paths = self.paths[keep]

    # ------------------------------------------------------------------ the model
    @property
    def mixture(self) -> GaussianMixture:
        """The IGMM over [θ, r] of the last clustering, with the policies' current means,
        r in return units.

        ``mixture.condition(range(D), theta).mean`` predicts the return of ``theta``;
        ``mixture.condition([D], r)`` is the distribution of policies given a return level.
        Components are the last clustering's; in the default variant policies created or
        merged since then are not in it.
        """
        if self.dp_state is None:
            raise RuntimeError("the mixture exists after the first tell()")
        slope = self.reward_scale.slope(self.rewards)
        scale = torch.ones(self.dim + 1, dtype=DTYPE, device=self.device)
        scale[-1] = slope
        means = self.dp_state.means.clone()
        if self.is_paper_variant and means.shape[0] == self.num_policies:
            means[:, : self.dim] = self.policy_means
        means[:, -1] = self.reward_scale.inverse(means[:, -1], self.rewards)
        covs = self.dp_state.covariances * scale[:, None] * scale[None, :]
        if self.is_paper_variant and means.shape[0] == self.num_policies:
            weights = self._policy_weights()
        else:
            weights = self.dp_state.counts.to(DTYPE).clamp_min(1.0)
        return GaussianMixture(weights, means, covs, validate_args=False)

    @property
    def policy_rewards(self) -> Tensor:
        """``[K]`` the return the mixture predicts at each policy's mean (r_c of eq. 6)."""
        mixture = self.mixture
        return mixture.condition(range(self.dim), self.policy_means).mean[..., 0]

    # ------------------------------------------------------------------ checkpoints
    _TENSORS = (*PolicySearch._TENSORS, "success", "paths")

    def state_dict(self) -> dict:
        state = super().state_dict()
        state["initial_prior"] = (
            None if self.initial_prior is None else self.initial_prior.state_dict()
        )
        state["dp_state"] = None if self.dp_state is None else self.dp_state.state_dict()
        state["clusterings_skipped"] = self.clusterings_skipped
        return state

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        prior = _to_device(state["initial_prior"], self.device)
        self.initial_prior = (
            None if prior is None else NormalInverseWishartPrior.from_state_dict(prior)
        )
        dp = _to_device(state["dp_state"], self.device)
        self.dp_state = None if dp is None else DPMixtureState.from_state_dict(dp)
        self.clusterings_skipped = int(state.get("clusterings_skipped", 0))


def _to_device(state, device: torch.device):
    """``state`` (nested dicts of tensors and numbers, or None) with its tensors on ``device``."""
    if isinstance(state, dict):
        return {key: _to_device(value, device) for key, value in state.items()}
    return state.to(device) if isinstance(state, Tensor) else state


__all__ = ["Dipole", "Power", "PolicySearch"]
