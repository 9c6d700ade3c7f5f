"""The documentation site: its tutorial code runs, it builds in strict mode, and the pages the
code comments cite hold the sections they cite.

Tutorial blocks are fenced ``python`` blocks preceded by a ``<!-- run: NAME -->`` line on any
page of ``docs/``; each runs as a script in an empty folder, on the embedded generated scenes.
(``tests/test_readme_recipes.py`` runs the ``recipe:`` blocks of ``docs/extending.md``.)
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
RUN_BLOCK = re.compile(r"<!-- run: (\S+) -->\n```python\n(.*?)\n```", flags=re.S)
MKDOCS_MODULES = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def run_blocks() -> dict[str, tuple[Path, str]]:
    """{name: (page, code)} of every ``run:`` block of the docs."""
    blocks: dict[str, tuple[Path, str]] = {}
    for page in sorted(DOCS.rglob("*.md")):
        for name, code in RUN_BLOCK.findall(page.read_text()):
            assert name not in blocks, f"run block {name!r} is used twice"
            blocks[name] = (page, code)
    return blocks


BLOCKS = run_blocks()


def test_the_docs_have_runnable_tutorials():
    assert len(BLOCKS) >= 8, sorted(BLOCKS)
    pages = {page.name for page, _ in BLOCKS.values()}
    for page in ("getting-started.md", "environments.md", "policies.md", "realism.md"):
        assert page in pages, page


@pytest.mark.parametrize("name", sorted(BLOCKS))
def test_a_tutorial_block_runs_as_written(name, tmp_path, monkeypatch, capsys):
    page, code = BLOCKS[name]
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs__"}
    exec(compile(code, f"<{page.relative_to(REPO)}: {name}>", "exec"), namespace)
    assert capsys.readouterr().out.strip(), "a tutorial block shows its result"


def test_readme_and_model_card_stay_short():
    readme = (REPO / "README.md").read_text().splitlines()
    card = (DOCS / "MODEL_CARD.md").read_text().splitlines()
    assert len(readme) <= 200, len(readme)
    assert len(card) <= 150, len(card)
    # The two commands of the README, exactly.
    text = "\n".join(readme)
    assert "python -m pip install torch==2.13.0 && python -m pip install -e . && tbsim demo" in text
    assert (
        'python -m pip install torch==2.13.0 && python -m pip install -e ".[test]" '
        "&& python -m pytest -q" in text
    )


def _model_sections() -> set[str]:
    """Numbers of the numbered headings of docs/model.md ("1", "1.6", ...)."""
    text = (DOCS / "model.md").read_text()
    return set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", text, flags=re.M))


def test_every_cited_model_section_exists():
    """Code comments cite "docs/model.md §N.M"; each cited section is a heading of the page."""
    sections = _model_sections()
    assert {"1.6", "3.7", "5.2", "7.3", "8"} <= sections
    cited: dict[str, str] = {}
    for root in ("tbsim_env", "policies", "tests", "scripts", "bench", "examples"):
        for path in (REPO / root).rglob("*.py"):
            for match in re.finditer(r"§\s?(\d+(?:\.\d+)?)", path.read_text()):
                cited.setdefault(match.group(1), str(path.relative_to(REPO)))
    missing = {n: where for n, where in cited.items() if n not in sections}
    assert not missing, f"sections cited but not in docs/model.md: {missing}"
    assert len(cited) >= 20


def test_mkdocs_builds_the_site_in_strict_mode(tmp_path):
    missing = [m for m in MKDOCS_MODULES if importlib.util.find_spec(m.split(".")[0]) is None]
    if missing:
        msg = f"documentation tools not installed ({', '.join(missing)}; the docs extra)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + "; under CI they are required")
        pytest.skip(msg)
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)]
    result = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "model" / "index.html").is_file()
    assert (tmp_path / "api" / "env" / "index.html").is_file()
