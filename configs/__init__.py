"""The Hydra config tree of ``train.py``: ``config.yaml``, the groups ``task/`` and ``algo/``.

Importing this package registers the schemas its files extend
(:func:`dipole_torch.training.config.register`), so that
``hydra.initialize_config_module("dipole_torch.configs")`` composes them from any directory.
"""

from dipole_torch.training.config import register

register()
