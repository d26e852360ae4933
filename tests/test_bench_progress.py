"""`sdfcodec bench` counts every step it takes (issue 44, item 5): its progress stays true to the end, the slow
final phases (decode on read, search, the start-up of `info`) included, instead of reaching 94 % and then saying
nothing for minutes."""

from __future__ import annotations

import re

from sdfcodec.bench.codecs import bench_codec, bench_steps


def test_bench_steps_counts_every_progress_call():
    said: list[str] = []
    bench_codec("pca", [16], [1, 8], min_time=0.0, progress=said.append, read_blocks=64, http=True, repeats=1)
    assert len(said) == bench_steps("pca", [16], [1, 8], read_blocks=64, http=True) == 2 * 4 + 3
    assert said[-3:] == ["pca-16 decode-on-read 64 blocks", "pca-16 decode-on-read-http 64 blocks",
                         "pca-16 decoding 64 blocks into place"]


def test_bench_progress_is_true_to_the_end(bench_run):
    # the run test_cli checks the records of (conftest.BENCH_ARGS: --quick --sizes 32 --batches 1,64 --read 300
    # --repeats 2 --json), progress lines every 0.05 s
    assert bench_run["exit_code"] == 0, bench_run["output"]
    stderr = bench_run["stderr"]
    counts = [(line.split(":")[0], int(m[1]), int(m[2]))
              for line in stderr.splitlines() if (m := re.search(r": (\d+) of (\d+) steps", line))]
    assert counts, stderr
    (total,) = {t for _, _, t in counts}
    # 4 timed operations at each of 2 batches, 3 decode-on-read steps, 1 search kernel, the start-up of `info`
    # (writing its map, then its fresh processes: the calibration's and one per round of 2)
    assert total == 4 * 2 + 3 + 1 + (1 + 1 + 2)
    assert all(done < total for _, done, _ in counts)  # never "done" while work goes on
    # the start-up's steps (a map written, fresh processes running `sdfcodec info`, seconds each) are counted one
    # by one, the last shown as running, not finished
    shown = {(what, done) for what, done, _ in counts}
    assert {("sdfcodec info start-up", total - k) for k in (1, 2, 3, 4)} <= shown, shown
