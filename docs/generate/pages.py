"""Render every generated page of docs/ (`make docs`), or with --check say which differ from the committed ones.

Each results page is rendered by one script of this folder from the JSON committed beside it (nothing is measured
here; the measurement scripts write the JSON), the reference pages from the code itself. tests/test_docs_pages.py
renders them in-process and compares, so a page cannot drift from its data."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

sys.path.insert(0, str(Path(__file__).resolve().parent))

import page_codecs  # noqa: E402
import page_eval  # noqa: E402
import page_rate_distortion  # noqa: E402
import page_reference  # noqa: E402
import page_results  # noqa: E402
import page_scale  # noqa: E402
import page_search  # noqa: E402
from common import DOCS  # noqa: E402

__all__ = ["PAGES", "render", "main"]

#: page (relative to docs/) -> the function that renders it
PAGES: dict[str, Callable[[], str]] = {
    page_results.PAGE: page_results.render,
    page_search.PAGE: page_search.render,
    page_rate_distortion.PAGE: page_rate_distortion.render,
    page_eval.PAGE: page_eval.render,
    page_codecs.PAGE: page_codecs.render,
    page_scale.PAGE: page_scale.render,
    page_reference.CLI_PAGE: page_reference.render_cli,
    page_reference.API_PAGE: page_reference.render_api,
}


def render(page: str) -> str:
    return PAGES[page]()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a page differs")
    ap.add_argument("pages", nargs="*", help="pages to render (default: all)")
    a = ap.parse_args(argv)
    stale = []
    for page in a.pages or PAGES:
        text, path = render(page), DOCS / page
        if path.exists() and path.read_text(encoding="utf-8") == text:
            continue
        stale.append(page)
        if not a.check:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
    verb = "differ from their data" if a.check else "written"
    print(f"{len(stale)} page(s) {verb}" + (": " + ", ".join(stale) if stale else ""))
    return 1 if a.check and stale else 0


if __name__ == "__main__":
    raise SystemExit(main())
