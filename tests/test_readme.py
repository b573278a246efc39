"""The README's promises: its quick start is what CI runs, it stays a short page for users,
its tables show the numbers of docs/figures/*.json, and its links lead somewhere. (Its code
blocks run in tests/test_docs_examples.py, with the documentation's.)"""

import re
from pathlib import Path

from test_docs_examples import figure1_rows, shown, switch_rows, viapoint_rows

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_ci_runs_the_readme_test_command():
    commands = re.findall(r"```bash\n(python3 -m venv .*?)\n```", README)
    assert len(commands) == 2, "the quick start has two commands"
    assert commands[0].endswith("python train.py task=viapoint")
    test_command = commands[1].split("&&")[-1].strip()
    assert test_command == "python -m pytest -n 2"
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_command in ci.splitlines()
    assert 'pip install --quiet -e ".[test]"' in ci and "torch==2.13.0" in ci


def test_the_readme_is_a_short_page_for_users():
    assert len(README.splitlines()) <= 300
    # Release history and measurement history live in CHANGELOG.md and the benchmark pages.
    for phrase in ("this release", "last release", "previous release", "release before"):
        assert phrase not in README.lower(), phrase


def test_the_readme_tables_show_the_numbers_of_the_json():
    rows = shown(ROOT / "README.md")
    for table in (figure1_rows, viapoint_rows, switch_rows):
        missing = [row for row in table() if row not in rows]
        assert not missing, "README lacks these rows of its JSON:\n" + "\n".join(missing)


def test_the_readme_links_and_pictures_exist():
    targets = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README)
    local = [t for t in targets if not t.startswith(("http://", "https://"))]
    assert "docs/figures/figure3_routes.png" in local
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_the_citation_file_and_the_readme_cite_the_same_paper_and_release():
    import yaml

    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    pyproject = (ROOT / "pyproject.toml").read_text()  # (tomllib: Python 3.11 on)
    # The keys the Citation File Format 1.2 requires, and this release's version.
    assert {"cff-version", "message", "title", "authors"} <= set(citation)
    assert f'\nversion = "{citation["version"]}"\n' in pyproject
    paper = citation["references"][0]
    bibtex = dict(re.findall(r"(\w+)\s*=\s*\{(.*?)\},?\n", README))
    assert f'\nPaper = "https://doi.org/{paper["doi"]}"\n' in pyproject
    assert bibtex["doi"] == paper["doi"]
    assert bibtex["title"] == paper["title"]
    assert bibtex["pages"] == f"{paper['start']}--{paper['end']}"
    assert bibtex["year"] == str(paper["year"])
    surnames = [a.split(",")[0] for a in bibtex["author"].split(" and ")]
    assert surnames == [a["family-names"] for a in paper["authors"]]


def test_ci_builds_the_docs_strictly_without_hiding_the_warnings():
    # mkdocs --quiet hides the warnings that --strict counts: a strict build then passes with
    # them (it once passed with two broken links of the changelog).
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    build = [line for line in ci if "mkdocs build" in line]
    assert build and all("--strict" in line and "--quiet" not in line for line in build), build


def test_the_changelog_has_no_relative_links():
    # CHANGELOG.md is read at the repository root and, included in docs/changelog.md, on the
    # docs site, where a relative link resolves from docs/: no relative path works in both.
    changelog = (ROOT / "CHANGELOG.md").read_text()
    targets = re.findall(r"\]\(([^)]+)\)", changelog)
    relative = [t for t in targets if not t.startswith(("http://", "https://"))]
    assert not relative, f"CHANGELOG.md links relative paths: {relative}"
