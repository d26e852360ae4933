"""docs/rate-distortion.md is made of sections, each written by its own script between two markers
(``<!-- section NAME -->`` ... ``<!-- end NAME -->``): a script replaces its own section and leaves the others."""

from __future__ import annotations

from pathlib import Path


def replace_section(page: Path, name: str, text: str, title: str = "") -> None:
    """Put ``text`` between the markers of section ``name`` of ``page`` (appended, after ``title`` when the page
    is new, if the markers are not there yet); every other line of the page is kept."""
    begin, end = f"<!-- section {name} -->", f"<!-- end {name} -->"
    block = f"{begin}\n{text.rstrip()}\n{end}"
    old = page.read_text() if page.exists() else (title.rstrip() + "\n\n" if title else "")
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        new = head + block + rest.split(end, 1)[1]
    else:
        new = old.rstrip() + "\n\n" + block + "\n"
    page.write_text(new)
