"""Modules imported on first use, so that light commands start light.

``torch = lazy_module("torch")`` at the top of a module gives a stand-in whose first attribute access
(``torch.float32``, ``torch.as_tensor(...)``) imports torch (about 2 s here) and forwards to it from then on.
``sdfcodec info``, ``codecs``, ``verify`` of a header and ``--help`` never touch torch, sklearn or scipy, so
they start in a fraction of a second. The stand-in is not put in ``sys.modules``: other libraries that ask
``"torch" in sys.modules`` (numpy's and scikit-learn's array-API checks) keep seeing the truth.

:func:`is_tensor` answers "is this a torch tensor?" without importing torch: if torch was never imported,
nothing can be a tensor.
"""

from __future__ import annotations

import contextlib
import importlib
import signal
import sys
import threading
import types
from typing import Any, Iterator

__all__ = ["lazy_module", "is_tensor", "LazyModule", "lazy_exports"]


class LazyModule(types.ModuleType):
    """A stand-in for the module ``name`` that imports it on first attribute access."""

    def __init__(self, name: str):
        super().__init__(name)
        self.__dict__["_lazy_target"] = None

    def _lazy_load(self) -> types.ModuleType:
        mod = self.__dict__["_lazy_target"]
        if mod is None:
            with _interrupt_after():
                mod = importlib.import_module(self.__name__)
            self.__dict__["_lazy_target"] = mod
        return mod

    def __getattr__(self, attr: str) -> Any:
        # only called for names not in the stand-in's own __dict__: everything of the real module
        return getattr(self._lazy_load(), attr)

    def __dir__(self) -> list[str]:
        return dir(self._lazy_load())

    def __repr__(self) -> str:
        state = "loaded" if self.__dict__["_lazy_target"] is not None else "not loaded yet"
        return f"<lazy module {self.__name__!r} ({state})>"


@contextlib.contextmanager
def _interrupt_after() -> Iterator[None]:
    """Ctrl-C during the block is raised when it ends, not inside it. Measured: torch's import swallows a
    KeyboardInterrupt raised inside it (2 of 8 SIGINTs sent 0.12-0.3 s into ``import torch`` were lost, the
    process ran on and exited 0; 0 of 8 with the interrupt held to the end of the import), so a Ctrl-C while
    a command first touches torch (``sdfcodec encode``: inside the write, 1-3 s under load) did nothing. Only in
    the main thread and under Python's default handler (a caller's own SIGINT handler is left alone)."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    got: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if got:
        old(signal.SIGINT, None)  # Python's default handler: raises KeyboardInterrupt, as the SIGINT would have


def lazy_module(name: str) -> Any:
    """A stand-in for module ``name`` (e.g. ``"torch"``, ``"sklearn.decomposition"``): imported on first
    attribute access. When the module is already imported, that module itself."""
    return sys.modules.get(name) or LazyModule(name)


def is_tensor(x: Any) -> bool:
    """True when ``x`` is a ``torch.Tensor``; never imports torch (no tensor exists before torch is imported)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def lazy_exports(module: str, where: dict[str, str], package: str | None = None) -> tuple[Any, Any]:
    """PEP 562 ``(__getattr__, __dir__)`` for the module ``module`` (its ``__name__``, while it runs): each name
    of ``where`` (name -> module path, relative to ``package``, default ``module``) is imported on first access
    and kept as a plain attribute from then on; ``dir()`` lists the module's ``__all__`` too."""
    namespace = sys.modules[module].__dict__

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where[name], package or module), name)
        namespace[name] = value  # once loaded, no further __getattr__ calls
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(namespace.get("__all__", ())))

    return __getattr__, __dir__
