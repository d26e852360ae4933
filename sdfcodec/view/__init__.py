"""Seeing maps: pictures of meshes (:mod:`~sdfcodec.view.pictures`), Rerun recordings
(:mod:`~sdfcodec.view.recording`, ``sdfcodec view``), and ``sdfcodec search``'s work with its pictures
(:mod:`~sdfcodec.view.search`)."""

__all__: list[str] = []
