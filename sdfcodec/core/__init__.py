"""The core: what every layer above shares and nothing in it knows about maps, codecs or commands.

Values and blocks (:mod:`~sdfcodec.core.blocks`, checked tensors in ``_validate``, :mod:`~sdfcodec.core.quantize`
int8/step code quantisation, :mod:`~sdfcodec.core.varrate` the entropy coding of variable-rate codes), the map
header models (:mod:`~sdfcodec.core.header`), exact analytic SDFs (:mod:`~sdfcodec.core.sdf`), decode tiles
over the cores (:mod:`~sdfcodec.core.tiling`), surface fidelity of volumes (:mod:`~sdfcodec.core.surface`),
geometry, trajectories and their metrics in the style of evo (:mod:`~sdfcodec.core.geometry`,
:mod:`~sdfcodec.core.trajectory`, :mod:`~sdfcodec.core.metrics`), lazy imports (``_lazy``) and atomic writes
(``_atomic``). Import the submodules; the package exports nothing itself."""

__all__: list[str] = []
