"""Puts the repository's train.py into the wheel as ``dipole_torch/train.py`` (the module of
the ``dipole-train`` command); everything else is declared in pyproject.toml.

train.py stays at the repository root, the one readable script users run (``python train.py
task=viapoint``), and the wheel installs no top-level ``train`` module. setuptools maps
packages, not single files, to folders, hence this step. In the source tree
``dipole_torch.train`` is the root train.py itself (dipole_torch/__init__.py).
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithTrain(build_py):
    def run(self) -> None:
        super().run()
        if not self.editable_mode:  # editable: dipole_torch.train resolves to ./train.py
            target = Path(self.build_lib, "dipole_torch", "train.py")
            self.copy_file("train.py", str(target))


setup(cmdclass={"build_py": BuildPyWithTrain})
