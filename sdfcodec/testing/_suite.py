"""Running the named checks: one at a time (a pytest parametrisation), all at once (a report of every
failure), or as ``check_codec`` (all of them, one error listing every failure).

Every check runs on its own copy of a fitted reference: the codec given is deep-copied (or rebuilt from its
config and state where it cannot be copied) and, when it ``requires_fit`` and is not fitted, the copy is
fitted once on the test blocks and shared, as the reference, by all checks of that codec.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence, Union

import numpy as np
import torch

from ..codec import Codec
from ..errors import InvalidValueError
from ..registry import get_codec
from ._checks import CHECKS, Case, CheckOptions
from ._data import analytic_blocks

__all__ = ["CodecCheck", "CheckResult", "CheckReport", "codec_checks", "run_codec_checks",
           "parametrize_codec_checks", "check_codec"]

#: a codec, or a function of no arguments that builds one (called once, when its first check runs)
CodecLike = Union[Codec, Callable[[], Codec]]
_FUNCS = dict(CHECKS)


@dataclass
class CheckResult:
    """The outcome of one check: ``passed``, the failure ``message`` ("" when it passed), measurements and the
    wall time it took (``seconds``; the first check of a codec includes building and fitting it)."""

    name: str
    passed: bool
    message: str = ""
    details: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    error: BaseException | None = field(default=None, repr=False, compare=False)


@dataclass
class CheckReport:
    """Every check's :class:`CheckResult` for one codec (``codec`` is its repr)."""

    codec: str
    results: list[CheckResult]

    @property
    def failures(self) -> list[CheckResult]:
        """The checks that failed, in the order they ran."""
        return [r for r in self.results if not r.passed]

    @property
    def ok(self) -> bool:
        """True when every check passed."""
        return not self.failures

    def summary(self) -> str:
        """One line per failed check (``name: message``) under a count; "" when every check passed."""
        if self.ok:
            return ""
        lines = [f"{len(self.failures)} of {len(self.results)} conformance checks failed for {self.codec}:"]
        lines += [f"  {r.name}: {r.message}" for r in self.failures]
        return "\n".join(lines)

    def raise_on_failure(self) -> None:
        """Raise one ``AssertionError`` listing every failed check (nothing when all passed)."""
        if not self.ok:
            raise AssertionError(self.summary()) from self.failures[0].error

    def as_dict(self) -> dict[str, Any]:
        """The report ``check_codec`` returns: ``codec``, ``checks`` (names of the checks passed, with spaces:
        ``"round trip"``), ``failed`` (names), and the measurements (``mse``, ``prefix_mse``...)."""
        out: dict[str, Any] = {"codec": self.codec, "checks": [r.name.replace("_", " ") for r in self.results
                                                              if r.passed],
                               "failed": [r.name for r in self.failures]}
        for r in self.results:
            out.update(r.details)
        return out


def _options(blocks: Any, golden: str | Path | None, devices: Sequence[str] | None, large_batch: int,
             atol: float, max_levels: int) -> CheckOptions:
    x = analytic_blocks(256) if blocks is None else np.asarray(blocks, dtype=np.float32)
    devs = tuple(devices) if devices is not None else ("cpu",) + (("cuda",) if torch.cuda.is_available() else ())
    return CheckOptions(blocks=x, atol=atol, devices=devs, large_batch=large_batch, max_levels=max_levels,
                        golden=None if golden is None else Path(golden))


def _copy(codec: Codec) -> Codec:
    """A copy a check may change freely: a deep copy, or a rebuild from config + state when copying fails."""
    try:
        return copy.deepcopy(codec)
    except Exception:  # noqa: BLE001 - e.g. a handle that cannot be copied; the rebuild is checked elsewhere
        state, fresh = codec.state_dict(), get_codec(codec.get_config())
        return fresh.load_state_dict(copy.deepcopy(state)) if state else fresh


class _Subject:
    """One codec under test: builds and fits the shared reference once, hands every check a fresh copy."""

    def __init__(self, entry: CodecLike, options: CheckOptions, fit_in_place: bool = False):
        self.entry, self.options, self._fit_in_place = entry, options, fit_in_place
        self._reference: tuple[Codec, bool | None] | None = None
        self._failure: BaseException | None = None

    def _prepare(self) -> tuple[Codec, bool | None]:
        if self._failure is not None:
            raise self._failure
        if self._reference is None:
            try:
                codec = self.entry if isinstance(self.entry, Codec) else self.entry()
                if not isinstance(codec, Codec):
                    raise TypeError(f"expected an sdfcodec.Codec, got {type(codec).__name__}")
                ref = codec if self._fit_in_place else _copy(codec)
                fit_returned_self = None
                if type(ref).requires_fit and not ref.is_fitted:
                    fit_returned_self = ref.fit(self.options.blocks) is ref
                self._reference = (ref, fit_returned_self)
            except Exception as e:  # noqa: BLE001 - every check of this codec reports it
                self._failure = AssertionError(f"preparing the codec (build, fit) raised {type(e).__name__}: {e}")
                self._failure.__cause__ = e
                raise self._failure from e
        return self._reference

    def label(self) -> str:
        return repr(self.entry) if isinstance(self.entry, Codec) else getattr(self.entry, "__name__", "codec")

    def run(self, name: str, regen_golden: bool = False) -> CheckResult:
        t0 = time.perf_counter()
        try:
            ref, fit_returned_self = self._prepare()
            case = Case(_copy(ref), self.options, fit_returned_self, regen_golden)
            out = _FUNCS[name](case) or {}
            result = CheckResult(name, True, details={**case.report, **out})
        except AssertionError as e:
            result = CheckResult(name, False, str(e) or "assertion failed", error=e)
        except Exception as e:  # noqa: BLE001 - an unexpected error is this check's failure
            result = CheckResult(name, False, f"raised {type(e).__name__}: {e}", error=e)
        result.seconds = time.perf_counter() - t0
        return result


class CodecCheck:
    """One named conformance check bound to a codec (and its options). Call it to run it on a fresh copy:
    ``check(codec, regen_golden=False)`` raises ``AssertionError`` on failure and returns its measurements."""

    __slots__ = ("name", "_subject")

    def __init__(self, name: str, subject: _Subject):
        self.name, self._subject = name, subject

    def __call__(self, codec: CodecLike | None = None, *, regen_golden: bool = False) -> dict[str, Any]:
        """Run the check on a copy of ``codec`` (default: the codec it was made for; the same object reuses
        its fitted reference). ``regen_golden`` rewrites the golden fixture instead of checking it."""
        subject = self._subject
        if codec is not None and codec is not subject.entry:
            subject = _Subject(codec, subject.options)
        result = subject.run(self.name, regen_golden)
        if not result.passed:
            raise AssertionError(f"{self.name}: {result.message}") from result.error
        return result.details

    def __repr__(self) -> str:
        return f"<conformance check {self.name!r} of {self._subject.label()}>"


def _names(golden: Any) -> list[str]:
    return [name for name, _ in CHECKS if name != "golden_fixture" or golden is not None]


def codec_checks(codec: CodecLike, *, golden: str | Path | None = None, blocks: Any = None,
                 devices: Sequence[str] | None = None, large_batch: int = 4096, atol: float = 1e-5,
                 max_levels: int = 512) -> Iterator[tuple[str, CodecCheck]]:
    """The conformance checks of ``codec`` as ``(name, check)`` pairs, in the order they run.

    Args:
        codec: an instance (fitted or not), or a function of no arguments that builds one. A codec that
            ``requires_fit`` and is not fitted is fitted once, as a copy, on ``blocks``.
        golden: a golden fixture directory (config, state, input, codes, decoded): adds ``golden_fixture``.
        blocks: normalised test blocks ``(N, 16, 16, 16)``, N >= 8; default: 256 exact analytic blocks.
        devices: torch devices whose results are compared with numpy's; default ``cpu`` (+ ``cuda`` when
            available). The ``meta`` device is always checked (``meta_device``).
        large_batch: size of the large-batch check.
        atol: tolerance of numerical comparisons (normalised units).
        max_levels: how many prefix levels to decode at most (all of them for codes up to this length).
    """
    subject = _Subject(codec, _options(blocks, golden, devices, large_batch, atol, max_levels))
    for name in _names(golden):
        yield name, CodecCheck(name, subject)


def _run_all(subject: _Subject, golden: Any, regen_golden: bool) -> CheckReport:
    return CheckReport(subject.label(), [subject.run(name, regen_golden) for name in _names(golden)])


def run_codec_checks(codec: CodecLike, *, golden: str | Path | None = None, regen_golden: bool = False,
                     blocks: Any = None, devices: Sequence[str] | None = None, large_batch: int = 4096,
                     atol: float = 1e-5, max_levels: int = 512) -> CheckReport:
    """Run every check of :func:`codec_checks` (same arguments), each on its own copy, and report them all:
    a failing check never stops the others. ``codec`` itself is not modified. ``regen_golden`` rewrites the
    golden fixture from the codec instead of checking it (format changes only)."""
    subject = _Subject(codec, _options(blocks, golden, devices, large_batch, atol, max_levels))
    return _run_all(subject, golden, regen_golden)


def check_codec(codec: Codec, *, blocks: np.ndarray | None = None, golden: str | Path | None = None,
                regen_golden: bool = False, devices: list[str] | None = None, large_batch: int = 4096,
                atol: float = 1e-5) -> dict[str, Any]:
    """Run every conformance check on ``codec`` and raise one ``AssertionError`` listing every failure;
    return the report as a dict (``checks`` passed, measured ``mse``, ``prefix_mse``...).

    Args:
        codec: an instance. If it ``requires_fit`` and is not fitted, it is fitted (in place) on ``blocks``.
        blocks: normalised test blocks ``(N, 16, 16, 16)``; default: 256 exact analytic blocks.
        golden: a directory with a frozen fixture (config, state, input, codes, decoded). The codec rebuilt
            from it must reproduce the codes and decoded blocks. Missing files fail unless ``regen_golden``.
        regen_golden: (re)write the fixture from ``codec`` instead of checking it. Only for format changes.
        devices: torch devices to compare with numpy; default ``cpu`` plus ``cuda`` when available.
        large_batch: size of the large-batch check.
        atol: tolerance of numerical comparisons (normalised units).
    """
    subject = _Subject(codec, _options(blocks, golden, devices, large_batch, atol, 512), fit_in_place=True)
    report = _run_all(subject, golden, regen_golden)
    report.raise_on_failure()
    return report.as_dict()


def _label(entry: CodecLike, i: int) -> str:
    if isinstance(entry, Codec):
        try:
            return f"{entry.codec_id}-{entry.code_size}"
        except Exception:  # noqa: BLE001 - a broken codec still gets an id; its checks say what is wrong
            return str(getattr(entry, "codec_id", f"codec{i}"))
    name = getattr(entry, "__name__", "")
    return name if name and name != "<lambda>" else f"codec{i}"


def parametrize_codec_checks(codecs: CodecLike | Sequence[CodecLike], *,
                             golden: str | Path | Sequence[str | Path | None] | None = None,
                             ids: Sequence[str] | None = None, **options: Any) -> Any:
    """A ``pytest.mark.parametrize`` over ``("codec", "check")``: one test per (codec, check), with ids like
    ``pca-32-round_trip``. Use it as

        @parametrize_codec_checks([MyCodec(code_size=32)], golden=[GOLDEN / "mycodec-32"])
        def test_conformance(codec, check, regen_golden):
            check(codec, regen_golden=regen_golden)

    Args:
        codecs: codecs (or functions of no arguments building them, called when their first check runs).
        golden: one fixture directory per codec (None for none), or one directory for a single codec.
        ids: one label per codec (default ``{codec_id}-{code_size}``, or the builder function's name).
        options: passed to :func:`codec_checks` (``blocks``, ``devices``, ``atol``...).
    """
    import pytest

    entries = [codecs] if isinstance(codecs, Codec) or callable(codecs) else list(codecs)
    goldens = list(golden) if isinstance(golden, (list, tuple)) else [golden] * len(entries)
    if len(goldens) != len(entries) or (golden is not None and not isinstance(golden, (list, tuple))
                                        and len(entries) != 1):
        raise InvalidValueError(f"golden: give one directory (or None) per codec; {len(entries)} codecs, "
                                f"golden={golden!r}")
    labels = list(ids) if ids is not None else [_label(e, i) for i, e in enumerate(entries)]
    if ids is None:  # the same codec id twice gets a counter
        labels = [lb if labels.count(lb) == 1 else f"{lb}-{i}" for i, lb in enumerate(labels)]
    params = [pytest.param(entry, check, id=f"{label}-{name}")
              for entry, g, label in zip(entries, goldens, labels)
              for name, check in codec_checks(entry, golden=g, **options)]
    return pytest.mark.parametrize(("codec", "check"), params)
