"""The README's promises: its reuse example runs, and CI runs its test command."""

import os
import re
from pathlib import Path

from test_train import train

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_reuse_example_runs_on_a_finished_run(tmp_path, capsys):
    train("task=multimodal", "algo=dipole", "trials=60", cwd=tmp_path)
    block = re.search(
        r"<!-- reuse-example -->\s*```python\n(.*?)```\s*<!-- /reuse-example -->", README, re.S
    )
    assert block, "README lost its reuse example"
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(block.group(1), "README example", "exec"), {})
    finally:
        os.chdir(cwd)
    assert "policies that return 0.95 live around" in capsys.readouterr().out


def test_ci_runs_the_readme_test_command():
    commands = re.findall(r"```bash\n(python3 -m venv .*?)\n```", README)
    assert len(commands) == 2, "the quick start has two commands"
    test_command = commands[1].split("&&")[-1].strip()
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_command in ci.splitlines()
    assert 'pip install --quiet -e ".[test]"' in ci and "torch==2.13.0" in ci
