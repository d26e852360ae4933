"""Every command's ``--help`` reads well (issue 44, item 2): paragraphs wrap at the terminal's width, not at the
source's line breaks; no type name where it says nothing (``<bool>`` on a flag); every option described."""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from sdfcodec.cli import app

WIDTH = 100
COMMANDS = sorted(typer.main.get_command(app).commands)  # type: ignore[attr-defined]


def _help(*args: str) -> str:
    r = CliRunner().invoke(app, [*args, "--help"], env={"COLUMNS": str(WIDTH), "TERMINAL_WIDTH": str(WIDTH)})
    assert r.exit_code == 0, r.output
    return r.output


def _description(text: str) -> list[list[str]]:
    """The paragraphs of the help's prose (between the usage line and the first panel), as lists of lines."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if "Usage:" in line) + 1
    end = next((i for i, line in enumerate(lines) if line.lstrip().startswith("╭")), len(lines))
    paragraphs, current = [], []
    for line in lines[start:end]:
        if line.strip():
            current.append(line.strip())
        elif current:
            paragraphs.append(current)
            current = []
    return paragraphs + ([current] if current else [])


def hard_breaks(text: str, width: int = WIDTH) -> list[tuple[str, str]]:
    """Lines of the prose broken mid-sentence where the next word would still have fitted: a line ending without
    punctuation, followed in the same paragraph by a line starting in lower case, whose first word fits on it
    (rich pads the prose by one column either side)."""
    found = []
    for para in _description(text):
        for a, b in zip(para, para[1:]):
            first = b.split()[0]
            if not re.search(r"[.:;!?)]$", a) and b[0].islower() and len(a) + 1 + len(first) <= width - 2:
                found.append((a, b))
    return found


def test_hard_breaks_are_found():
    """The check itself: it finds a break in a hand-made help and none in a paragraph rich wrapped by width."""
    broken = "Usage: x\n\n Fuse a sequence into a map. With this flag the fusion is online and\n memory-bounded.\n"
    wrapped = "Usage: x\n\n " + "word " * 19 + "word\n more words here.\n"
    assert hard_breaks(broken) == [("Fuse a sequence into a map. With this flag the fusion is online and",
                                    "memory-bounded.")]
    assert hard_breaks(wrapped) == []


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help_wraps_by_paragraph_and_shows_no_bool(command):
    text = _help(*([command] if command else []))
    assert hard_breaks(text) == [], f"sdfcodec {command} --help breaks a paragraph mid-sentence"
    assert "<bool>" not in text and "<str>" not in text, f"sdfcodec {command} --help shows a type that says nothing"
    assert max(len(line) for line in text.splitlines()) <= WIDTH  # rendered at the width asked for


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_is_described(command):
    """Every argument and option of every command has help (``--overwrite`` and ``--json`` had none on several),
    and the help shows it."""
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    missing = [p.opts[0] if p.opts else p.name for p in cmd.params if not (getattr(p, "help", None) or "").strip()]
    assert missing == [], f"sdfcodec {command}: no help for {missing}"
    text = _help(command)
    for p in cmd.params:
        if p.param_type_name == "option" and not getattr(p, "hidden", False):  # hidden: an old spelling, on purpose
            # the first word of its help sits on the option's row of the panel
            name = max(p.opts, key=len)
            # the option's own row (its name a few spaces in), not a wrapped help line that mentions it
            own = re.compile(rf"│\s{{1,5}}(\*\s+)?{re.escape(name)}(\s|,)")
            row = next(line for line in text.splitlines() if own.match(line))
            assert p.help.split()[0] in row, (command, name, row)


@pytest.mark.parametrize("command", COMMANDS)
def test_no_help_text_is_lost_as_markup(command):
    """Every word of every option's help reaches the screen: typer renders help as rich markup, where a bracketed
    phrase starting with a letter (``[default: with raw ...]``) is a style tag and silently disappears (fuse's
    ``--keep-weights`` lost its whole default that way)."""
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    shown = set(re.findall(r"[A-Za-z]{3,}", _help(command)))
    for p in (p for p in cmd.params if not getattr(p, "hidden", False)):
        lost = set(re.findall(r"[A-Za-z]{3,}", getattr(p, "help", None) or "")) - shown
        assert not lost, f"sdfcodec {command} {p.name}: {sorted(lost)} of its help is not shown"


@pytest.mark.parametrize("command", COMMANDS)
def test_no_option_name_is_cut(command):
    """At 80 columns every option's names show whole: fuse's four spellings of --keep-weights made rich cut them
    ("--keep-weights,--we…") and squeeze every option's help into a narrow column."""
    r = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "80", "TERMINAL_WIDTH": "80"})
    assert r.exit_code == 0 and "…" not in r.output, r.output


def test_fuse_still_takes_the_older_weights_flag(tmp_path):
    """--weights/--no-weights, hidden from the help, still parse as --keep-weights/--no-keep-weights; the two
    spellings contradicting each other is one line, not a silent pick."""
    cmd = typer.main.get_command(app).commands["fuse"]  # type: ignore[attr-defined]
    ctx = cmd.make_context("fuse", ["seq", "out.sdfz", "--no-weights"])
    assert ctx.params["weights_alias"] is False and ctx.params["weights"] is None
    r = CliRunner().invoke(app, ["fuse", str(tmp_path / "seq"), str(tmp_path / "o.sdfz"), "--keep-weights",
                                 "--no-weights"])
    assert r.exit_code == 1 and "contradict each other" in r.stderr and not (tmp_path / "o.sdfz").exists()
