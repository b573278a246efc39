"""The DP mixture's Gibbs sampler as a Pyro MCMC kernel.

``pyro.infer.MCMC(DPMixtureKernel(DPSampler(prior)), num_samples=..., warmup_steps=...).run(y)``
runs the sweeps of a ``DPSampler`` (Algorithm 8, re-used auxiliaries or
the slice sampler) with Pyro's progress bar, and keeps label-switching-invariant summaries of
every kept state for ``get_samples()``, ``summary()`` and ``diagnostics()``.

The kernel adds nothing to the chain: with the same generator it makes exactly the sweeps of
``DPSampler.fit <dipole_torch.dp.DPSampler.fit>`` (``tests/test_mcmc.py`` checks this).
It does add bookkeeping (``benchmarks/bench_mcmc_kernel.py`` measures it), so DIPOLE's own
clusterings call the sampler directly.
"""

from __future__ import annotations

import torch
from pyro.infer.mcmc.mcmc_kernel import MCMCKernel
from torch import Tensor

from dipole_torch.dp.sampler import INITS, Chain, DPSampler
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE
from dipole_torch.pyro_model import canonical_state, dp_log_joint
from dipole_torch.validation import check_choice

__all__ = ["DPMixtureKernel"]


class DPMixtureKernel(MCMCKernel):
    """One step = one sweep of ``sampler`` (a ``DPSampler``) on the DP
    Gaussian mixture.

    Run it with ``pyro.infer.MCMC(kernel, num_samples, warmup_steps).run(y)``, ``y: [N, D]``.
    Each kept sample holds (MCMC stores every site as float64, labels included):

    * ``num_components``: ``[]`` K, the number of occupied components;
    * ``labels``: ``[N]`` component of each point, numbered in order of first appearance
      (so that they do not switch between samples);
    * ``point_means``: ``[N, D]`` μ_{c_i}, the mean of the component of each point;
    * ``log_joint``: ``[]`` log p(labels, μ, Σ, y) under the state's H
      (``dipole_torch.pyro_model.dp_log_joint``; with ``reward_weighted=True`` the chain
      samples a reweighted distribution and this is a diagnostic only).

    ``MCMC(..., save_params=[...])`` keeps a subset. The full current state (a
    ``DPMixtureState``, e.g. ``kernel.state.mixture()``) is
    ``state``; a ``hook_fn(kernel, params, stage, i)`` passed to ``MCMC`` sees every one.

    Args:
        sampler: the sampler whose sweeps are the steps (its prior starts the chain).
        init: ``"single"`` (one component, Algorithm 1's start) or ``"sequential"`` (one
            sequential CRP pass); ignored when ``MCMC(initial_params={"labels": ...})`` or
            ``initial_params`` gives labels.
        generator: source of all randomness (``None``: the global RNG, e.g.
            ``pyro.set_rng_seed``).

    Example:
        >>> from pyro.infer import MCMC
        >>> from dipole_torch import DPSampler, NormalInverseWishartPrior
        >>> g = torch.Generator().manual_seed(0)
        >>> y = torch.randn(40, 2, generator=g)
        >>> y[:20] -= 3
        >>> y[20:] += 3
        >>> prior = NormalInverseWishartPrior.from_exploration(
        ...     torch.zeros(2, dtype=torch.float64), 9 * torch.eye(2, dtype=torch.float64))
        >>> sampler = DPSampler(prior, m=3, update_prior=False)
        >>> kernel = DPMixtureKernel(sampler, init="sequential", generator=g)
        >>> mcmc = MCMC(kernel, num_samples=10, warmup_steps=5, disable_progbar=True)
        >>> mcmc.run(y)
        >>> labels = mcmc.get_samples()["labels"]  # [10, 40]: the two groups never mix
        >>> labels.shape, bool((labels[:, :20, None] != labels[:, None, 20:]).all())
        (torch.Size([10, 40]), True)
    """

    def __init__(
        self,
        sampler: DPSampler,
        init: str = "single",
        generator: torch.Generator | None = None,
    ):
        if not isinstance(sampler, DPSampler):
            raise TypeError(f"sampler must be a DPSampler, got {type(sampler).__name__}")
        check_choice(init, INITS, "init")
        self.sampler = sampler
        self.init = init
        self.generator = generator
        # MCMC reads these: samples are stored as they are (no unconstraining transforms),
        # and there is no Pyro model to trace.
        self.transforms: dict = {}
        self.model = None
        self._initial_labels: Tensor | None = None
        self._y: Tensor | None = None
        self._chain: Chain | None = None
        self._state: DPMixtureState | None = None
        self._params: dict[str, Tensor] | None = None
        self._num_sweeps = 0

    # ------------------------------------------------------------------ the MCMCKernel API
    def setup(self, warmup_steps: int, y: Tensor) -> None:
        """Start a chain on ``y: [N, D]`` (called by ``MCMC.run(y)``)."""
        y = self.sampler.checked_data(y)
        self._y = y
        if self._initial_labels is not None:
            if self._initial_labels.shape != (y.shape[0],):
                raise ValueError(
                    f"initial labels must have shape [{y.shape[0]}], "
                    f"got {list(self._initial_labels.shape)}"
                )
            state = DPMixtureState.from_labels(y, self._initial_labels, self.sampler.prior)
        else:
            state = self.sampler.start(y, self.init, self.generator)
        self._chain = self.sampler.to_chain(state)
        self._set_state(state)
        self._num_sweeps = 0

    @property
    def initial_params(self) -> dict[str, Tensor]:
        """The summaries of the chain's start (after ``setup``)."""
        if self._params is None:
            raise RuntimeError("initial_params exist after setup(warmup_steps, y)")
        return self._params

    @initial_params.setter
    def initial_params(self, params: dict[str, Tensor]) -> None:
        """Start the next chain from ``params["labels"]: [N]`` (any integer numbering); the
        component parameters start at their conditional posterior means."""
        if "labels" not in params:
            raise ValueError(f"initial_params must contain 'labels', got {sorted(params)}")
        labels = torch.as_tensor(params["labels"])
        if labels.dim() != 1 or (labels != labels.round()).any():
            raise ValueError(f"initial labels must be [N] integers, got {labels}")
        self._initial_labels = labels.long()

    def sample(self, params: dict[str, Tensor]) -> dict[str, Tensor]:
        """One Gibbs sweep from the current state; ``params`` (the previous summaries) only
        mirror it."""
        if self._chain is None or self._y is None:
            raise RuntimeError("call setup(warmup_steps, y) before sample()")
        state = self._sweep(self._y)
        self._num_sweeps += 1
        return self._set_state(state)

    def _sweep(self, y: Tensor) -> DPMixtureState:
        """One sweep from the current chain (a slice sampler's keeps its stick labels); the
        new state."""
        self._chain = self.sampler.sweep(y, self._chain, self.generator)
        return self.sampler.to_state(self._chain)

    def logging(self) -> dict[str, int]:
        """Shown next to Pyro's progress bar: the current number of components."""
        return {"K": self._state.num_components if self._state is not None else 0}

    def diagnostics(self) -> dict[str, int]:
        return {"num_sweeps": self._num_sweeps}

    # ------------------------------------------------------------------ helpers
    @property
    def state(self) -> DPMixtureState:
        """The chain's current state (labels, means, covariances Σ + R, H)."""
        if self._state is None:
            raise RuntimeError("the kernel has no state before setup(warmup_steps, y)")
        return self._state

    @property
    def chain(self) -> Chain:
        """What the sampler carries between sweeps: the state for Algorithm 8, the
        ``SliceChain`` (stick labels, every stick's atom) for the
        slice sampler."""
        if self._chain is None:
            raise RuntimeError("the kernel has no state before setup(warmup_steps, y)")
        return self._chain

    def _set_state(self, state: DPMixtureState) -> dict[str, Tensor]:
        assert self._y is not None
        self._state = state
        canonical = canonical_state(state)
        k = torch.tensor(float(state.num_components), dtype=DTYPE, device=self._y.device)
        self._params = {
            "num_components": k,
            "labels": canonical.labels.to(DTYPE),
            "point_means": canonical.means[canonical.labels],
        }
        # MCMC(save_params=...) sets save_params: the log joint only when it is kept.
        if "log_joint" in getattr(self, "save_params", ("log_joint",)):
            self._params["log_joint"] = dp_log_joint(self._y, state, self.sampler.alpha)
        return self._params
