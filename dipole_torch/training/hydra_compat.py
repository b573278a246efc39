"""The Hydra and OmegaConf calls whose spelling differs between the releases the package runs
on: hydra-core 1.3 with omegaconf 2.3 (what ``pyproject.toml`` asks for today) and Hydra 1.4
with omegaconf 2.4.

Hydra 1.4 deprecates three things a start of ``train.py`` did, each a warning printed at
every start (which would break the one-line errors of ``training.checks``), and omegaconf
2.4 one:

* ``version_base``: Hydra 1.3 wants ``version_base=None`` (its current defaults; without it,
  a warning); 1.4 deprecates the parameter, whose absence then means those same defaults.
  ``VERSION_BASE`` is the keyword arguments to pass: ``**VERSION_BASE``.
* Resolvers: omegaconf 2.4 deprecates ``register_new_resolver`` for ``register_resolver``,
  which in 2.3 is the legacy API (its resolvers get their arguments as strings):
  ``register_resolver`` here calls the one that registers the same resolver.
* ``instantiate``: Hydra 1.4 asks the calling code for an execution whitelist, the targets it
  trusts a config to build (without one, a warning; an error from Hydra 1.5). ``instantiate``
  here trusts the package's own targets and the config's top-level ``_target_``; on Hydra
  1.3 it is ``hydra.utils.instantiate``.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from typing import Any

import hydra
import omegaconf
from hydra import utils as hydra_utils
from omegaconf import OmegaConf

__all__ = ["PACKAGE_TARGETS", "VERSION_BASE", "instantiate", "register_resolver"]


def _release(version: str) -> tuple[int, int]:
    """``(major, minor)`` of a version string (a pre-release counts as its release)."""
    match = re.match(r"(\d+)\.(\d+)", version)
    if match is None:
        raise ValueError(f"cannot read a version from {version!r}")
    return int(match[1]), int(match[2])


HYDRA_1_4 = _release(hydra.__version__) >= (1, 4)
OMEGACONF_2_4 = _release(omegaconf.__version__) >= (2, 4)
VERSION_BASE: dict[str, Any] = {} if HYDRA_1_4 else {"version_base": None}
# The targets every config of the package builds: the tasks, the optimizers, their parts.
PACKAGE_TARGETS = ("dipole_torch.*",)


def register_resolver(name: str, resolver: Callable[..., Any]) -> None:
    """Register (or replace) the OmegaConf resolver ``name``: ``${name:a,b}`` calls
    ``resolver(a, b)`` with the arguments' values."""
    if OMEGACONF_2_4:
        OmegaConf.register_resolver(name, resolver, replace=True)
    else:
        OmegaConf.register_new_resolver(name, resolver, replace=True)


def instantiate(config: Any, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate(config, **kwargs)``, trusting ``PACKAGE_TARGETS`` and
    ``config``'s own ``_target_`` (a task of the user's own, say) unless the standard
    library's.

    Which targets to trust is for the code that reads the config to say. ``train.py``'s
    config is its user's (their config files and command line; a checkpoint's config is
    compared with it, never built), so the target it names at the top is trusted by name,
    and the targets below it must be the package's. Not one of the standard library's: a
    task or an optimizer is never one, and some of its callables (``shutil.rmtree``,
    ``os.kill``) are what Hydra refuses to build from a config unless trusted code names
    them.
    """
    if not HYDRA_1_4:
        return hydra_utils.instantiate(config, **kwargs)
    target = config.get("_target_") if hasattr(config, "get") else None
    trusted = PACKAGE_TARGETS + ((target,) if _trusted_by_name(target) else ())
    return hydra_utils.instantiate(config, _execution_whitelist_=list(trusted), **kwargs)


def _trusted_by_name(target: Any) -> bool:
    """Whether a config's top-level ``_target_`` may be trusted by name: a dotted path
    outside the standard library."""
    if not isinstance(target, str) or not target:
        return False
    return target.split(".", 1)[0] not in sys.stdlib_module_names
