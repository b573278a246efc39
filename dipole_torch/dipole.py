"""DIPOLE (Algorithm 2 of the paper): PoWER on every component of a reward-weighted DP mixture."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from dipole_torch.archive import PROBE
from dipole_torch.dp.conditionals import check_estimate, posterior_point_estimate
from dipole_torch.dp.sampler import DPSampler
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE
from dipole_torch.inputs import Bounds, SigmaStart, Theta0
from dipole_torch.mechanisms.exploration import make_exploration
from dipole_torch.mechanisms.hill_valley import make_vetting
from dipole_torch.mechanisms.matching import OverlapMatching, ReplaceMatching, adopt_components
from dipole_torch.mechanisms.retirement import Retirement
from dipole_torch.mechanisms.scouting import Scouting
from dipole_torch.options import DipoleOptions
from dipole_torch.power import make_importance
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.search import PolicySearch
from dipole_torch.tell_batch import TellBatch

if TYPE_CHECKING:  # a Pyro distribution: Pyro is imported when a mixture is built
    from dipole_torch.gaussian_mixture import GaussianMixture

__all__ = ["Dipole"]

# auxiliary="auto" re-uses auxiliary draws from this dimension p = D + 1 of [θ, r] on, where
# Algorithm 8's N·m inverse-Wishart draws of p × p are most of a clustering. Below it, fresh
# draws: m new proposals at every point open new components (new policies) in fewer sweeps
# than m slots shared by all points (measured on the viapoint routes, docs Speed).
REUSE_AUXILIARY_DIM = 32

# A clustering that meets these is skipped: a factorisation of a numerically singular
# covariance, or a label whose every probability underflowed to 0.
NUMERICAL_FAILURES = (torch.linalg.LinAlgError, FloatingPointError)


class Dipole(PolicySearch):
    """DIPOLE (Algorithm 2): PoWER on every component of a reward-weighted DP mixture.

    * ``ask()``: first ``n0`` samples from N(θ0, Σ_start); then one sample per sampled policy
      from its exploration Gaussian, and any scouts and hill-valley probes
      (``asked_owner`` says which row is which).
    * ``tell()``: the PoWER step (eq. 7) of every policy on its importance set; after the
      initial batch and every ``cluster_every`` iterations, a weighted DP clustering (eq. 6,
      Neal's Algorithm 8) of the kept samples, augmented with their reward weights
      y = [θ, w], redefines the policies.

    The options (``DipoleOptions``: keyword arguments, or ``options=``)
    choose one object per mechanism, and the core below calls them at fixed points of an
    iteration: the importance sets (``dipole_torch.power``), exploration
    (``exploration``), scouting and turn-taking
    (``scouting``), hill-valley vetting
    (``hill_valley``), retirement, merging and restarts
    (``retirement``), and matching components to policies
    (``matching``). ``paper`` builds the paper's set.

    >>> opt = Dipole([0.0, 0.0], 0.7, generator=torch.Generator().manual_seed(0))
    >>> while not opt.stop(max_trials=300):
    ...     theta = opt.ask()
    ...     opt.tell(theta, -100.0 * (theta - 1.0).pow(2).sum(-1))  # any units, no range
    >>> bool(opt.best()[1] > -1e-3)
    True

    Args:
        theta0: ``[D]`` initial policy (a tensor, a list or a numpy array).
        sigma_start: initial exploration: one std σ (σ² I), ``[D]`` stds or a ``[D, D]``
            covariance Σ_start.
        options: a ``DipoleOptions`` (default: the library's variant).
        generator: ``torch.Generator`` for every draw (default: seeded from torch's global
            generator).
        bounds: ``(lower, upper)`` box of the parameters (numbers, lists of D numbers or
            ``[D]`` tensors; ±inf leaves a side open), or ``None``.
        **changes: options to change (``alpha``, ``M``, ``explore``, …; see
            ``DipoleOptions``).

    Choices where the paper is silent:
        * The prior H is built at the first clustering from the exploration distribution:
          μ0 = [θ0, mean w], Σ0 = E[Σ] = blockdiag(Σ_start, var w) (var w floored at 1 % of
          the largest weight squared), ν0 = ``prior_df`` (default D + 3 = p + 2 for the
          p = D + 1 dimensions of y: the weakest inverse-Wishart prior with a finite mean).
          It is carried from clustering to clustering, updated after every sweep.
        * A clustering ends with the conditional posterior means of the last Gibbs state
          (``posterior_point_estimate``).
        * r_c in eq. 6 is E[w | θ = μ_c^θ] under the mixture at the start of each sweep.
    """

    def __init__(
        self,
        theta0: Theta0,
        sigma_start: SigmaStart,
        options: DipoleOptions | None = None,
        *,
        generator: torch.Generator | None = None,
        bounds: Bounds = None,
        **changes: Any,
    ):
        if options is not None and not isinstance(options, DipoleOptions):
            raise TypeError(
                f"options must be a DipoleOptions, got {type(options).__name__} (single "
                "options are keyword arguments: Dipole(theta0, sigma_start, M=3))"
            )
        options = (options or DipoleOptions()).replace(**changes)
        n0 = 2 * options.M if options.n0 is None else options.n0
        super().__init__(
            theta0, sigma_start, options.M, n0, options.reward_range, options.reward_floor,
            generator, bounds,
        )  # fmt: skip
        self.options = options
        self.repeats.evaluations = options.best_evaluations
        d = self.dim
        self.cluster_every = options.M if options.cluster_every is None else options.cluster_every
        self.prior_df = float(d + 3 if options.prior_df is None else options.prior_df)
        if not self.prior_df > d + 2:
            raise ValueError(f"prior_df must exceed D + 2 = {d + 2}, got {options.prior_df}")
        if options.auxiliary == "reuse" and self.device.type != "cpu":
            raise ValueError(
                f"auxiliary='reuse' runs on the CPU only; on {self.device} use 'fresh' or 'auto'"
            )
        reuse = options.auxiliary == "reuse" or (
            options.auxiliary == "auto"
            and d + 1 >= REUSE_AUXILIARY_DIM
            and self.device.type == "cpu"
        )
        self.auxiliary = "reuse" if reuse else "fresh"
        # Active policies at most (the cap the clusterings and the hill-valley test keep):
        # ``coverage_max_policies`` from ``coverage_from`` on.
        self.max_policies = options.max_policies
        # The mechanisms, one object each ("off" is an object too).
        self.importance = make_importance(options.importance)
        self.exploration = make_exploration(options.exploration, d, options.success_target)
        self.scouting = Scouting(
            options.explore, options.max_sampled, options.restarts, options.unjudged_share
        )
        self.vetting = make_vetting(
            options.hill_valley, d, self.device, options.pair_points, self.cluster_every,
            options.accept_unjudged, options.marks_unjudged,
        )  # fmt: skip
        self.retirement = Retirement(
            options.retire_std, options.merge_radius, self.exploration.keeps_covariance,
            options.refine, options.refine_share, options.retire_spread, options.refine_gate,
            options.wake_while_active,
        )  # fmt: skip
        self.matching = (
            ReplaceMatching()
            if options.matching == "replace"
            else OverlapMatching(options.start_cap)
        )
        self.exploration.register(self)
        self.matching.register(self)
        self.retirement.register(self)
        self.vetting.register(self)
        self.clusterings_skipped = 0  # clusterings that failed numerically
        self.sampler: DPSampler | None = None  # built with H at the first clustering
        self.dp_state: DPMixtureState | None = None

    @classmethod
    def paper(cls, theta0: Theta0, sigma_start: SigmaStart, **changes: Any) -> Dipole:
        """DIPOLE exactly as in the paper (``DipoleOptions.paper``), then ``changes``."""
        if "options" in changes:  # (DipoleOptions' own error named no such option)
            raise TypeError(
                "Dipole.paper sets the options itself (the paper's, then the changes given as "
                "keywords); for options of your own, Dipole(theta0, sigma_start, options)"
            )
        generator, bounds = changes.pop("generator", None), changes.pop("bounds", None)
        return cls(theta0, sigma_start, DipoleOptions.paper(**changes),
                   generator=generator, bounds=bounds)  # fmt: skip

    @property
    def initial_prior(self) -> NormalInverseWishartPrior | None:
        """H as the first clustering built it (``None`` before)."""
        return None if self.sampler is None else self.sampler.prior

    @property
    def converged(self) -> Tensor:
        """``[K]`` whether each policy has converged for good: its exploration std is below
        its retirement threshold and no wake could refine it further (with ``refine > 0``, a
        retired policy is woken while trials remain, so a run's ``stop()`` says
        ``"converged"`` only once θ or the returns are resolved to rounding)."""
        return self.retirement.final(self)

    @property
    def clustered_policies(self) -> Tensor:
        """``[K]`` the policies whose samples a clustering sees (``matching="overlap"``): the
        active ones but for those woken to refine, whose own exploration alone moves them
        (``Waking``)."""
        return self.active & ~self.retirement.refining(self)

    # ------------------------------------------------------------------ ask
    def _batch_size(self) -> int:
        # The options the next ask draws under: the batch read at coverage_from's trial, before
        # that ask, was the one before covering (train.py cut the first covering batch to it,
        # and a run resumed at that trial, whose load switches, did not).
        self._cover_from_trial()
        sampled = (
            self.scouting.sampled_policies(self).numel() if self.policy_set.any_active() else 0
        )
        probes = self.vetting.probes()
        return (
            sampled
            + self.scouting.scouts(self, sampled)
            + (0 if probes is None else probes.shape[0])
        )

    def _sampled_policies(self) -> Tensor:
        return self.scouting.sampled_policies(self)

    def _cover_from_trial(self) -> None:
        """With ``coverage_from``: for the batches asked from that trial on, the candidates
        the probe cannot judge are accepted, every active policy is sampled and
        ``coverage_max_policies`` caps the active ones; before it, the options as set. Set
        from the trial count at each ask and each ``batch_size`` read (which counts the rows
        of that ask), and at load (so a resumed run switches as it ran), and kept through the
        batch's tell: a run whose batches were all asked before the
        trial is the run without the option, draw for draw."""
        start = self.options.coverage_from
        if start is None:
            return
        covering = self.trials >= start
        self.vetting.accept_unjudged = covering or self.options.accept_unjudged
        self.scouting.max_sampled = None if covering else self.options.max_sampled
        cap = self.options.coverage_max_policies
        self.max_policies = cap if covering and cap is not None else self.options.max_policies

    def _propose(self) -> tuple[Tensor, Tensor]:
        """Policy samples, then scouts, then hill-valley probes."""
        self._cover_from_trial()
        if self.policy_set.any_active():
            theta, owner = super()._propose()
        else:
            theta, owner = self.archive.thetas[:0], self.archive.owner[:0]
        scouts = self.scouting.scouts(self, theta.shape[0])
        if scouts:
            extra, extra_owner = self.scouting.draw_scouts(self, scouts)
            theta, owner = torch.cat((theta, extra)), torch.cat((owner, extra_owner))
        probes = self.vetting.probes()
        if probes is not None:
            theta = torch.cat((theta, probes))
            owner = torch.cat((owner, torch.full_like(probes[:, 0], PROBE, dtype=torch.long)))
        return theta, owner

    # ------------------------------------------------------------------ tell
    def _observe(self, batch: TellBatch) -> None:
        """Before the samples are archived: the success rule judges them against the kept
        ones, retirement notes the samples worse than all kept ones, vetting keeps the
        probes' returns."""
        self.vetting.observe(self, batch)
        self.scouting.observe(self, batch)
        self.exploration.observe(self, batch)
        self.retirement.observe(self, batch)

    def _iterate(self) -> None:
        """One iteration of Algorithm 2 after the samples are told."""
        self.importance.power_step(self)  # eq. 7 on each policy's importance set
        self.retirement.restart_straddlers(self)  # while policies are numbered as told
        self.vetting.judge(self)  # the probes told in this batch
        restart = not self.policy_set.any_active()  # every policy retired: cluster the scouts
        clustered = restart or self.iteration % self.cluster_every == 0
        if clustered:
            self._cluster()
        self.retirement.retire_and_merge(self)
        self.vetting.queue_probes(self, clustered)
        self.retirement.wake(self)  # every policy retired: refine them further, or restart

    # ------------------------------------------------------------------ clustering
    def _augmented(self, rows: Tensor | None = None) -> Tensor:
        """``[N, D + 1]`` the kept samples (or ``rows`` of them) as y = [θ, w]."""
        rewards = self.archive.rewards
        w = self.reward_scale.weights(rewards, reference=rewards)
        if rows is not None:
            return torch.cat((self.archive.thetas[rows], w[rows, None]), dim=1)
        return torch.cat((self.archive.thetas, w[:, None]), dim=1)

    def _fit(self, y: Tensor, sweeps: int, start: DPMixtureState | None = None) -> DPMixtureState:
        """``sweeps`` Gibbs sweeps of the weighted DP mixture on ``y`` from ``start`` (or
        Algorithm 1's single component), ending with the posterior point estimate. A
        warm start ends early once its partition settles (``settle``)."""
        settle = None if start is None else self.options.settle
        state = self.sampler.fit(y, sweeps, self.generator, start, settle=settle)
        spread = self.sampler.prior.mean_covariance.diagonal().sqrt()
        return check_estimate(y, posterior_point_estimate(y, state), spread)

    def _after_initial_batch(self) -> None:
        """Build H from the exploration distribution, cluster the n0 samples (from one
        component) and make the components the policies."""
        y = self._augmented()
        w = y[:, -1]
        var_w = float(w.var()) if w.numel() > 1 else 0.0
        mean = torch.cat((self.theta0, w.mean()[None]))
        # Floor the prior's reward variance relative to the weights' own scale (positive
        # returns used as weights may be of any order).
        floor = 1e-2 * float(w.abs().max()) ** 2
        reward_variance = torch.tensor([[max(var_w, floor)]], dtype=DTYPE, device=self.device)
        prior = NormalInverseWishartPrior.from_exploration(
            mean,
            torch.block_diag(self.sigma_start, reward_variance),
            df=self.prior_df,
            regularization=self.options.regularization,
        )
        self.sampler = self._sampler(prior)
        try:
            state = self._fit(y, self.options.initial_sweeps)
        except NUMERICAL_FAILURES:
            # See _cluster: start from Algorithm 1's single component instead.
            self.clusterings_skipped += 1
            state = posterior_point_estimate(y, DPMixtureState.single_component(y, prior))
        self.matching.adopted(self, adopt_components(self, state))

    def _cluster(self) -> None:
        """Algorithm 2's weighted DP clustering, warm-started, its result matched to the
        policies (``matching`` decides which samples, the start, and the matching)."""
        rows = self.matching.clustered_rows(self)
        if rows.numel() == 0:
            return
        y = self._augmented(rows)
        try:
            state = self._fit(y, self._sweeps(rows), self.matching.warm_start(self, y, rows))
        except NUMERICAL_FAILURES:
            # Converged policies' samples can make a component's covariance numerically
            # singular in float64. A run that goes well must not stop: skip this clustering
            # (the policies go on with their own exploration) and forget the scouts.
            self.clusterings_skipped += 1
            self.archive.keep(self.archive.owner >= 0)
            return
        self.matching.apply(self, rows, y, state)

    def _sweeps(self, rows: Tensor) -> int:
        """The sweeps of a warm-started clustering of ``rows``: ``scout_sweeps`` when they
        are scouts alone, else ``sweeps``.

        Scouts alone are clustered when every policy has retired (a restart) or is woken to
        refine: the chain starts from one component per scout, and its components are only
        candidates for the hill-valley probes, which decide what becomes a policy. Such a
        partition of fresh scouts rarely settles, so it ran all ``sweeps``, the largest
        cost of a long low-dimensional run; one sweep found as many optima (not in the
        paper, which has no scouts; docs: Speed)."""
        scouts_only = self.options.scout_sweeps is not None and not bool(
            (self.archive.owner[rows] >= 0).any()
        )
        return self.options.scout_sweeps if scouts_only else self.options.sweeps

    # ------------------------------------------------------------------ the world changes
    def _reevaluate(self, returns: Tensor) -> None:
        self.vetting.forget()  # queued tests compare returns of the old world
        self.retirement.forget()
        super()._reevaluate(returns)

    # ------------------------------------------------------------------ the model
    @property
    def mixture(self) -> GaussianMixture:
        """The IGMM over [θ, r] of the last clustering, with the policies' current means,
        r in return units, in float64 whatever ``theta0``'s dtype (the model's own numbers;
        ``policies`` is in ``theta0``'s).

        ``mixture.condition(range(D), theta).mean`` predicts the return of ``theta``;
        ``mixture.condition([D], r)`` is the distribution of policies given a return level.
        Components are the last clustering's; with ``matching="overlap"`` policies created
        or merged since then are not in it.
        """
        if self.dp_state is None:
            raise RuntimeError("the mixture exists after the first tell()")
        rewards = self.archive.rewards
        scale = torch.ones(self.dim + 1, dtype=DTYPE, device=self.device)
        scale[-1] = self.reward_scale.slope(rewards)
        means = self.dp_state.means.clone()
        current = isinstance(self.matching, ReplaceMatching)
        current = current and means.shape[0] == self.num_policies
        if current:  # the components are the policies: at their current means
            means[:, : self.dim] = self.policy_means
        means[:, -1] = self.reward_scale.inverse(means[:, -1], rewards)
        covs = self.dp_state.covariances * scale[:, None] * scale[None, :]
        if current:
            weights = self.archive.counts(self.num_policies).to(DTYPE).clamp_min(1.0)
        else:
            weights = self.dp_state.counts.to(DTYPE).clamp_min(1.0)
        from dipole_torch.gaussian_mixture import GaussianMixture

        return GaussianMixture(weights, means, covs, validate_args=False)

    @property
    def policy_rewards(self) -> Tensor:
        """``[K]`` the return the mixture predicts at each policy's mean (r_c of eq. 6)."""
        return self.mixture.condition(range(self.dim), self.policy_means).mean[..., 0]

    def _sampler(self, prior: NormalInverseWishartPrior) -> DPSampler:
        """The DP mixture's sampler (Algorithm 3) with the options' α, m and eq. 6 switch."""
        return DPSampler(
            prior,
            alpha=self.options.alpha,
            m=self.options.m,
            reward_weighted=self.options.reward_weighted,
            auxiliary=self.auxiliary,
        )

    # ------------------------------------------------------------------ checkpoints
    def _settings(self) -> dict[str, Any]:
        """The base's settings (M, n0 and the reward scale as they take effect), and every
        other option as given."""
        return {**dataclasses.asdict(self.options), **super()._settings()}

    def _state(self, copy: bool) -> dict:
        # (H and the DP state are kept as they are, copied or not: neither is ever changed,
        # a clustering makes new ones.)
        return {
            **super()._state(copy),
            **self.vetting.state_dict(copy),
            **self.retirement.state_dict(),
            **self.scouting.state_dict(),
            "initial_prior": None if self.sampler is None else self.sampler.prior.state_dict(),
            "dp_state": None if self.dp_state is None else self.dp_state.state_dict(),
            "clusterings_skipped": self.clusterings_skipped,
        }

    def _load_state_dict(self, state: dict) -> None:
        super()._load_state_dict(state)
        try:
            self.vetting.load_state_dict(state, self.device)
            self.retirement.load_state_dict(state)
            self.scouting.load_state_dict(state)
            prior, dp = (
                _to_device(state[key], self.device) for key in ("initial_prior", "dp_state")
            )
        except KeyError as missing:
            raise ValueError(f"state_dict has no {missing} (not a Dipole's)") from None
        self.sampler = None
        if prior is not None:
            prior = NormalInverseWishartPrior.from_state_dict(prior)
            if prior.dim != self.dim + 1:
                raise ValueError(
                    f"state_dict['initial_prior'] is over {prior.dim} dimensions, not D + 1 = "
                    f"{self.dim + 1}"
                )
            self.sampler = self._sampler(prior)
        self.dp_state = None if dp is None else DPMixtureState.from_state_dict(dp)
        if self.dp_state is not None:
            self.dp_state.check(self.dim + 1, name="state_dict['dp_state']")
        self.clusterings_skipped = int(state.get("clusterings_skipped", 0))
        self._cover_from_trial()


def _to_device(state, device: torch.device):
    """``state`` (nested dicts of tensors and numbers, or None) with its tensors on ``device``."""
    if isinstance(state, dict):
        return {key: _to_device(value, device) for key, value in state.items()}
    return state.to(device) if isinstance(state, Tensor) else state
