"""The compiled rANS path (sdfcodec.core.ans, numba) against constriction 0.5.0 itself: the encoder's words
equal constriction's on random streams, the decoders read arbitrary words exactly as a plain symbol-by-symbol
constriction decode does (what a stream is does not matter to an ANS decoder: every word sequence decodes), and
the observation masks and variable-rate chunks of fused scenes and of the golden maps decode to the same values
on both paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

pytest.importorskip("numba")
constriction = pytest.importorskip("constriction")

from _fused_maps import fused_like  # noqa: E402
from sdfcodec import errors  # noqa: E402
from sdfcodec.core import ans  # noqa: E402
from sdfcodec.core.blocks import split_blocks  # noqa: E402
from sdfcodec.core.sdf import sample_volume  # noqa: E402
from sdfcodec.core.varrate import EntropyModel, decode_chunk, encode_chunk  # noqa: E402
from sdfcodec.map import maskcoder  # noqa: E402
from sdfcodec.map.maskcoder import OFFSETS, decode_mask_rows, encode_mask_rows  # noqa: E402
from sdfcodec.map.observed import pack_mask  # noqa: E402
from sdfcodec.testing import analytic_scene  # noqa: E402

ST = constriction.stream
GOLDEN = Path(__file__).parent / "golden" / "maps"


def _random_words(rng, n: int) -> np.ndarray:
    words = rng.integers(0, 2 ** 32, n, dtype=np.uint64).astype(np.uint32)
    if n:
        words[-1] |= 1  # constriction refuses a last word of 0
    return words


@pytest.fixture
def constriction_only(monkeypatch):
    """The path without numba: the callers ask ans.available() and take constriction's."""
    monkeypatch.setattr(ans, "available", lambda: False)


def test_encoder_words_equal_constrictions():
    rng = np.random.default_rng(1)
    for trial in range(30):
        n = int(rng.integers(1, 4000))
        p = np.clip(rng.random(n) ** rng.uniform(0.1, 8), 1e-12, 1 - 1e-12)
        p[: n // 10] = rng.choice([1e-12, 1 - 1e-12, 0.5], n // 10)  # the extremes a KT count never reaches
        bits = (rng.random(n) < p).astype(np.int32)
        bits[:5] = 1 - bits[:5]  # improbable symbols too
        coder = ST.stack.AnsCoder()
        coder.encode_reverse(bits, ST.model.Bernoulli(perfect=False), p)
        assert np.array_equal(ans.encode(*ans.bernoulli_intervals(bits, p)),
                              np.asarray(coder.get_compressed(), np.uint32)), trial
        k = int(rng.integers(2, 7))
        probs = rng.random((n, k)) ** 4 + 1e-12
        probs /= probs.sum(axis=1, keepdims=True)
        sym = (probs.cumsum(axis=1) < rng.random((n, 1))).sum(axis=1).clip(max=k - 1).astype(np.int32)
        coder = ST.stack.AnsCoder()
        coder.encode_reverse(sym, ST.model.Categorical(perfect=False), probs)
        assert np.array_equal(ans.encode(*ans.categorical_intervals(sym, probs)),
                              np.asarray(coder.get_compressed(), np.uint32)), trial


def _reference_mask_decode(words: np.ndarray, n_rows: int, p_rows: int):
    """The M1 layout (maskcoder's docstring) decoded one symbol at a time by constriction, written from the
    description, not from either decoder: (partial, states (p, 8, 8, 8), voxels (p, 16, 16, 16))."""
    coder = ST.stack.AnsCoder(words) if len(words) else ST.stack.AnsCoder()
    bern, cat = ST.model.Bernoulli(perfect=False), ST.model.Categorical(perfect=False)

    def bit(p1):
        return int(coder.decode(bern, np.array([p1]))[0])

    partial = ([bit(p_rows / n_rows) for _ in range(n_rows)] if p_rows < n_rows else [1] * n_rows)
    states = np.full((p_rows, 8, 8, 8), -1)
    counts = np.zeros((3, 64), np.int64)
    for w in range(22):
        seen = []
        for r in range(p_rows):
            for i, j, k in np.ndindex(8, 8, 8):
                if i + j + k != w:
                    continue
                nb = [states[r, i - 1, j, k] if i else 3, states[r, i, j - 1, k] if j else 3,
                      states[r, i, j, k - 1] if k else 3]
                ctx = nb[0] + 4 * nb[1] + 16 * nb[2]
                c = counts[:, ctx] + 0.5
                states[r, i, j, k] = int(coder.decode(cat, (c / c.sum())[None, :])[0])
                seen.append((states[r, i, j, k], ctx))
        for s, ctx in seen:
            counts[s, ctx] += 1
    per = np.repeat(np.repeat(np.repeat(states, 2, 1), 2, 2), 2, 3)
    vox = np.where(per == 1, 1, 0)
    counts = np.zeros((2, 1 << len(OFFSETS)), np.int64)
    for w in range(46):
        seen = []
        for r in range(p_rows):
            for i, j, k in np.ndindex(16, 16, 16):
                if i + j + k != w or per[r, i, j, k] != 2:
                    continue
                ctx = 0
                for q, (a, b, c_) in enumerate(OFFSETS):
                    x, y, z = i + a, j + b, k + c_
                    inside = 0 <= x < 16 and 0 <= y < 16 and 0 <= z < 16
                    ctx |= (int(vox[r, x, y, z]) if inside else 0) << q
                n0, n1 = counts[0, ctx] + 0.5, counts[1, ctx] + 0.5
                vox[r, i, j, k] = bit(n1 / (n0 + n1))
                seen.append((vox[r, i, j, k], ctx))
        for s, ctx in seen:
            counts[s, ctx] += 1
    return np.array(partial, bool), states.reshape(p_rows, 512), vox


def test_mask_decoder_reads_any_words_as_constriction_does():
    rng = np.random.default_rng(2)
    for trial in range(6):
        n_rows = int(rng.integers(1, 6))
        p_rows = int(rng.integers(1, min(n_rows, 2) + 1))
        words = _random_words(rng, int(rng.integers(0, 300)))
        partial, states, vpad = ans.decode_mask(words, n_rows, p_rows, *maskcoder._flat_waves(),
                                                maskcoder._CUBE_DELTAS, maskcoder._DELTAS)
        rp, rs, rv = _reference_mask_decode(words, n_rows, p_rows)
        assert np.array_equal(partial, rp) and np.array_equal(states, rs), trial
        assert np.array_equal(vpad[:, 1:-1, 1:-1, 1:-1], rv), trial
        assert (states == 2).sum() > 50, trial  # random words give mixed sub-cubes: the voxel stage runs


def _fused_rows() -> np.ndarray:
    vol, obs = fused_like(sample_volume(analytic_scene(), (96, 80, 48), 0.02, truncation=(-0.04, 0.1)))
    blocks = split_blocks(obs.astype(np.float32), fill=1.0).reshape(-1, 16, 16, 16) > 0.5
    return pack_mask(blocks)


def _golden_mask_rows() -> dict[str, np.ndarray]:
    out = {}
    for name in ("coded-mask-pca-8", "lossy-mask-pca-8", "varrate-pca-8", "varrate-compact-pca-8"):
        path = GOLDEN / name / "map.zarr"
        g = zarr.open_group(path, mode="r")
        if "observed" in g and g["observed"].metadata.codecs[0].to_dict().get("name") == maskcoder.MASK_ANS_CODEC:
            out[name] = g["observed"][...].reshape(-1, 512)
    assert out, "no golden map with a coded mask"
    return out


def test_real_masks_decode_the_same_on_both_paths(monkeypatch):
    rng = np.random.default_rng(3)
    cases = {"fused room": _fused_rows(), **_golden_mask_rows(),
             "random rows, some full": np.where(rng.random((30, 1)) < 0.3, 255,
                                                rng.integers(0, 256, (30, 512))).astype(np.uint8)}
    for name, rows in cases.items():
        stream = encode_mask_rows(rows)
        assert np.array_equal(decode_mask_rows(stream, len(rows)), rows), name
        with monkeypatch.context() as m:
            m.setattr(ans, "available", lambda: False)
            assert np.array_equal(decode_mask_rows(stream, len(rows)), rows), name
            assert encode_mask_rows(rows) == stream, name  # constriction's encoder writes the same bytes
        # and the words themselves, stage by stage, as constriction reads them
        words = np.frombuffer(stream[6:], "<u4").astype(np.uint32)
        p_rows = int(np.frombuffer(stream[2:6], "<u4")[0])
        if p_rows:
            got = ans.decode_mask(words, len(rows), p_rows, *maskcoder._flat_waves(), maskcoder._CUBE_DELTAS,
                                  maskcoder._DELTAS)
            ref = maskcoder._decode_words(words, len(rows), p_rows)
            assert all(np.array_equal(a, b) for a, b in zip(got, ref)), name


def test_bit_decoder_takes_an_extra_context():
    """Ternary neighbour contexts (first neighbour most significant, as a caller might weigh them) plus an extra
    per-voxel array: encoded here by constriction, decoded by ans.Decoder.bits."""
    rng = np.random.default_rng(4)
    edge, n = 12, 900
    grid = np.full(edge ** 3, 2, np.int64)  # 2: not coded
    coords = np.unique(rng.integers(1, edge - 1, (n, 3)), axis=0)
    wave = coords.sum(axis=1)
    order = np.lexsort((np.ravel_multi_index(coords.T, (edge,) * 3), wave))
    at = np.ravel_multi_index(coords[order].T, (edge,) * 3)
    bounds = np.searchsorted(wave[order], np.arange(wave.max() + 2))
    deltas = np.array([-edge * edge, -edge, -1, -edge - 1])
    weights = 3 ** np.arange(len(deltas))[::-1]
    extra = rng.integers(0, 4, len(at)) * 81
    truth = (rng.random(len(at)) < 0.3).astype(np.int64)
    grid_true = grid.copy()
    grid_true[at] = truth
    counts = np.zeros((2, 324), np.int64)
    ctx_all = (grid_true[at[:, None] + deltas] * weights).sum(axis=1) + extra
    p = np.empty(len(at))
    for w in range(len(bounds) - 1):
        a, b = bounds[w], bounds[w + 1]
        c = counts[:, ctx_all[a:b]] + 0.5
        p[a:b] = c[1] / (c[0] + c[1])
        np.add.at(counts, (truth[a:b], ctx_all[a:b]), 1)
    coder = ST.stack.AnsCoder()
    coder.encode_reverse(truth.astype(np.int32), ST.model.Bernoulli(perfect=False), p)
    dec = ans.Decoder(np.asarray(coder.get_compressed(), np.uint32))
    dec.bits(grid, at, bounds, deltas, weights, 324, extra)
    assert np.array_equal(grid[at], truth) and dec.is_empty()
    with pytest.raises(ValueError, match="outside"):
        ans.Decoder(np.asarray(coder.get_compressed(), np.uint32)).bits(grid.copy(), at, bounds, deltas, weights,
                                                                          81, extra)


def _random_model(rng, d: int) -> EntropyModel:
    return EntropyModel(center=rng.integers(-3, 4, d), decay=rng.uniform(0.05, 0.999, d),
                        extent=rng.choice([0, 1, 5, 60, 3000], d), lengths=rng.integers(0, 50, d + 1))


def test_chunk_decoder_equals_constriction(monkeypatch):
    rng = np.random.default_rng(5)
    for trial in range(8):
        d, n = int(rng.integers(1, 24)), int(rng.integers(0, 60))
        model = _random_model(rng, d)
        # any words (what a reader meets in a corrupted chunk whose CRC held): both paths read the same values
        words = _random_words(rng, int(rng.integers(0, 400)))
        got = decode_chunk(words, n, model)
        with monkeypatch.context() as m:
            m.setattr(ans, "available", lambda: False)
            ref = decode_chunk(words, n, model)
            # and a real chunk: codes within each element's extent, prefixes of random lengths
        e = np.maximum(model.extent, 1)
        k = rng.integers(0, d + 1, n)
        q = np.where(np.arange(d) < k[:, None], model.center + rng.integers(-e, e + 1, (n, d)), 0).astype(np.int32)
        real = encode_chunk(q, k, model)
        assert np.array_equal(got, ref), trial
        assert np.array_equal(decode_chunk(real, n, model), q), trial
        assert np.array_equal(decode_chunk(real, n, model, level=max(d - 2, 0)), q[:, :max(d - 2, 0)]), trial


def test_a_trailing_zero_word_fails_alike_on_both_paths(monkeypatch):
    rows = _fused_rows()
    stream = encode_mask_rows(rows) + b"\0\0\0\0"
    with pytest.raises(errors.ChecksumError, match="never ends in a zero word") as fast:
        decode_mask_rows(stream, len(rows))
    monkeypatch.setattr(ans, "available", lambda: False)
    with pytest.raises(errors.ChecksumError, match="never ends in a zero word") as slow:
        decode_mask_rows(stream, len(rows))
    assert str(fast.value) == str(slow.value)


@pytest.mark.parametrize("law", ["peaked", "flat", "wide"])
def test_categorical_decoder_reads_any_words_as_constriction_does(law):
    """The slot table's packed entries (a slot inside one symbol) and its fallback (a slot across symbols, and
    every symbol from 2^15 on) read arbitrary words as constriction's ``Categorical(perfect=False)`` does: a
    peaked law (most slots inside one symbol), a flat one over 3,000 symbols (most slots across symbols), and a
    peaked one over 40,000 symbols (slots inside symbols past the packed entries' 2^15)."""
    rng = np.random.default_rng(11)
    size = {"peaked": 79, "flat": 3000, "wide": 40000}[law]
    probs = rng.dirichlet(np.full(size, 5.0 if law == "flat" else 0.2))  # "wide": heavy symbols past 2^15
    cdf = ans.categorical_cdf(probs)
    model = ST.model.Categorical(probs, perfect=False)
    for n in (0, 1, 7, 400):
        words = _random_words(rng, n)
        want = ST.stack.AnsCoder(words).decode(model, 3 * n + 5)
        dec = ans.Decoder(words)
        got = dec.categorical(3 * n + 5, cdf)
        assert np.array_equal(got, want), (law, n)
        ahead = ans.symbols_ahead(ans.Decoder(words).categorical_ahead(3 * n + 5, cdf), 3 * n + 5)[0]
        assert np.array_equal(ahead, want), (law, n)
