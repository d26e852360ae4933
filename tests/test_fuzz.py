"""Fuzzing untrusted maps (issue 8): hypothesis mutates the header, the arrays' metadata and the chunk bytes of
a valid map, then opens, reads, decodes and verifies it. Every call must either work or raise one of
sdfcodec's own errors (SDFCodecError): any other exception, a hang, or an allocation past the memory bound is
a bug. Bounded: a fixed number of examples (derandomized, so CI sees the same ones), a per-example time
limit, and an address-space limit (RLIMIT_AS) a little above what the process already uses. The scale fuzzers at
the end of the file (issue 40) run thousands of cases over headers, chunks and command lines in the slow suite.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import tempfile
import time
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

import sdfcodec
from sdfcodec.errors import SDFCodecError
from sdfcodec.testing import analytic_blocks
from sdfcodec.map.verify import verify_map

VS, TRUNC = 0.02, (-0.04, 0.1)
LIMIT = 64 << 20  # max_decode_bytes for the fuzzed reads: every allocation the header could ask for is below it
# the geometry fuzzer's limit: a read may touch at most 1024 chunks of at most 4 MiB. Its grids go up to 2^31
# blocks a side, so with LIMIT the reads it allows (16384 chunks, re-read by each of a dozen calls) made single
# cases take 20-40 s; a smaller limit puts the same checks at the same places and bounds the work that passes them
GEOMETRY_LIMIT = 4 << 20
HEADROOM = 2 << 30  # address space allowed beyond what the process uses when the fuzzing starts
PER_EXAMPLE_S = 20
# per fuzz test: cases run and their outcomes; CASES: (seconds, test, case) of every case, for the slow-case report
COUNTS: dict[str, dict[str, int]] = {}
CASES: list[tuple[float, str, str]] = []
# no shrinking: it can take minutes on a failure; the report still shows every draw of the failing case
# SDFCODEC_FUZZ_EXAMPLES=2000 make test for a long run; CI's default keeps the file near a minute
EXAMPLES = int(os.environ.get("SDFCODEC_FUZZ_EXAMPLES", "60"))
EXPECTED = {"header": EXAMPLES, "array_metadata": EXAMPLES, "chunk_bytes": EXAMPLES, "codes_and_state_values": EXAMPLES,
            "geometry": max(1, EXAMPLES // 2)}  # cases each fuzz test runs (hypothesis's max_examples)
SETTINGS = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                    phases=(Phase.explicit, Phase.generate),
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                           HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def base_map(tmp_path_factory) -> Path:
    """A small valid map: pca-8 codes over 2x2x2-block chunks (prefix levels 4, 8), empties, weights."""
    codec = sdfcodec.get_codec("pca", code_size=8).fit(analytic_blocks(200, seed=4))
    path = tmp_path_factory.mktemp("fuzz") / "base.sdfz"
    blocks = analytic_blocks(6, seed=5) * (TRUNC[1] - TRUNC[0]) + TRUNC[0]
    coords = [[0, 0, 0], [1, 0, 0], [2, 1, 0], [0, 1, 1], [2, 0, 1], [1, 1, 1]]
    # keep_weights: a lossy map drops its weights by default (sdfcodec.map.weights); kept, they are uint8 counts.
    # No integrity manifest: the fuzzers test the checks under it (every mutated chunk would fail its digest;
    # tests/test_manifest.py fuzzes manifests)
    with sdfcodec.create_map(path, codec=codec, voxel_size=VS, truncation=TRUNC, chunk_blocks=2, chunk_code=4,
                             keep_weights=True, manifest=False) as m:
        m.write_blocks(coords, blocks, weights=np.ones((6, 16, 16, 16), np.float32))
        m.mark_empty([[1, 0, 1]])
    assert verify_map(path).ok
    return path


@pytest.fixture(scope="module")
def bounded_memory():
    """Limit the address space for the fuzz tests: a reader that tried to allocate gigabytes fails loudly."""
    status = Path("/proc/self/status")
    if not status.exists():
        yield
        return
    vm = next(int(line.split()[1]) * 1024 for line in status.read_text().splitlines() if line.startswith("VmSize"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = vm + HEADROOM
    if hard != resource.RLIM_INFINITY and hard < limit:
        limit = hard
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang(f"an operation took more than {PER_EXAMPLE_S} s")


def _exercise(path: Path, limit: int = LIMIT) -> tuple[str, bool]:
    """Everything a reader does with a map (reading at most ``limit`` bytes at once). Returns "worked" or
    "refused" (an SDFCodecError somewhere), and whether the map opened and its block states could be read (the
    checks past open_map ran on data)."""
    outcome = "worked"

    def attempt(fn):
        nonlocal outcome
        try:
            return fn()
        except SDFCodecError:
            outcome = "refused"
            return None

    m = attempt(lambda: sdfcodec.open_map(path, max_decode_bytes=limit))
    read = False
    if m is not None:
        read = attempt(m.block_states) is not None
        attempt(m.count_states)
        attempt(m.read_codes)
        attempt(lambda: m.read_codes(level=4))
        attempt(lambda: list(m.iter_codes()))
        attempt(m.decode_region)
        attempt(lambda: m.decode_region(((0, 16), (0, 16), (0, 16)), level=4))
        attempt(lambda: list(m.iter_blocks()))
        attempt(m.info)
        attempt(lambda: m.read_weights([[0, 0, 0]]))
        m.close()
    rep = verify_map(path, max_decode_bytes=limit, decode_blocks=64)
    internal = [p for p in rep.problems if p.where == "verify"]
    assert not internal, internal  # verify itself must not fail on any input
    return outcome, read


def _run_case(base: Path, mutate, test: str, case: str = "", limit: int = LIMIT) -> None:
    """Copy the map, ``mutate`` the copy, exercise it under the time limit, and count the outcome under ``test``
    (``case`` describes the draw for the slow-case report)."""
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="sdfcodec-fuzz-"))
    try:
        path = tmp / "m.sdfz"
        shutil.copytree(base, path)
        mutate(path)
        old = signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, PER_EXAMPLE_S)
        try:
            outcome, read = _exercise(path, limit)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
        counts = COUNTS.setdefault(test, {"cases": 0, "worked": 0, "refused": 0, "read": 0})
        counts["cases"] += 1
        counts[outcome] += 1
        counts["read"] += read
        CASES.append((time.perf_counter() - t0, test, case))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# -- strategies ---------------------------------------------------------------------------------------------

SPECIAL = [0, 1, -1, 2, 3, 4, 8, 16, 255, 256, 4096, 2**31 - 1, 2**31, 2**32, 2**40, 2**53, 2**63, 2**64, -2**63,
           10**30, 0.5, -0.0, 1e-300, 1e308, "", "float64", "float16", "uint8", "int8", "bool", "complex64", "|O",
           "string", "numcodecs.pickle", "sharding_indexed", "transpose", "vlen-utf8", "blosc", "zstd", "gzip",
           "crc32c", "bytes", "c", "v2", ".", "/", "../codes", "pca", "raw", "ae", "sdfcodec-map", "regular",
           "fusion-weights", "array", "group"]
leaf = st.one_of(st.none(), st.booleans(), st.sampled_from(SPECIAL),
                 st.integers(min_value=-2**70, max_value=2**70), st.floats(allow_nan=True, allow_infinity=True),
                 st.text(max_size=8))
json_value = st.recursive(leaf, lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids,
                                                                                             max_size=3),
                          max_leaves=8)


def _paths(doc, prefix=()):
    """Every path (tuple of keys/indices) into a JSON document, containers included."""
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, prefix + (i,))
    return out


def _apply(doc, path, how: str, value):
    if not path:
        return value if how == "replace" else doc
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    last = path[-1]
    if how == "replace":
        parent[last] = value
    elif how == "delete":
        del parent[last]
    elif how == "insert" and isinstance(parent, dict):
        parent[f"x{len(parent)}"] = value
    elif how == "insert" and isinstance(parent, list):
        parent.insert(last, value)
    elif how == "wrap":
        parent[last] = [parent[last]]
    return doc


def _meta_files(base: Path) -> list[str]:
    return sorted(str(p.relative_to(base)) for p in base.rglob("zarr.json"))


def _chunk_files(base: Path) -> list[str]:
    return sorted(str(p.relative_to(base)) for p in base.rglob("*") if p.is_file() and p.name != "zarr.json")


@SETTINGS
@given(data=st.data())
def test_fuzz_header(base_map, bounded_memory, data):
    """Mutate the sdfcodec header (the group attribute): values, types, missing and unknown fields."""
    doc = json.loads((base_map / "zarr.json").read_text())
    header = doc["attributes"]["sdfcodec"]
    edits = data.draw(st.integers(1, 3))
    for _ in range(edits):
        path = data.draw(st.sampled_from(_paths(header)))
        how = data.draw(st.sampled_from(["replace", "replace", "delete", "insert", "wrap"]))
        header = _apply(header, path, how, data.draw(json_value))
    doc["attributes"]["sdfcodec"] = header

    def mutate(p: Path) -> None:
        (p / "zarr.json").write_text(json.dumps(doc))

    _run_case(base_map, mutate, "header")


@SETTINGS
@given(data=st.data())
def test_fuzz_array_metadata(base_map, bounded_memory, data):
    """Mutate the Zarr metadata of the arrays and groups: shapes, chunk grids, data types, codecs, fill values."""
    name = data.draw(st.sampled_from(_meta_files(base_map)))
    doc = json.loads((base_map / name).read_text())
    edits = data.draw(st.integers(1, 2))
    for _ in range(edits):
        focus = [p for p in _paths(doc) if p and p[0] in ("shape", "chunk_grid", "data_type", "codecs", "fill_value",
                                                          "chunk_key_encoding", "node_type", "zarr_format")]
        path = data.draw(st.sampled_from(focus or _paths(doc)))
        how = data.draw(st.sampled_from(["replace", "replace", "delete", "insert", "wrap"]))
        doc = _apply(doc, path, how, data.draw(json_value))
    raw = json.dumps(doc)
    if data.draw(st.integers(0, 9)) == 0:
        raw = raw[: data.draw(st.integers(0, len(raw)))]  # not even JSON

    def mutate(p: Path) -> None:
        (p / name).write_text(raw)

    _run_case(base_map, mutate, "array_metadata", name)


@SETTINGS
@given(data=st.data())
def test_fuzz_chunk_bytes(base_map, bounded_memory, data):
    """Mutate chunk files: bit flips, truncation, garbage, deletion, and tampered Blosc headers, with the CRC32C
    recomputed half the time so the damage reaches the decompressor and the decoders."""
    name = data.draw(st.sampled_from(_chunk_files(base_map)))
    orig = (base_map / name).read_bytes()
    how = data.draw(st.sampled_from(["flip", "truncate", "extend", "garbage", "delete", "blosc-header", "zero"]))
    b = bytearray(orig)
    if how == "flip" and b:
        i = data.draw(st.integers(0, len(b) - 1))
        b[i] ^= 1 << data.draw(st.integers(0, 7))
    elif how == "truncate":
        b = b[: data.draw(st.integers(0, max(0, len(b) - 1)))]
    elif how == "extend":
        b += data.draw(st.binary(min_size=1, max_size=64))
    elif how == "garbage":
        b = bytearray(data.draw(st.binary(max_size=128)))
    elif how == "blosc-header" and len(b) >= 16:
        b[4:16] = data.draw(st.binary(min_size=12, max_size=12))
    elif how == "zero":
        b = bytearray(len(b))
    if how != "delete" and len(b) >= 4 and data.draw(st.booleans()):
        body = bytes(b[:-4])
        b = bytearray(body + google_crc32c.value(body).to_bytes(4, "little"))

    def mutate(p: Path) -> None:
        if how == "delete":
            (p / name).unlink()
        else:
            (p / name).write_bytes(bytes(b))

    _run_case(base_map, mutate, "chunk_bytes", f"{how} {name}")


@SETTINGS
@given(data=st.data())
def test_fuzz_codes_and_state_values(base_map, bounded_memory, data):
    """Write hostile *values* with valid checksums: NaN/Inf/huge codes, reserved states, altered codec state."""
    import zarr

    which = data.draw(st.sampled_from(["codes", "state", "codec/components", "codec/mean", "weights"]))
    value = data.draw(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.integers(0, 255)))
    index = data.draw(st.integers(0, 2**16))

    def mutate(p: Path) -> None:
        arr = zarr.open_array(str(p / which), mode="r+")
        flat = np.asarray(arr[...]).copy()
        if flat.dtype == np.uint8:
            v = int(value) % 256 if np.isfinite(value) else 3
        else:
            v = value
        with np.errstate(all="ignore"):
            flat.reshape(-1)[index % flat.size] = v
        arr[...] = flat

    _run_case(base_map, mutate, "codes_and_state_values", f"{which}[{index}] = {value}")


@settings(SETTINGS, max_examples=EXPECTED["geometry"])
@given(data=st.data())
def test_fuzz_geometry(base_map, bounded_memory, data):
    """Hostile but *consistent* sizes: header and array metadata agree on a grid, code size and chunk shapes
    (up to absurd ones), so the checks past "header and arrays disagree" are exercised too."""
    dims = st.sampled_from([0, 1, 2, 3, 5, 64, 1000, 4096, 2**20, 2**31 - 1])
    grid = [data.draw(dims) for _ in range(3)]
    shape_voxels = [data.draw(st.integers(0, min(16 * g, 2**31 - 1))) for g in grid]
    size = data.draw(st.sampled_from([8, 4, 16, 4096, 65536]))
    chunk_code = data.draw(st.sampled_from([c for c in (1, 4, 8, 32, size) if c <= size]))
    cb = data.draw(st.sampled_from([1, 2, 3, 8, 256]))
    state_chunks = [data.draw(st.sampled_from([1, 2, 4, 64, 4096, 2**20])) for _ in range(3)]
    weights_chunks = [data.draw(st.sampled_from([1, 4, 64])) for _ in range(3)] + [data.draw(st.sampled_from([1, 4096]))]
    prefix = data.draw(st.booleans())
    levels = sorted({*range(chunk_code, size, chunk_code), size})[-64:] if prefix else [size]

    def mutate(p: Path) -> None:
        doc = json.loads((p / "zarr.json").read_text())
        h = doc["attributes"]["sdfcodec"]
        h.update(grid_blocks=grid, shape_voxels=shape_voxels)
        h["codes"].update(size=size, chunk_code=chunk_code, chunk_blocks=cb, prefix_ordered=prefix, levels=levels)
        (p / "zarr.json").write_text(json.dumps(doc))
        for name, shp, chunks in (("codes", [*grid, size], [cb, cb, cb, chunk_code]), ("state", grid, state_chunks),
                                  ("weights", [*grid, 4096], weights_chunks), ("observed", [*grid, 512], [cb, cb, cb, 512])):
            if not (p / name).exists():
                continue
            meta = json.loads((p / name / "zarr.json").read_text())
            meta["shape"] = shp
            if meta["chunk_grid"]["configuration"]["chunk_shape"] != chunks:
                # chunks cut for the old shape are damaged data (test_fuzz_chunk_bytes's job), and every read
                # would stop at them: without them the array is consistent, all fill value (unobserved)
                shutil.rmtree(p / name / "c", ignore_errors=True)
            meta["chunk_grid"]["configuration"]["chunk_shape"] = chunks
            (p / name / "zarr.json").write_text(json.dumps(meta))

    _run_case(base_map, mutate, "geometry", f"grid {grid} ({shape_voxels} voxels) codes {size}/{chunk_code} in "
                                            f"{cb}^3-block chunks{' prefix' if prefix else ''}, state chunks "
                                            f"{state_chunks}, weights chunks {weights_chunks}", GEOMETRY_LIMIT)


def test_examples_are_pinned(examples_pinned):
    """The fuzzers draw the same examples in any selection of tests and any state of the package's literals
    (tests/conftest.py, _pin_examples): a case that is slow or fails in the full suite is slow or fails alone."""
    if os.environ.get("HYPOTHESIS_PROFILE", "deterministic") != "deterministic":
        pytest.skip("another Hypothesis profile: examples vary on purpose")
    assert examples_pinned, "this Hypothesis lacks the hook that tests/conftest.py _pin_examples replaces: update it"


def test_fuzz_counts():
    """Runs after the fuzz tests (file order): each fuzzer that ran in this session ran all its examples, some
    of them were refused (its mutations reach the checks) and some were read (past open_map, so the checks
    there ran too; a reader that refused every map would pass the fuzzers otherwise). The mutations of an
    existing map also leave some maps fully usable; the geometry fuzzer's hostile grids never quite do (some
    call of the dozen always hits a limit), so for it reading the block states is the bar."""
    print(f"fuzz: {COUNTS}")
    for seconds, test, case in sorted(CASES, reverse=True)[:5]:
        print(f"slowest fuzz case: {seconds:6.2f} s  {test}  {case}")
    if not COUNTS:
        pytest.skip("no fuzz test ran in this session (run the file, not this test alone)")
    for test, counts in COUNTS.items():
        assert counts["cases"] == EXPECTED[test], (test, counts)
        assert counts["refused"] and counts["read"], (test, counts)
        assert counts["worked"] or test == "geometry", (test, counts)


# -- fuzzing at scale (issue 40, item 9): headers, chunks and CLI inputs, thousands of cases -------------------
# The map is held in memory (a Zarr MemoryStore built from its files), so that a case costs milliseconds, not a
# copy of a directory: what a store-independent reader checks is the same (the local store's own checks are the
# fuzzers' above). Foreign exceptions are collected, not raised, so that one run finds them all; the report test
# at the end of the file fails if there is any. SDFCODEC_FUZZ_SCALE=N sets the slow run's cases in all (10,000);
# the default suite runs QUICK_SCALE of them.

SCALE = int(os.environ.get("SDFCODEC_FUZZ_SCALE", "10000"))
QUICK_SCALE = 200
SHARE = {"scale_headers": 0.4, "scale_chunks": 0.3, "scale_cli": 0.3}  # of the cases, per fuzzer
SCALE_COUNTS: dict[str, dict[str, int]] = {}
FOREIGN: list[tuple[str, str, str]] = []  # (fuzzer, exception, case) of every foreign exception or traceback


def _scale_settings(total: int, name: str):
    return settings(SETTINGS, max_examples=max(1, round(total * SHARE[name])))


@pytest.fixture(scope="module")
def base_files(base_map) -> dict[str, bytes]:
    """The base map as ``{store key: bytes}``."""
    return {str(p.relative_to(base_map)): p.read_bytes() for p in sorted(base_map.rglob("*")) if p.is_file()}


def _count(name: str, outcome: str) -> None:
    c = SCALE_COUNTS.setdefault(name, {"cases": 0, "worked": 0, "refused": 0, "foreign": 0})
    c["cases"] += 1
    c[outcome] += 1
    if c["cases"] % 500 == 0:  # a long run's progress (pytest -s shows it)
        print(f"{time.strftime('%H:%M:%S')} {name}: {c}", flush=True)


def _guarded(name: str, case: str, fn) -> str:
    """Run ``fn`` under the per-case time limit: "worked", "refused" (an SDFCodecError) or "foreign" (anything
    else, recorded in FOREIGN)."""
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, PER_EXAMPLE_S)
    try:
        return fn()
    except SDFCodecError:
        return "refused"
    except Exception as e:  # noqa: BLE001 - what this fuzzer looks for
        FOREIGN.append((name, f"{type(e).__name__}: {str(e)[:300]}", case[:300]))
        return "foreign"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _exercise_files(name: str, files: dict[str, bytes], case: str) -> None:
    """Open the map held by ``files`` from memory, read and decode it, verify it; count the outcome."""
    import zarr
    from zarr.core.buffer import cpu

    def run() -> str:
        store = zarr.storage.MemoryStore({k: cpu.Buffer.from_bytes(v) for k, v in files.items()}, read_only=True)
        outcome = "worked"
        try:
            m = sdfcodec.open_map(store, max_decode_bytes=LIMIT)
        except SDFCodecError:
            m, outcome = None, "refused"
        for call in (lambda m: m.decode_region(), lambda m: list(m.iter_codes(level=4))) if m is not None else ():
            try:
                call(m)
            except SDFCodecError:
                outcome = "refused"
        if m is not None:
            m.close()
        rep = verify_map(store, max_decode_bytes=LIMIT, decode_blocks=16)
        internal = [str(p) for p in rep.problems if p.where == "verify"]
        if internal:
            raise AssertionError(f"verify failed internally: {internal[0]}")
        return outcome

    _count(name, _guarded(name, case, run))


def _scale_headers(data, files: dict[str, bytes]) -> None:
    """Mutate one metadata document: the sdfcodec header in the root's, or an array's Zarr metadata."""
    name = data.draw(st.sampled_from(sorted(k for k in files if k.endswith("zarr.json"))))
    doc = json.loads(files[name])
    target = doc["attributes"]["sdfcodec"] if name == "zarr.json" and data.draw(st.booleans()) else doc
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(_paths(target)))
        how = data.draw(st.sampled_from(["replace", "replace", "delete", "insert", "wrap"]))
        target = _apply(target, path, how, data.draw(json_value))
    if target is not doc and isinstance(doc.get("attributes"), dict):
        doc["attributes"]["sdfcodec"] = target
    elif target is not doc:
        doc = target
    raw = json.dumps(doc).encode()
    if data.draw(st.integers(0, 19)) == 0:
        raw = raw[: data.draw(st.integers(0, len(raw)))]  # not even JSON
    _exercise_files("scale_headers", {**files, name: raw}, f"{name}: {raw[:200]!r}")


def _scale_chunks(data, files: dict[str, bytes]) -> None:
    """Damage chunks: bit flips, truncation, growth, two chunks swapped, a chunk's bytes in another's place of
    another size; the CRC32C recomputed half the time, so that the damage reaches the decompressor."""
    chunks = sorted(k for k in files if not k.endswith("zarr.json"))
    name = data.draw(st.sampled_from(chunks))
    how = data.draw(st.sampled_from(["flip", "flips", "truncate", "extend", "swap", "resize", "delete"]))
    out, b = dict(files), bytearray(files[name])
    if how == "flip" and b:
        i = data.draw(st.integers(0, len(b) - 1))
        b[i] ^= 1 << data.draw(st.integers(0, 7))
    elif how == "flips" and b:
        for _ in range(data.draw(st.integers(2, 32))):
            b[data.draw(st.integers(0, len(b) - 1))] ^= data.draw(st.integers(1, 255))
    elif how == "truncate":
        b = b[: data.draw(st.integers(0, max(0, len(b) - 1)))]
    elif how == "extend":
        b += data.draw(st.binary(min_size=1, max_size=256))
    elif how in ("swap", "resize"):
        other = data.draw(st.sampled_from(chunks))
        if how == "swap":
            out[other] = bytes(b)
        b = bytearray(files[other])
        if how == "resize" and b:
            b = (b * data.draw(st.integers(1, 4)))[: data.draw(st.integers(1, 4 * len(b)))]
    if how == "delete":
        del out[name]
    else:
        if len(b) >= 4 and data.draw(st.booleans()):
            body = bytes(b[:-4])
            b = bytearray(body + google_crc32c.value(body).to_bytes(4, "little"))
        out[name] = bytes(b)
    _exercise_files("scale_chunks", out, f"{how} {name}")


# the CLI's vocabulary: options of info, verify, decode and encode, and values for them (good and hostile)
CLI_OPTIONS = ["--json", "--decode-blocks", "--level", "--region", "--units", "--device", "--overwrite", "--codec",
               "--code-size", "--model", "--voxel-size", "--truncation", "--origin", "--key", "--code-dtype", "--fit",
               "--fit-max-blocks", "--codec-state", "--step", "--target-bytes", "--max-error", "--sign-exact",
               "--chunk-blocks", "--shard-blocks", "--no-such-option", "-o", "--"]
CLI_VALUES = ["0", "1", "-1", "2", "4", "8", "16", "64", "4096", "2147483648", "1e308", "-1e308", "5e-324", "nan",
              "inf", "-inf", "0.02", "-0.04,0.1", "0.1,-0.04", "nan,0.1", "0,0,0", "1e308,0,0", "0:16,0:16,0:16",
              "0:1e9,0:16,0:16", "16:0,0:16,0:16", "0:0.32,0:0.32,0:0.32", "0:16", "a:b,c:d,e:f", "m", "voxels",
              "km", "cpu", "cuda", "foo", "meta", "raw", "pca", "gaussian-blur", "no-such-codec", "float32", "int8",
              "float16", "float64", "embedded", "reference", "x", "", " ", "-", "--", "é", "\\", "a\nb"]
CLI_FLAGS = {"--json", "--overwrite", "--fit", "--sign-exact"}
CLI_COMMAND_OPTIONS = {
    "info": ["--json"], "verify": ["--json", "--decode-blocks"],
    "decode": ["--level", "--region", "--units", "--device", "--overwrite", "--json"],
    "encode": ["--codec", "--code-size", "--voxel-size", "--truncation", "--origin", "--key", "--code-dtype", "--fit",
               "--fit-max-blocks", "--codec-state", "--overwrite", "--step", "--target-bytes", "--max-error",
               "--sign-exact", "--chunk-blocks", "--shard-blocks", "--device", "--json"]}
CLI_PATHS = ["{map}", "{vol}", "{npz}", "{garbage}", "{empty}", "{dir}", "{missing}", "{out}.npy", "{out}.npz",
             "{out}.sdfz", "{out}.zip", "{out}", "{out}.txt", "{map}/zarr.json", "{map}/codes", "/dev/null",
             "http://127.0.0.1:9/x.sdfz", "file:///nonexistent/x.sdfz"]


@pytest.fixture(scope="module")
def cli_inputs(tmp_path_factory, base_map) -> dict[str, Path]:
    """Inputs the CLI fuzzer's paths name: a small volume (.npy, .npz), garbage, an empty file, a directory."""
    root = tmp_path_factory.mktemp("cli-inputs")
    vol = (analytic_blocks(4, seed=9).reshape(2, 2, 16, 16, 16).transpose(0, 2, 1, 3, 4).reshape(32, 32, 16)
           * (TRUNC[1] - TRUNC[0]) + TRUNC[0]).astype(np.float32)
    np.save(root / "vol.npy", vol)
    np.savez(root / "vol.npz", tsdf=vol)
    (root / "garbage.npy").write_bytes(b"\x93NUMPY\x01\x00garbage" * 3)
    (root / "empty.npy").write_bytes(b"")
    (root / "dir").mkdir()
    return {"vol": root / "vol.npy", "npz": root / "vol.npz", "garbage": root / "garbage.npy",
            "empty": root / "empty.npy", "dir": root / "dir"}


def _scale_cli(data, base: Path, inputs: dict[str, Path]) -> None:
    """One command line of info, verify, decode or encode from the vocabulary above, on a fresh copy of the map,
    in a fresh directory: it works, or ends in a clean error (a one-line error or a usage message), never a
    traceback or an exception escaping the command."""
    from typer.testing import CliRunner

    from sdfcodec.cli import app
    from sdfcodec.map.io.stores import set_read_defaults

    command = data.draw(st.sampled_from(["info", "verify", "decode", "encode"]))
    n_pos = {"info": 1, "verify": 1, "decode": 2, "encode": 2}[command]
    token = st.one_of(st.sampled_from(CLI_OPTIONS), st.sampled_from(CLI_VALUES), st.sampled_from(CLI_PATHS),
                      st.text(max_size=6))
    if data.draw(st.booleans()):  # a plausible command line: the right inputs, options each with a value
        first = "{vol}" if command == "encode" and data.draw(st.booleans()) else "{map}"
        args = [first, "{out}" + data.draw(st.sampled_from([".npy", ".npz", ".sdfz", ""]))][:n_pos]
        for _ in range(data.draw(st.integers(0, 3))):
            opt = data.draw(st.sampled_from(CLI_COMMAND_OPTIONS[command]))
            args += [opt] if opt in CLI_FLAGS else [opt, data.draw(st.sampled_from(CLI_VALUES))]
    else:  # anything from the vocabulary, in any order
        args = [data.draw(st.sampled_from(CLI_PATHS)) for _ in range(data.draw(st.integers(0, n_pos)))]
        args += data.draw(st.lists(token, max_size=6))
        if data.draw(st.booleans()):
            args = data.draw(st.permutations(args))
    tmp = Path(tempfile.mkdtemp(prefix="sdfcodec-fuzz-cli-"))
    try:
        shutil.copytree(base, tmp / "m.sdfz")
        names = {"map": tmp / "m.sdfz", "out": tmp / "out", "missing": tmp / "missing.npy", **inputs}
        argv = ["--remote-tries", "1", "--remote-timeout", "2", command,
                *(a.format(**names) if a in CLI_PATHS else a for a in args)]
        case = " ".join(argv)

        def run() -> str:
            r = CliRunner().invoke(app, argv)
            if r.exception is not None and not isinstance(r.exception, SystemExit):
                raise r.exception
            if "Traceback" in r.output:
                raise AssertionError(f"a traceback in the output: {r.output[-300:]}")
            return "worked" if r.exit_code == 0 else "refused"

        cwd = os.getcwd()
        os.chdir(tmp)  # relative outputs land in the case's directory
        try:
            _count("scale_cli", _guarded("scale_cli", case, run))
        finally:
            os.chdir(cwd)
            set_read_defaults()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# Zarr warns (ZarrUserWarning) about the unknown objects a mutated document holds; the warning is expected here,
# the map's refusal or sound read is what is checked
@pytest.mark.filterwarnings("ignore::zarr.errors.ZarrUserWarning")
@_scale_settings(QUICK_SCALE, "scale_headers")
@given(data=st.data())
def test_fuzz_scale_headers_quick(base_files, bounded_memory, data):
    _scale_headers(data, base_files)


@_scale_settings(QUICK_SCALE, "scale_chunks")
@given(data=st.data())
def test_fuzz_scale_chunks_quick(base_files, bounded_memory, data):
    _scale_chunks(data, base_files)


@_scale_settings(QUICK_SCALE, "scale_cli")
@given(data=st.data())
def test_fuzz_scale_cli_quick(base_map, cli_inputs, bounded_memory, data):
    _scale_cli(data, base_map, cli_inputs)


@pytest.mark.slow
# Zarr warns (ZarrUserWarning) about the unknown objects a mutated document holds; the warning is expected here,
# the map's refusal or sound read is what is checked
@pytest.mark.filterwarnings("ignore::zarr.errors.ZarrUserWarning")
@_scale_settings(SCALE, "scale_headers")
@given(data=st.data())
def test_fuzz_scale_headers(base_files, bounded_memory, data):
    """SCALE x 40 % mutated metadata documents of the base map (the slow suite: ``pytest -m slow``)."""
    _scale_headers(data, base_files)


@pytest.mark.slow
@_scale_settings(SCALE, "scale_chunks")
@given(data=st.data())
def test_fuzz_scale_chunks(base_files, bounded_memory, data):
    """SCALE x 30 % damaged chunk sets."""
    _scale_chunks(data, base_files)


@pytest.mark.slow
@_scale_settings(SCALE, "scale_cli")
@given(data=st.data())
def test_fuzz_scale_cli(base_map, cli_inputs, bounded_memory, data):
    """SCALE x 30 % command lines."""
    _scale_cli(data, base_map, cli_inputs)


def test_fuzz_scale_report():
    """Runs after the scale fuzzers (file order): no foreign exception in any case, every case counted, and
    each fuzzer's cases both refused and worked (its mutations reach the checks, and the checks let sound
    input through)."""
    print(f"scale fuzz: {SCALE_COUNTS}")
    kinds: dict[str, list[str]] = {}  # one line per kind of foreign exception, with its count and first case
    for name, exc, case in FOREIGN:
        kinds.setdefault(f"{name}: {exc.splitlines()[0][:90]}", []).append(case)
    for kind, cases in sorted(kinds.items(), key=lambda kv: -len(kv[1])):
        print(f"foreign x{len(cases)}: {kind}\n    first case: {cases[0]}")
    if not SCALE_COUNTS:
        pytest.skip("no scale fuzz test ran in this session (run the file, not this test alone)")
    assert not FOREIGN, f"{len(FOREIGN)} foreign exception(s), first: {FOREIGN[0]}"
    for name, c in SCALE_COUNTS.items():
        assert c["cases"] == c["worked"] + c["refused"] + c["foreign"]
        assert c["refused"] and c["worked"], (name, c)
