"""The requirements the .ci scripts install, read from pyproject.toml: the core dependencies
and the test and sweep extras' (the environment CI makes), each of the form ``name>=floor``.

    python .ci/requirements.py floors            # each pinned at its floor: name==floor
    python .ci/requirements.py floors --numpy2   # the same beside numpy 2, with the bench extra
    python .ci/requirements.py names             # the names, torch left out, omegaconf added

``floors`` is for ``.ci/lowest-versions``, ``names`` for ``.ci/prerelease-versions``.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import tomllib

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def requirements(bench: bool = False) -> list[tuple[str, str]]:
    """``(name, floor)`` of every core, test and sweep requirement (and bench's)."""
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    extras = project["optional-dependencies"]
    listed = project["dependencies"] + extras["test"] + extras["sweep"]
    if bench:
        listed += extras["bench"]
    parsed = []
    for requirement in listed:
        match = re.fullmatch(r"([A-Za-z0-9_.\-]+)>=([0-9.]+)", requirement.split(";")[0].strip())
        if match is None:
            raise SystemExit(f"{requirement!r}: not of the form name>=floor")
        parsed.append(match.groups())
    return parsed


def floors(numpy2: bool) -> list[str]:
    """Each requirement at its floor. With ``numpy2``, numpy and scipy are left to pip (the
    newest: numpy 2) and the bench extra's floors join (pyribs needs numpy 2)."""
    pins = {}
    for name, floor in requirements(bench=numpy2):
        pins[name] = f"{name}>=2" if numpy2 and name == "numpy" else f"{name}=={floor}"
    if numpy2:
        pins["scipy"] = "scipy"  # (its floor caps numpy below 2; pip takes one that does not)
    return list(pins.values())


def names() -> list[str]:
    """The requirements' names but torch's (the CPU wheel on disk stays), and omegaconf:
    Hydra's, whose releases change what the package calls."""
    return [name for name, _ in requirements() if name != "torch"] + ["omegaconf"]


if __name__ == "__main__":
    command, *options = sys.argv[1:] or [""]
    if command == "floors" and options in ([], ["--numpy2"]):
        print("\n".join(floors(numpy2=options == ["--numpy2"])))
    elif command == "names" and not options:
        print("\n".join(names()))
    else:
        raise SystemExit(__doc__)
