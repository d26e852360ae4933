"""`sdfcodec bench` counts every step it takes (issue 44, item 5): its progress stays true to the end, the slow
final phases (decode on read, search, the start-up of `info`) included, instead of reaching 94 % and then saying
nothing for minutes."""

from __future__ import annotations

import re

from typer.testing import CliRunner

from sdfcodec.bench.codecs import bench_codec, bench_steps
from sdfcodec.cli import app


def test_bench_steps_counts_every_progress_call():
    said: list[str] = []
    bench_codec("pca", [16], [1, 8], min_time=0.0, progress=said.append, read_blocks=64, http=True, repeats=1)
    assert len(said) == bench_steps("pca", [16], [1, 8], read_blocks=64, http=True) == 2 * 4 + 3
    assert said[-3:] == ["pca-16 decode-on-read 64 blocks", "pca-16 decode-on-read-http 64 blocks",
                         "pca-16 decoding 64 blocks into place"]


def test_bench_progress_is_true_to_the_end():
    r = CliRunner().invoke(app, ["bench", "--quick", "--sizes", "16", "--batches", "1", "--read", "64",
                                 "--repeats", "1", "--json"], env={"SDFCODEC_PROGRESS_SECONDS": "0.05"})
    assert r.exit_code == 0, r.output
    counts = [(line.split(":")[0], int(m[1]), int(m[2]))
              for line in r.stderr.splitlines() if (m := re.search(r": (\d+) of (\d+) steps", line))]
    assert counts, r.stderr
    (total,) = {t for _, _, t in counts}
    # 4 timed operations at one batch, 3 decode-on-read steps, 1 search kernel, the start-up of `info` (writing its
    # map, then its fresh processes: the calibration's and one per round)
    assert total == 4 + 3 + 1 + (1 + 1 + 1)
    assert all(done < total for _, done, _ in counts)  # never "done" while work goes on
    # the start-up's steps (a map written, fresh processes running `sdfcodec info`, seconds each) are counted one
    # by one, the last shown as running, not finished
    shown = {(what, done) for what, done, _ in counts}
    assert {("sdfcodec info start-up", total - k) for k in (1, 2, 3)} <= shown, shown
