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


def _anchors(page: Path) -> set[str]:
    """The fragment ids a renderer gives the headings of ``page`` (GitHub's rule: lower case, punctuation other
    than ``-`` and ``_`` dropped, spaces to ``-``, a repeated heading numbered ``-1``, ``-2``...), plus explicit
    ``<a name=...>``/``id=`` anchors. Headings inside fenced code are not headings."""
    found, seen, fenced = set(), {}, False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        if fenced:
            continue
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            found.add(slug if n == 0 else f"{slug}-{n}")
        found.update(re.findall(r'<a (?:name|id)="([^"]+)"', line))
    return found


def test_relative_links_resolve():
    """Every relative link of the README, docs/, spec/ and examples/ pages leads to a file or folder of the
    repository, and a link into a page's section to a heading that page has (pages move and headings change:
    a user following a dead link gets nothing)."""
    pages = [ROOT / "README.md", *[p for d in ("docs", "spec", "examples") for p in (ROOT / d).rglob("*.md")]]
    dead = []
    for page in pages:
        text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)  # code is not links
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-zA-Z][a-zA-Z+.-]*:", target):  # http:, https:, mailto: ...
                continue
            path, _, fragment = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)}: ({target})"
            if not dest.exists():
                dead.append(f"{where}: no such file")
            elif fragment and dest.suffix == ".md" and fragment not in _anchors(dest):
                dead.append(f"{where}: no heading '{fragment}' in {dest.relative_to(ROOT)}")
    assert not dead, "dead links:\n" + "\n".join(dead)
