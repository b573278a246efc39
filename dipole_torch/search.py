"""The ask/tell policy search that DIPOLE and PoWER share.

pycma's interface: ``ask()`` proposes policy parameters, the caller evaluates them however it
likes (batched simulator, gymnasium env, real robot) and ``tell()`` reports the returns. The
optimizer never calls the task and needs no range of the returns.
"""

from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from dipole_torch.archive import NO_POLICY, PROBE, REPEAT, SampleArchive
from dipole_torch.gaussian import DTYPE
from dipole_torch.inputs import (
    Bounds,
    SigmaStart,
    Theta0,
    as_covariance,
    as_theta0,
    check_asked,
    check_in_box,
    into_box,
    make_box,
    told_as_asked,
)
from dipole_torch.policy_set import PolicySet
from dipole_torch.repeats import RepeatedEvaluations
from dipole_torch.result import SearchResult
from dipole_torch.reward import RewardRange, check_rewards, make_reward_scale
from dipole_torch.sampling import draw_gaussian
from dipole_torch.settings import setting_differences
from dipole_torch.tell_batch import TellBatch
from dipole_torch.validation import (
    check_count,
    check_finite,
    check_generator,
    check_matrix_shape,
    check_real_tensor,
)

if TYPE_CHECKING:  # a Pyro distribution: Pyro is imported when a mixture is built
    from dipole_torch.gaussian_mixture import GaussianMixture

__all__ = ["NO_POLICY", "PROBE", "REPEAT", "PolicySearch", "TellBatch"]


class PolicySearch:
    """Ask/tell over a ``PolicySet`` and a
    ``SampleArchive``: proposals, the transactional tell, the box,
    best-so-far, results and checkpoints. Subclasses decide what an ask proposes and what a
    tell changes (``_propose``, ``_observe``, ``_after_initial_batch``,
    ``_iterate``).

    Internal maths run in float64 on ``theta0``'s device; ``ask`` returns ``theta0``'s dtype
    (float64 for a list). ``tell`` is transactional: if it raises, the optimizer is exactly as
    before the call.

    With ``bounds = (lower, upper)`` every asked row is projected onto the box (each
    coordinate clipped), a told row outside it raises, and the policy means stay inside.
    Clipping, not resampling or reflection, so that an optimum on the boundary (a joint
    limit) is sampled exactly; θ0 must lie in the box.

    Args:
        theta0: ``[D]`` initial policy: a floating tensor, a list or a numpy array.
        sigma_start: initial exploration: one std σ (σ² I), ``[D]`` stds or a ``[D, D]``
            covariance.
        M: importance-set size (a checked positive integer).
        n0: initial samples (a checked positive integer).
        reward_range: ``None``, ``(low, high)`` or ``"positive"`` (see
            ``dipole_torch.RewardScale``).
        reward_floor: smallest reward weight.
        generator: ``torch.Generator`` for every draw (default: seeded from torch's global
            generator, as torch's own samplers follow ``torch.manual_seed``).
        bounds: ``(lower, upper)``, each a number, a list of D numbers, a numpy array or a
            ``[D]`` tensor (±inf leaves a side open), or ``None``.

    Attributes:
        trials: reward evaluations told so far (the x-axis of the paper's plots).
        iteration: tells after the first batch.
        policy_samples: trials spent on policy samples after the first batch.
        last_rewards: ``[K]`` each policy's latest return, for the curves of the paper's
            figures (their max and mean): the returns of the latest told batch's policy
            samples (the whole batch after the first tell), then, for each policy that drew
            no sample in it, the mean return of its kept samples. In that order, and for the
            policies of the batch's ask (the tell's clustering may add or drop some): not
            row by row those of ``policy_means``, but after ``reevaluate``, where it is the
            returns told. Per policy, row by row: ``policy_best_rewards``.
    """

    def __init__(
        self,
        theta0: Theta0,
        sigma_start: SigmaStart,
        M: int,
        n0: int,
        reward_range: RewardRange,
        reward_floor: float,
        generator: torch.Generator | None,
        bounds: Bounds,
    ):
        theta0 = as_theta0(theta0)
        sigma = as_covariance(sigma_start, theta0)
        check_generator(generator)
        self.dtype = theta0.dtype
        self.device = theta0.device
        self.theta0 = theta0.to(DTYPE, copy=True)  # a copy: the caller's edits leave it be
        self.sigma_start = sigma
        self._start_variances = sigma.diagonal()  # [D] (a view: it follows Σ_start)
        self.box = make_box(bounds, self.theta0)
        self.M = int(M)
        self.n0 = int(n0)
        self.reward_scale = make_reward_scale(reward_range, reward_floor)
        if generator is None:
            generator = torch.Generator(self.device)
            generator.manual_seed(int(torch.randint(0, 2**62, (1,))))
        self.generator = generator
        self.archive = SampleArchive(self.dim, self.device)
        self.policy_set = PolicySet(self.theta0[None].clone(), self.sigma_start[None].clone())
        self.trials = 0
        self.iteration = 0
        self.policy_samples = 0
        self.last_rewards = torch.empty(0, dtype=DTYPE, device=self.device)
        self._best_theta = self.theta0.clone()
        self._best_reward = -math.inf
        self._pending: Tensor | None = None
        self._pending_owner: Tensor | None = None
        self._pending_boxed = False  # the pending rows were projected by this ask (not loaded)
        # Kept samples evaluated again (a subclass sets their number from its options).
        self.repeats = RepeatedEvaluations()

    # ------------------------------------------------------------------ views
    @property
    def dim(self) -> int:
        return int(self.theta0.shape[0])

    @property
    def num_policies(self) -> int:
        return len(self.policy_set)

    @property
    def started(self) -> bool:
        return self.trials > 0

    @property
    def policy_means(self) -> Tensor:
        """``[K, D]`` the policies' means (float64). This and the properties below are the
        optimizer's own tensors, as a module's parameters are, not copies: editing one in
        place edits the run (``.clone()`` to keep or change one; ``result`` is a snapshot)."""
        return self.policy_set.means

    @property
    def policy_covariances(self) -> Tensor:
        """``[K, D, D]`` the policies' exploration covariances (float64; not a copy)."""
        return self.policy_set.covariances

    @property
    def active(self) -> Tensor:
        """``[K]`` which policies are still sampled (not a copy)."""
        return self.policy_set.active

    @property
    def thetas(self) -> Tensor:
        """``[N, D]`` the kept samples (float64; not a copy)."""
        return self.archive.thetas

    @property
    def rewards(self) -> Tensor:
        """``[N]`` the kept samples' returns (float64; not a copy)."""
        return self.archive.rewards

    @property
    def owner(self) -> Tensor:
        """``[N]`` the policy owning each kept sample (−1: a scout of no policy yet; not a
        copy)."""
        return self.archive.owner

    @property
    def policy_best_rewards(self) -> Tensor:
        """``[K]`` the best return among each policy's kept samples (−inf: none)."""
        return self.archive.per_policy("amax", self.num_policies)

    @property
    def converged(self) -> Tensor:
        """``[K]`` whether each policy's exploration has converged (PoWER's never does: its
        exploration is fixed or follows a schedule)."""
        return torch.zeros(self.num_policies, dtype=torch.bool, device=self.device)

    def relative_std(self, covariances: Tensor | None = None) -> Tensor:
        """``[K]`` each policy's largest exploration std relative to Σ_start's, per axis
        (or that of ``covariances [..., D, D]``)."""
        covs = self.policy_covariances if covariances is None else covariances
        ratio = covs.diagonal(dim1=-2, dim2=-1) / self._start_variances
        return ratio.amax(-1).sqrt()

    @property
    def policies(self) -> GaussianMixture:
        """The current policies as a mixture over θ: component k is N(θ_k, Σ_k), weighted by
        the number of kept samples it owns (at least 1), in ``theta0``'s dtype (float32 for
        a half-precision ``theta0``: a mixture's factorisations need float32 at least).

        The covariances are factorised in float64 before the cast: a converged policy's
        exploration can be too ill-conditioned for a float32 Cholesky."""
        weights = self.archive.counts(self.num_policies).to(DTYPE).clamp_min(1.0)
        from dipole_torch.gaussian_mixture import GaussianMixture

        mixture = GaussianMixture(  # on copies: editing it leaves the run be
            weights, self.policy_means.clone(), self.policy_covariances.clone(), validate_args=False
        )
        dtype = self.dtype if torch.finfo(self.dtype).bits >= 32 else torch.float32
        if dtype != DTYPE:
            mixture.scale_tril  # noqa: B018 (factorised here, carried by .to())
        return mixture.to(dtype)

    def best(self) -> tuple[Tensor, float]:
        """The best parameters evaluated so far and their return: ``([D], float)``.

        With ``best_evaluations`` > 1 on returns the repeats found noisy, the best sample
        whose return averages ``best_evaluations`` returns, with that mean, once one does
        (``RepeatedEvaluations.best``): the best single return told would be the luckiest.
        Otherwise (and until then) the best single return told."""
        averaged = self.repeats.best_averaged
        theta, value = (self._best_theta, self._best_reward) if averaged is None else averaged
        return theta.to(self.dtype, copy=True), value  # a copy: editing it leaves the run be

    def stop(self, max_trials: int | None = None) -> dict[str, str]:
        """The stopping criteria met (pycma's ``stop()``): empty while the run should go on.

        ``"max_trials"`` once ``trials >= max_trials`` (a budget you pass), ``"converged"``
        once every policy's exploration has converged. A run may go on after either.
        ``max_trials`` must be a whole number >= 0 or ``None`` (a NaN would never be met)."""
        check_count(max_trials, "max_trials", minimum=0, optional=True)
        met = {}
        if max_trials is not None and self.trials >= max_trials:
            met["max_trials"] = f"{self.trials} trials of {max_trials}"
        if self.started and self.num_policies and bool(self.converged.all()):
            met["converged"] = f"every one of the {self.num_policies} policies"
        return met

    @property
    def result(self) -> SearchResult:
        """Where the run stands: the best evaluation and every policy (see
        ``SearchResult``; ``print`` it for a summary)."""
        best_theta, best_reward = self.best()
        return SearchResult(
            best_theta=best_theta,
            best_reward=best_reward,
            trials=self.trials,
            iterations=self.iteration,
            means=self.policy_means.to(self.dtype, copy=True),  # copies: a snapshot
            covariances=self.policy_covariances.to(self.dtype, copy=True),
            best_rewards=self.policy_best_rewards.clone(),
            active=self.active.clone(),
            converged=self.converged.clone(),
            ids=self.policy_set.ids.clone(),
            best_evaluations=self.repeats.reported_evaluations,
        )

    def __getstate__(self) -> dict:
        """For ``copy.deepcopy`` and ``pickle``: the generator as its device and state (torch
        2.3's ``torch.Generator`` does not pickle); the copy draws what this would."""
        state = self.__dict__.copy()
        generator = state.pop("generator")
        state["_generator"] = (str(generator.device), generator.get_state())
        return state

    def __setstate__(self, state: dict) -> None:
        device, generator_state = state.pop("_generator")
        generator = torch.Generator(device)
        generator.set_state(generator_state)
        self.__dict__.update(state)
        self.generator = generator

    # ------------------------------------------------------------------ ask
    @property
    def batch_size(self) -> int:
        """Rows the next ``ask`` returns (before ``max_rows``): known before the draw,
        so a run can decide whether the next batch fits its trial budget."""
        if not self.started:
            return self.n0
        size = self._batch_size()
        if self.repeats.evaluations > 1:
            sampled = self._sampled_policies().tolist()
            size += len(self.repeats.rows(self.archive, sampled, self.num_policies))
        return size

    def _batch_size(self) -> int:
        return int(self._sampled_policies().numel())

    def ask(self, max_rows: int | None = None) -> Tensor:
        """Policy parameters to evaluate next.

        Args:
            max_rows: return only the first ``max_rows`` rows of the batch (e.g. to end a run
                exactly at a trial budget); the draws are those of the whole batch, and
                ``tell`` takes the rows returned.

        Returns:
            ``[n0, D]`` draws from N(θ0, Σ_start) on the first call; afterwards ``[B, D]``:
            one row per sampled policy, drawn from its Gaussian, then any exploration rows
            (see ``asked_owner``). Asking again before telling discards the previous
            proposal, with a warning.
        """
        check_count(max_rows, "max_rows", optional=True)
        if self._pending is not None:
            warnings.warn(
                "ask() again before tell(): the pending proposal is discarded (its draws are "
                "spent); tell() each ask's returns to learn from them",
                stacklevel=2,
            )
        if not self.started:
            theta = draw_gaussian(self.theta0, self.sigma_start, (self.n0,), self.generator)
            owner = torch.zeros(self.n0, dtype=torch.long, device=self.device)
        else:
            theta, owner = self._propose()
        self.repeats.pending = None
        if self.started and self.repeats.evaluations > 1:
            theta, owner = self.repeats.extend(self.archive, theta, owner, self.num_policies)
        theta = into_box(self.box, theta)
        self._pending, self._pending_owner = theta, owner
        self._pending_boxed = True
        if max_rows is not None:
            theta = theta[: int(max_rows)]
        # A copy: rows edited in place must not edit the pending ones that tell checks against.
        return theta.to(self.dtype, copy=True)

    @property
    def asked_owner(self) -> Tensor | None:
        """``[B]`` the policy each row of the pending ask belongs to (−1: a scout of no
        policy yet, −2: a probe, −3: a kept sample evaluated again; see
        ``dipole_torch.archive``)."""
        return self._pending_owner

    def _propose(self) -> tuple[Tensor, Tensor]:
        """The next batch after the first: ``(theta [B, D], owner [B])``. Here one sample
        per sampled policy."""
        index = self._sampled_policies()
        if index.numel() == self.num_policies:
            means, covs = self.policy_means, self.policy_covariances
        else:
            means, covs = self.policy_means[index], self.policy_covariances[index]
        return draw_gaussian(means, covs, (), self.generator), index

    def _sampled_policies(self) -> Tensor:
        """``[K_sampled]`` the policies that draw a sample at the next ask: the active ones."""
        return self.active.nonzero().squeeze(-1)

    # ------------------------------------------------------------------ tell
    def tell(self, theta: Tensor, rewards: Tensor) -> None:
        """Report the returns of the parameters from the last ``ask``.

        Args:
            theta: ``[B, D]`` the asked parameters (row i as asked; the tensor ``ask``
                returned, or its numpy array), or only the first ``n < B`` rows of the ask
                (e.g. to end a run exactly at a trial budget).
            rewards: ``[B]`` (or ``[n]``) their returns; all finite (a NaN or inf raises
                before anything changes), inside ``reward_range`` when a fixed one was given.

        If anything raises, the optimizer is left exactly as it was before the call.
        """
        if self._pending is None:
            raise RuntimeError(
                "tell() called without a pending ask(): each ask is told once (a tell of its "
                "first n rows discards the others, and reevaluate() an ask not yet told); "
                "ask() again"
            )
        asked, d = self._pending.shape
        if isinstance(theta, np.ndarray):  # the asked tensor as numpy (ask().numpy())
            theta = torch.from_numpy(theta)
        elif not isinstance(theta, Tensor):
            raise TypeError(
                f"theta must be the rows ask() returned (a tensor, or the numpy array of "
                f"one), got {type(theta).__name__}"
            )
        check_matrix_shape(theta, (-1, d), "theta")
        check_real_tensor(theta, "theta")  # an integer θ equals the asked rows cast to it
        if not 1 <= theta.shape[0] <= asked:
            raise ValueError(
                f"theta has {theta.shape[0]} rows: tell() takes the {asked} rows of the last "
                f"ask, or its first n (1 <= n <= {asked})"
            )
        check_finite(theta, "theta")
        # Rows told as this optimizer asked them lie in its box: one comparison checks both.
        if not (self._pending_boxed and told_as_asked(self._pending, theta, self.dtype)):
            check_in_box(self.box, theta)
            check_asked(self._pending, theta, self.dtype)
        rewards = check_rewards(rewards, theta.shape[0], "asked θ").to(self.device)
        self.reward_scale.check_range(rewards, first=not self.started)  # before any change
        theta = into_box(self.box, theta.detach().to(device=self.device, dtype=DTYPE))
        snapshot = self._snapshot()
        try:
            self._tell(theta, rewards)
            if self.box is not None:
                # Eq. 7's means are convex combinations of samples in the box, but the
                # posterior means of the paper's DIPOLE weigh them by matrices.
                self.policy_set.means = into_box(self.box, self.policy_means)
        except BaseException:
            self._load_state_dict(snapshot)
            raise

    def _tell(self, theta: Tensor, rewards: Tensor) -> None:
        first = not self.started
        owner = self._pending_owner[: theta.shape[0]]
        batch = TellBatch(theta, rewards, owner, cut=owner.shape[0] < self._pending_owner.shape[0])
        self._pending = self._pending_owner = None
        if self.repeats.pending is not None:  # before the samples are judged against them
            self.repeats.tell(self.archive, rewards[batch.probe_end :])
        self._observe(batch)
        policy_rows = batch.policy_rows
        self.policy_samples += policy_rows if not first else 0
        samples = batch.sample_rows  # probes are evaluations, not samples
        if samples == theta.shape[0]:
            self.archive.append(theta, rewards, owner)
        else:
            self.archive.append(theta[:samples], rewards[:samples], owner[:samples])
        self.trials += theta.shape[0]
        k = self.num_policies
        if first:
            self.last_rewards = rewards.clone()  # not the caller's tensor
        elif batch.every_policy(k):
            self.last_rewards = rewards[:policy_rows].clone()
        else:
            # Each policy's latest return: the sampled ones' new returns; a policy that drew
            # no sample keeps the mean return of its kept samples.
            sampled = torch.zeros(k, dtype=torch.bool, device=self.device)
            sampled[owner[:policy_rows]] = True
            held = self.archive.mean_rewards(k)[~sampled]
            self.last_rewards = torch.cat((rewards[:policy_rows], held))
        values = rewards.tolist()
        best = max(range(len(values)), key=values.__getitem__)  # the first best, as argmax
        if values[best] > self._best_reward:
            self._best_reward = values[best]
            self._best_theta = theta[best].clone()
        if first:
            self._after_initial_batch()
        else:
            self.iteration += 1
            self._iterate()

    # Hooks of the subclasses.
    def _observe(self, batch: TellBatch) -> None:
        """The told batch, before its samples enter the archive."""

    def _after_initial_batch(self) -> None:
        """After the first batch (n0 samples of policy 0) is archived."""

    def _iterate(self) -> None:
        """After every later batch is archived: the iteration's updates."""

    # ------------------------------------------------------------------ the world changes
    def reevaluate(self, returns: Tensor) -> None:
        """Tell the optimizer that the world changed: ``returns`` are the returns of its
        stored policies measured after the change.

        Every return the optimizer kept was measured before the change and is forgotten:
        each policy keeps one sample, its mean, with its new return, and the best so far
        (``best``) becomes the best policy mean. A policy whose new return is below every
        return it had kept was hurt by the change: it is sampled again (a retired one too)
        from its mean with Σ_start's exploration, so it searches for a way around. The others
        go on as before. The next ``ask``/``tell`` continue the run; the trial count grows by
        K (one evaluation per stored policy, no relearning)::

            theta = opt.policy_means.to(dtype)        # [K, D], retired policies included
            opt.reevaluate(evaluate(theta))           # [K] returns in the changed world
            best_policy = opt.policy_means[opt.last_rewards.argmax()]   # switch to it

        Args:
            returns: ``[K]`` the return of each row of ``policy_means``, finite (and inside
                ``reward_range`` when a fixed one was given).

        A pending ``ask`` is discarded. If anything raises, the optimizer is unchanged.
        """
        if not self.started:
            raise RuntimeError("reevaluate() needs a started run: tell() the first batch first")
        returns = check_rewards(returns, self.num_policies, "stored policy", "returns")
        returns = returns.to(self.device)
        self.reward_scale.check_range(returns, name="returns")
        snapshot = self._snapshot()
        try:
            self._reevaluate(returns.to(DTYPE))
        except BaseException:
            self._load_state_dict(snapshot)
            raise

    def _reevaluate(self, returns: Tensor) -> None:
        k = self.num_policies
        hurt = returns < self.archive.per_policy("amin", k)  # no kept samples: +inf, hurt
        self.archive.replace(
            self.policy_means.clone(), returns.clone(), torch.arange(k, device=self.device)
        )
        self.trials += k
        self.last_rewards = returns.clone()
        best = int(returns.argmax())
        self._best_theta = self.policy_means[best].clone()
        self._best_reward = float(returns[best])
        self._pending = self._pending_owner = None
        self.repeats.forget()
        self._restart(hurt)

    def _restart(self, rows: Tensor) -> None:
        """Policies ``rows [K]`` (bool) search again: active, Σ_start's exploration, their
        mechanisms' fields at their defaults."""
        self.policy_set.active = self.active | rows
        self.policy_set.covariances = torch.where(
            rows[:, None, None], self.sigma_start, self.policy_covariances
        )
        self.policy_set.reset_fields(rows)

    def remove_policies(self, index: Tensor) -> None:
        """Drop policies ``index [P]`` and their samples; renumber the others."""
        keep = torch.ones(self.num_policies, dtype=torch.bool, device=self.device)
        keep[index] = False
        self.archive.drop_policies(keep)
        self.policy_set.index(keep)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything needed to continue the run exactly, generator state included (copies:
        the run goes on without changing them), and the settings the optimizer was built
        with (``load_state_dict`` compares them)."""
        settings = {
            key: value.clone() if isinstance(value, Tensor) else value
            for key, value in self._settings().items()
        }
        return {**self._state(copy=True), "settings": settings}

    def _snapshot(self) -> dict:
        """What ``_load_state_dict`` needs to undo a call that raised: ``state_dict``
        without its copies, the optimizer's tensors themselves. The snapshot stays as it was
        because every step of a run *replaces* a tensor it changes (``policy_set.means =
        …``) and never writes into one; a step that must write into a tensor writes into
        its own copy (``Retirement.restart_straddlers``)."""
        return self._state(copy=False)

    def _state(self, copy: bool) -> dict:
        """The entries of ``state_dict``: the tensors copied, or (``copy=False``) not."""

        def kept(tensor: Tensor | None) -> Tensor | None:
            return tensor.clone() if copy and tensor is not None else tensor

        return {
            **self.archive.state_dict(copy),
            **self.policy_set.state_dict(copy),
            "last_rewards": kept(self.last_rewards),
            "trials": self.trials,
            "iteration": self.iteration,
            "policy_samples": self.policy_samples,
            "best_theta": kept(self._best_theta),
            "best_reward": self._best_reward,
            "pending": kept(self._pending),
            "pending_owner": kept(self._pending_owner),
            **self.repeats.state_dict(copy),
            "generator": self.generator.get_state(),
            "kind": type(self).__name__,
        }

    def _settings(self) -> dict[str, Any]:
        """What the optimizer was built with and its state does not hold, as plain values
        and tensors (``load_state_dict`` compares them): θ0 ``[D]``, Σ_start ``[D, D]``, the
        box (``[2, D]`` or None), M, n0 and the reward scale; a subclass adds its options."""
        scale = self.reward_scale
        fixed = None if scale.low is None else (scale.low, scale.high)
        return {
            "theta0": self.theta0,
            "sigma_start": self.sigma_start,
            "bounds": None if self.box is None else torch.stack(self.box),
            "M": self.M,
            "n0": self.n0,
            "reward_range": "positive" if scale.positive else fixed,
            "reward_floor": scale.floor,
        }

    def load_state_dict(self, state: dict, strict: bool = True) -> None:
        """Continue from ``state`` (of ``state_dict``); raises ``ValueError`` naming what
        does not fit this optimizer (another kind, another dimension, a missing key), and
        then the optimizer is as it was before the call.

        The state holds the run, not the settings the optimizer was built with (θ0,
        Σ_start, the box, the options): those are the constructor's, as a module's
        hyperparameters are. With ``strict`` (the default) a state saved by an optimizer
        built with other settings is refused, naming them; ``strict=False`` continues the
        run under this optimizer's settings (a deliberate change of options mid-run)."""
        if not isinstance(state, dict):
            raise ValueError(f"state_dict must be a dict, got {type(state).__name__}")
        if state.get("kind") != type(self).__name__:
            kind = state.get("kind")
            origin = "not an optimizer's state_dict" if kind is None else f"from a {kind}"
            raise ValueError(f"state_dict is {origin}, not a {type(self).__name__}'s")
        saved_theta0 = state.get("settings", {}).get("theta0")
        if isinstance(saved_theta0, Tensor) and tuple(saved_theta0.shape) != (self.dim,):
            raise ValueError(
                f"state_dict was saved by a {type(self).__name__} of dimension D = "
                f"{saved_theta0.numel()}; this one has D = {self.dim} (its theta0 has "
                f"{self.dim} parameters)"
            )
        snapshot = self._snapshot()
        try:
            self._load_state_dict(state)  # (what does not fit is named first)
            if strict and "settings" in state:  # (states saved before settings were kept: none)
                differences = setting_differences(state["settings"], self._settings())
                if differences:
                    raise ValueError(
                        f"state_dict was saved by a {type(self).__name__} built with other "
                        f"settings: {'; '.join(differences)}. Build this one as that one was, or "
                        f"load with strict=False to continue under this one's settings"
                    )
        except BaseException:
            self._load_state_dict(snapshot)  # a refused state leaves no part of it behind
            raise

    def _load_state_dict(self, state: dict) -> None:
        """Load ``state`` part by part (a subclass loads its own parts after these)."""
        try:
            self.archive.load_state_dict(state, self.device)
            self.policy_set.load_state_dict(state, self.device)
            self.last_rewards = state["last_rewards"].to(self.device)
            self.trials = int(state["trials"])
            self.iteration = int(state["iteration"])
            self.policy_samples = int(state["policy_samples"])
            best_theta = state["best_theta"]
            if tuple(best_theta.shape) != (self.dim,):
                raise ValueError(
                    f"state_dict['best_theta'] must have shape [{self.dim}], "
                    f"got {list(best_theta.shape)}"
                )
            self._best_theta = best_theta.to(self.device)
            self._best_reward = float(state["best_reward"])
            if math.isnan(self._best_reward) or self._best_reward == math.inf:
                raise ValueError(
                    f"state_dict['best_reward'] must be a return or -inf (none yet), got "
                    f"{self._best_reward}"
                )
            pending, owner = state["pending"], state["pending_owner"]
            self._pending = None if pending is None else pending.to(self.device)
            self._pending_owner = None if owner is None else owner.to(self.device)
            self._pending_boxed = False  # (rows from elsewhere: checked against the box)
            self.repeats.load_state_dict(state, owner, len(self.archive), self.dim, self.device)
            self.generator.set_state(state["generator"])
        except KeyError as missing:
            raise ValueError(
                f"state_dict has no {missing} (not a {type(self).__name__}'s)"
            ) from None
