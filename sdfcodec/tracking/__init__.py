"""Tracking: the SDF Tracker (:mod:`~sdfcodec.tracking.tracker`) and the fields it tracks against, a dense one
(:mod:`~sdfcodec.tracking.densefield`) and a map decoded on demand (:mod:`~sdfcodec.tracking.mapfield`)."""

__all__: list[str] = []
