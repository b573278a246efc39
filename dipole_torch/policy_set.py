"""Every per-policy tensor of a policy search, in one object that re-indexes them together."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dipole_torch.memo import Memo
from dipole_torch.validation import check_finite, check_positive_semidefinite

__all__ = ["PolicyField", "PolicySet"]


@dataclass(frozen=True)
class PolicyField:
    """A per-policy tensor that a mechanism keeps (e.g. the success rule's success rate):
    its trailing shape, dtype and the value a new or restarted policy starts with."""

    shape: tuple[int, ...] = ()
    default: float = 0.0
    dtype: torch.dtype = torch.float64


class PolicySet:
    """K policies in rows: ``means [K, D]``, ``covariances [K, D, D]`` (each policy's
    exploration), ``active [K]`` (whether it is still sampled), ``ids [K]`` (a number that
    stays a policy's own while others come and go: 0, 1, 2, … in order of creation), and the
    fields mechanisms register (``register``, e.g. ``success [K]`` and ``paths [K, D]``).

    Every tensor follows the same rows: ``index`` keeps a subset of the policies in all of
    them, ``extend`` appends new policies (fields at their defaults), ``reset``
    replaces them all. A new per-policy tensor is one ``register`` call.

    Args:
        means: ``[K, D]`` policy means.
        covariances: ``[K, D, D]`` exploration covariances.
    """

    CORE = ("means", "covariances", "active", "ids")

    def __init__(self, means: Tensor, covariances: Tensor):
        object.__setattr__(self, "_fields", {})
        object.__setattr__(self, "_tensors", {})
        object.__setattr__(self, "next_id", 0)
        object.__setattr__(self, "_memo", Memo())
        self.means = means
        self.covariances = covariances
        self.active = torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
        self.ids = self._new_ids(means.shape[0])

    def _new_ids(self, n: int) -> Tensor:
        ids = torch.arange(self.next_id, self.next_id + n, device=self.means.device)
        object.__setattr__(self, "next_id", self.next_id + n)
        return ids

    # ------------------------------------------------------------------ fields
    def register(self, name: str, field: PolicyField) -> None:
        """Add a per-policy tensor ``name`` (every policy at ``field.default``)."""
        if name in self.CORE or name in self._fields:
            raise ValueError(f"policy field {name!r} exists already")
        self._fields[name] = field
        self._tensors[name] = self._default(field, len(self))

    def _default(self, field: PolicyField, n: int) -> Tensor:
        return torch.full(
            (n, *field.shape), field.default, dtype=field.dtype, device=self.means.device
        )

    def __getattr__(self, name: str) -> Tensor:
        if name.startswith("_"):  # copy and pickle look for _tensors before it is set
            raise AttributeError(name)
        try:
            return self._tensors[name]
        except KeyError:
            raise AttributeError(f"PolicySet has no field {name!r}") from None

    def __setattr__(self, name: str, value: Tensor) -> None:
        if name not in self.CORE and name not in self._fields:
            raise AttributeError(f"PolicySet has no field {name!r} (register it first)")
        self._tensors[name] = value

    @property
    def field_names(self) -> tuple[str, ...]:
        """The registered fields' names (the core tensors excluded)."""
        return tuple(self._fields)

    def __len__(self) -> int:
        return int(self._tensors["means"].shape[0])

    # ------------------------------------------------------------------ derived, memoised
    # Several mechanisms of one iteration need these while the tensors stand still
    # (``Memo``: recomputed once a tensor is replaced or written into).
    def active_flags(self) -> tuple[bool, ...]:
        """Which policies are active, on the host (the mechanisms branch on it)."""
        return self._memo.get("active", (self.active,), lambda: tuple(self.active.tolist()))

    def any_active(self) -> bool:
        """Whether some policy is active (on the host, from ``active_flags``)."""
        return True in self.active_flags()

    def exploration_factors(self) -> tuple[Tensor, Tensor]:
        """``(L [K, D, D], ok [K])``: the Cholesky factors of the exploration covariances,
        and whether each exists in float64 (where not, L is the identity). Not to be
        written into."""

        def compute() -> tuple[Tensor, Tensor]:
            chol, info = torch.linalg.cholesky_ex(self.covariances)
            ok = info == 0
            eye = torch.eye(chol.shape[-1], dtype=chol.dtype, device=chol.device)
            return torch.where(ok[:, None, None], chol, eye), ok

        return self._memo.get("factors", (self.covariances,), compute)

    # ------------------------------------------------------------------ rows
    def index(self, keep: Tensor) -> None:
        """Keep the policies ``keep`` (``[K]`` bool, or indices, in their new order) in
        every tensor."""
        for name, value in self._tensors.items():
            self._tensors[name] = value[keep]

    def extend(self, means: Tensor, covariances: Tensor, **values: Tensor) -> None:
        """Append n policies ``means [n, D]``, ``covariances [n, D, D]``, active, with
        ``values`` for their fields (the others at their defaults)."""
        n = means.shape[0]
        new = {
            "means": means,
            "covariances": covariances,
            "active": torch.ones(n, dtype=torch.bool, device=means.device),
            "ids": self._new_ids(n),
        }
        for name, field in self._fields.items():
            new[name] = values.pop(name) if name in values else self._default(field, n)
        if values:
            raise ValueError(f"unknown policy field(s) {sorted(values)}")
        for name, value in new.items():
            self._tensors[name] = torch.cat((self._tensors[name], value))

    def reset(self, means: Tensor, covariances: Tensor) -> None:
        """Replace every policy by ``means [K, D]``, ``covariances [K, D, D]``: new
        policies, all active, their fields at their defaults."""
        self.means, self.covariances = means, covariances
        self.active = torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
        self.ids = self._new_ids(means.shape[0])
        for name, field in self._fields.items():
            self._tensors[name] = self._default(field, means.shape[0])

    def reset_fields(self, rows: Tensor) -> None:
        """The fields of the policies ``rows [K]`` (bool) back to their defaults."""
        for name, field in self._fields.items():
            value = self._tensors[name]
            mask = rows.reshape(-1, *([1] * len(field.shape)))
            self._tensors[name] = torch.where(mask, field.default, value)

    # ------------------------------------------------------------------ checkpoints
    KEYS = {
        "means": "policy_means",
        "covariances": "policy_covariances",
        "active": "active",
        "ids": "policy_ids",
    }

    def state_dict(self, copy: bool = True) -> dict[str, Tensor | int]:
        """Every tensor under its state key, and ``next_policy_id``: copies, or
        (``copy=False``) the tensors themselves (see ``PolicySearch.tell``'s snapshot)."""
        state = {
            self.KEYS.get(name, name): value.clone() if copy else value
            for name, value in self._tensors.items()
        }
        return state | {"next_policy_id": self.next_id}

    def load_state_dict(self, state: dict, device: torch.device) -> None:
        """Load every tensor (state keys ``policy_means``, ``policy_covariances``, ``active``
        and the field names); raises ``ValueError`` naming a key whose shape does not fit. A
        field missing from ``state`` (a checkpoint from before a mechanism kept it) starts at
        its default."""
        d = self.means.shape[1]
        means = state["policy_means"]
        if not isinstance(means, Tensor) or means.dim() != 2 or means.shape[1] != d:
            raise ValueError(
                f"state_dict['policy_means'] must have shape [K, {d}], got "
                f"{list(getattr(means, 'shape', [type(means).__name__]))}"
            )
        k = means.shape[0]
        shapes = {"means": (k, d), "covariances": (k, d, d), "active": (k,), "ids": (k,)}
        shapes |= {name: (k, *field.shape) for name, field in self._fields.items()}
        loaded = {}
        for name, shape in shapes.items():
            key = self.KEYS.get(name, name)
            if name in self._fields and key not in state:
                loaded[name] = self._default(self._fields[name], k)
                continue
            if name == "ids" and key not in state:  # (from before policies had ids)
                loaded[name] = torch.arange(k, device=device)
                continue
            value = state[key]
            if not isinstance(value, Tensor) or tuple(value.shape) != shape:
                raise ValueError(
                    f"state_dict[{key!r}] must have shape {list(shape)}, got "
                    f"{list(getattr(value, 'shape', [type(value).__name__]))}"
                )
            dtype = torch.bool if name == "active" else self._tensors[name].dtype
            loaded[name] = value.to(device=device, dtype=dtype)
        check_finite(loaded["means"], "state_dict['policy_means']")
        if k:  # semi-definite: a run may leave a retired policy's exploration rounded to zero
            covariances = loaded["covariances"]
            check_positive_semidefinite(covariances, "state_dict['policy_covariances']")
            singular = torch.linalg.cholesky_ex(covariances)[1] != 0
            active = (singular & loaded["active"]).nonzero().flatten().tolist()
            if active:
                raise ValueError(
                    f"state_dict['policy_covariances'] is not positive definite for the "
                    f"active policies {active}: an active policy's exploration is sampled"
                )
        self._tensors.update(loaded)
        ids = loaded["ids"]
        next_id = int(state.get("next_policy_id", int(ids.max()) + 1 if ids.numel() else 0))
        object.__setattr__(self, "next_id", next_id)
