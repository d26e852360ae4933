"""Every error sdfcodec raises on purpose is an SDFCodecError (issue 14, item 6).

A caller catches one type (``except SDFCodecError``) for everything the project refuses, and still catches the
nearest built-in (``except ValueError``...) because every class mixes one in. The source walk below keeps it
that way: a new ``raise ValueError(...)`` in the package or the built-in plugins fails here, naming file:line.
"""

from __future__ import annotations

import ast
import builtins
from pathlib import Path

import numpy as np
import pytest

import sdfcodec.errors as errors
from sdfcodec.errors import SDFCodecError

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [ROOT / "sdfcodec", ROOT / "plugins"]
BUILTIN_ERRORS = {name for name, obj in vars(builtins).items()
                  if isinstance(obj, type) and issubclass(obj, BaseException)}

# Built-ins that are protocols, not errors the project chose: abstract methods, and the assertion protocol the
# conformance suite (sdfcodec.testing) reports its failures in, as pytest does.
ANYWHERE = {"NotImplementedError", "AssertionError"}
# pydantic turns a ValueError/AssertionError raised in a validator into its ValidationError, which the callers
# convert into an SDFCodecError (FormatError, InvalidValueError); a validator must raise one of those.
VALIDATOR_DECORATORS = {"field_validator", "model_validator", "validator", "root_validator"}
VALIDATOR_ERRORS = {"ValueError", "AssertionError"}
# (enclosing function, exception) pairs that report someone else's failure, not a refusal of ours.
FOREIGN = {
    ("_exchange", "OSError"),  # the errno of a failed renameat2 syscall, raised as os.rename would
    ("make_temp_dir", "OSError"),  # the file system kept colliding or dropping locks, as os.mkdir reports it
}


def _exception_name(node: ast.Raise) -> str | None:
    """The built-in class a ``raise`` names (``raise KeyError(...)`` or ``raise KeyError``), else None."""
    exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
    if isinstance(exc, ast.Name) and exc.id in BUILTIN_ERRORS:
        return exc.id
    return None


def _handled_here(name: str, try_nodes: list[ast.Try]) -> bool:
    """True when an enclosing ``try`` body has a handler for ``name`` (or for every Exception) that does not
    re-raise it: the raise is local control flow (caught and turned into an SDFCodecError, or a conformance
    failure, a few lines down) and never reaches a caller."""
    for t in try_nodes:
        for h in t.handlers:
            types = h.type.elts if isinstance(h.type, ast.Tuple) else [h.type]
            catches = any(ty is None or (isinstance(ty, ast.Name) and ty.id in (name, "Exception", "BaseException"))
                          for ty in types)
            reraises = any(isinstance(n, ast.Raise) and n.exc is None for n in ast.walk(h))
            if catches and not reraises:
                return True
    return False


def _decorator_names(fn: ast.AST) -> set[str]:
    out = set()
    for d in getattr(fn, "decorator_list", []):
        d = d.func if isinstance(d, ast.Call) else d
        out.add(d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", ""))
    return out


def _bare_raises(path: Path, root: Path = ROOT) -> list[str]:
    """``file:line: raise Name`` (file relative to ``root``) for each raise of a bare built-in in ``path`` that
    no rule above allows."""
    found = []

    def visit(node: ast.AST, fn: ast.AST | None, tries: list[ast.Try]) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            fn, tries = node, []  # a try around a def does not catch what the def raises later
        if isinstance(node, ast.Raise) and node.exc is not None and (name := _exception_name(node)):
            fname = getattr(fn, "name", "<module>")
            allowed = (name in ANYWHERE
                       or (fname == "__getattr__" and name == "AttributeError")  # the attribute protocol
                       or (name in VALIDATOR_ERRORS and _decorator_names(fn) & VALIDATOR_DECORATORS)
                       or (fname, name) in FOREIGN
                       or _handled_here(name, tries))
            if not allowed:
                found.append(f"{path.relative_to(root)}:{node.lineno}: raise {name} in {fname}()")
        for field, value in ast.iter_fields(node):
            children = value if isinstance(value, list) else [value]
            for child in children:
                if isinstance(child, ast.AST):
                    # only the try's own body is guarded by its handlers (not the handlers, else or finally)
                    inner = tries + [node] if isinstance(node, ast.Try) and field == "body" else tries
                    visit(child, fn, inner)

    visit(ast.parse(path.read_text(), str(path)), None, [])
    return found


def test_no_bare_builtin_raises():
    """Deliberate errors derive from SDFCodecError: use (or add to sdfcodec/errors.py) the class that mixes in
    the built-in you meant, e.g. InvalidValueError for ValueError."""
    files = sorted(p for src in SOURCES for p in src.rglob("*.py"))
    assert len(files) > 20  # the walk found the package
    bad = [hit for f in files for hit in _bare_raises(f)]
    assert not bad, "raise an sdfcodec.errors class instead of a bare built-in:\n" + "\n".join(bad)


def test_scan_catches_a_bare_raise(tmp_path):
    """The walk itself: it flags a bare built-in and lets the allowed forms through."""
    src = tmp_path / "m.py"
    src.write_text(
        "def f(x):\n"
        "    if x:\n"
        "        raise ValueError('bad')\n"            # flagged
        "    try:\n"
        "        raise KeyError(x)\n"                  # caught below: local control flow
        "    except KeyError:\n"
        "        raise LookupError(x) from None\n"     # flagged: escapes
        "    try:\n"
        "        raise TypeError(x)\n"                 # flagged: the handler re-raises it
        "    except Exception:\n"
        "        raise\n"
        "    raise NotImplementedError\n"
        "def __getattr__(name):\n"
        "    raise AttributeError(name)\n")
    assert _bare_raises(src, tmp_path) == ["m.py:3: raise ValueError in f()", "m.py:7: raise LookupError in f()",
                                           "m.py:9: raise TypeError in f()"]


@pytest.mark.parametrize("name", [n for n in errors.__all__ if not issubclass(getattr(errors, n), Warning)])
def test_error_classes_mix_in_a_builtin(name):
    """Each error is an SDFCodecError and (except the base) also the nearest built-in, so ``except ValueError``
    and friends written before the class existed keep working."""
    cls = getattr(errors, name)
    assert issubclass(cls, SDFCodecError)
    if cls is not SDFCodecError:
        mixed = [b for b in cls.__mro__ if b.__module__ == "builtins" and b not in (Exception, BaseException, object)]
        assert mixed, f"{name} mixes in no built-in exception"


def test_converted_raises_keep_their_builtin():
    """The raises converted in issue 14 are still caught as the built-ins callers used."""
    from sdfcodec.core.sdf import Scene

    with pytest.raises(errors.InvalidValueError, match="at least one primitive"):
        Scene()(np.zeros((1, 3)))
    with pytest.raises(ValueError):
        Scene()(np.zeros((1, 3)))
    assert issubclass(errors.OutOfRangeError, IndexError)
    assert issubclass(errors.MissingDependencyError, ImportError)
    assert issubclass(errors.InputNotFoundError, FileNotFoundError)
    assert issubclass(errors.SamplingError, RuntimeError)
    e = errors.InputNotFoundError(2, "no such input file", "v.npy")
    assert (e.errno, e.strerror, e.filename) == (2, "no such input file", "v.npy")
