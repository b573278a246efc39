"""Registers dipole-torch's structured configs whenever Hydra starts.

Hydra imports every module under the ``hydra_plugins`` namespace package when it discovers its
plugins (before composing any config), so ``configs/`` -- whose files extend the schemas
``base_config``, ``task/base_*`` and ``algo/base_*`` -- composes in any process: ``train.py``,
``hydra.compose`` in a test or a notebook, or a config directory of your own that extends them.
"""

import dipole_torch.config  # noqa: F401 (registers the schemas in Hydra's ConfigStore)
