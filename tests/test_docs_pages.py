"""The generated pages of docs/ are what their generators make of the committed JSON and code (issue 41, item 6):
each page is rendered in-process from its data (nothing measured, a few seconds) and compared with the committed
page, so a re-measurement, an edit of a generator or a changed help text that was not followed by `make docs`
fails here. Also: every JSON file under docs/ is read by some page or script, and no page names a local path."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _pages():
    sys.path.insert(0, str(DOCS / "generate"))
    spec = importlib.util.spec_from_file_location("docs_pages", DOCS / "generate" / "pages.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


PAGES = _pages()


@pytest.mark.parametrize("page", sorted(PAGES.PAGES))
def test_generated_page_matches_its_data(page):
    committed = (DOCS / page).read_text(encoding="utf-8")
    assert PAGES.render(page) == committed, f"docs/{page} differs from what its generator makes: run `make docs`"


def test_every_json_under_docs_is_used():
    """A raw run no page reads is deleted (git history keeps it): each JSON under docs/ is named by a generator,
    by the script that writes it, or by a test."""
    texts = "\n".join(p.read_text(encoding="utf-8", errors="replace")
                      for d in (DOCS, ROOT / "examples", ROOT / "tests", ROOT / "sdfcodec")
                      for p in d.rglob("*.py"))
    # a script may name its files by pattern: "{name}.curves.json" (examples/train_ae_models.py)
    unused = [str(p.relative_to(DOCS)) for p in DOCS.rglob("*.json")
              if p.name not in texts and str(p.relative_to(DOCS)) not in texts
              and not (p.name.count(".") > 1 and "." + p.name.split(".", 1)[1] in texts)]
    assert not unused, f"JSON under docs/ that nothing reads: {unused}"


def test_no_local_paths_in_docs():
    bad = [f"{p.relative_to(ROOT)}:{i}" for p in DOCS.rglob("*.md")
           for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
           if re.search(r"(?<![\w.])/(work|tmp|home|root)/", line)]
    assert not bad, f"local paths in docs: {bad}"


def test_the_generator_writes_and_checks(tmp_path, monkeypatch, capsys):
    """`make docs` (pages.py) rewrites a stale page and `--check` then passes; a stale page fails `--check`."""
    page = "scale.md"
    monkeypatch.setattr(PAGES, "DOCS", tmp_path)
    (tmp_path / page).write_text("stale\n")
    assert PAGES.main(["--check", page]) == 1
    assert (tmp_path / page).read_text() == "stale\n"
    assert PAGES.main([page]) == 0 and PAGES.main(["--check", page]) == 0
    assert (tmp_path / page).read_text() == (DOCS / page).read_text(encoding="utf-8")
