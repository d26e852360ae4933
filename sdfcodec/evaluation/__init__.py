"""Evaluation: tracking against compressed maps, the paper's Table 1 (:mod:`~sdfcodec.evaluation.tracking`: the
``track`` and ``eval`` commands' work), and ``sdfcodec compare`` (:mod:`~sdfcodec.evaluation.compare`)."""

__all__: list[str] = []
