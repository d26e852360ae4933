"""The demo (``sdfcodec demo``, :mod:`~sdfcodec.demo.run`) and its pictures (:mod:`~sdfcodec.demo.pictures`)."""

__all__: list[str] = []
