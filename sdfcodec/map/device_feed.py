"""The staging step of the read pipeline (:mod:`sdfcodec.map.reader`): a group's host codes brought to the
decode device, overlapping the copy of the next group with the decode of the current one on CUDA."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core._lazy import lazy_module

torch = lazy_module("torch")  # imported on first use: info, codecs, verify of a header never need it

__all__ = ["DeviceFeed"]


class DeviceFeed:
    """Brings a group's host codes to the decode device (the staging step of the read pipeline).

    ``stage`` runs in the worker thread that fetched the group; ``ready`` in the thread that decodes it. On CUDA,
    ``stage`` copies the codes into pinned (page-locked) host memory and starts a non-blocking host-to-device
    copy on a side stream, recording an event; ``ready`` makes the decoding stream wait for that event (on the
    GPU, not the host) and tells the caching allocator that the decoding stream uses the tensor. The copy of
    the next group thus overlaps the decode of the current one. On the CPU the codes are used as they are.
    """

    def __init__(self, dev: torch.device):
        self.cuda = dev.type == "cuda"
        if self.cuda and dev.index is None:
            dev = torch.device("cuda", torch.cuda.current_device())
        self.dev = dev
        self.stream = torch.cuda.Stream(device=dev) if self.cuda else None

    def stage(self, codes: np.ndarray) -> tuple[torch.Tensor, Any, Any]:
        t = torch.from_numpy(codes)
        if not self.cuda:
            return (t if self.dev.type == "cpu" else t.to(self.dev)), None, None
        host = t.pin_memory()
        with torch.cuda.device(self.dev), torch.cuda.stream(self.stream):
            on_dev = host.to(self.dev, non_blocking=True)
            done = torch.cuda.Event()
            done.record(self.stream)
        # ``host`` travels with the group until ``ready``: the pinned buffer outlives its copy (the caching host
        # allocator would also hold it until the copy's event, but nothing depends on that)
        return on_dev, done, host

    def ready(self, staged: tuple[torch.Tensor, Any, Any]) -> torch.Tensor:
        on_dev, done, _host = staged
        if done is not None:
            current = torch.cuda.current_stream(self.dev)
            current.wait_event(done)
            on_dev.record_stream(current)
        return on_dev
