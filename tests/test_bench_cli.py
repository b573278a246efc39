"""The benchmark scripts' command lines: the ``--help`` text and bad option values."""

import ast
import re
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
SCRIPTS = sorted(p for p in BENCHMARKS.glob("*.py") if "argparse.ArgumentParser(" in p.read_text())


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_the_help_describes_a_script_in_whole_sentences(script):
    # ``--help`` shows the docstring's first paragraph, not its first line (cut mid-sentence:
    # "… against the CPU a trial may").
    source = script.read_text()
    assert "__doc__.splitlines()[0]" not in source
    assert 'description=__doc__.split("\\n\\n")[0]' in source
    first = ast.get_docstring(ast.parse(source), clean=False).split("\n\n")[0].rstrip()
    assert re.search(r"[.?!)]$", first), f"{script.name}: {first[-60:]!r}"
