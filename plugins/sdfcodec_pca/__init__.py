"""The ``pca`` codec: the paper's eigenshapes (projection onto principal components of TSDF blocks).

Two readings of the paper's "one slot stores the mean" are supported (``mean=``):

``"dataset"`` (default; what the authors' released code does)
    A data-set mean block ``mu`` (4096 values) is part of the learned state; all ``code_size`` slots are
    principal components of the centred data: ``code = (x - mu) W^T``, ``x ~= code W + mu``.
``"block"`` (the paper's text)
    Slot 0 stores the block's own mean ``m``; the other ``code_size - 1`` slots are principal components of
    the block-centred data ``x - m`` (whose small data-set mean ``mu_c`` is kept in the state):
    ``x ~= m 1 + code[1:] W + mu_c``.

Measured, the two are within 1 % of each other on synthetic, analytic and real blocks (docs/pca-choices.md).
``"dataset"`` is the default: at equal error all its slots are coefficients on one orthonormal basis, so code
distances equal reconstruction distances (what descriptor search relies on), as in the authors' code.

Both are affine maps, so encode and decode are each one batched matrix product (``torch.addmm``) on the
input's device. Components are sorted by explained variance, so any code prefix decodes
(``prefix_ordered``): the first 32 of a 128-slot code give a 32-slot reconstruction.

Shipped weights: ``models/pca-128.npz`` in this package, the default eigenshapes (128 principal components of
normalised 16^3 blocks at voxel size 0.02 m, truncation [-0.04, 0.1] m), trained by ``make default-model``
(``examples/train_default_model.py``) on synthetic blocks plus real sub-volumes fused from 7-Scenes
redkitchen. :meth:`PCACodec.pretrained` serves them; its prefixes serve pca-1 .. pca-128.
"""

from __future__ import annotations

from typing import Any, Callable, Iterator, Mapping

import numpy as np

from sdfcodec import Codec
from sdfcodec.errors import InvalidValueError, ModelNotFoundError, ShapeError
from sdfcodec.plugin import empty, lazy_module, load_shipped_model, run_tiles, scratch, shipped_model_file

from . import truncated

# imported on first use: listing codecs and reading map headers (the shipped model's digest) never need them
torch = lazy_module("torch")
scipy_linalg = lazy_module("scipy.linalg")
sklearn_decomposition = lazy_module("sklearn.decomposition")

__all__ = ["PCACodec", "SHIPPED_MODEL", "RIDGE", "WEIGHTED_FIT_ITERATIONS", "ridge_centre"]

_N = 16 ** 3
SHIPPED_MODEL = "pca-128.npz"  # in this package's models/
#: Relative Tikhonov weight of the weighted encode (towards the plain projection), times the mean weight.
RIDGE = 1e-4
#: Alternations per stage of the weighted fit (fit_weighted); measured on the kitchen: the held-out error stops
#: improving after 2-3
WEIGHTED_FIT_ITERATIONS = 3
#: Largest |C C^T - I| of an accepted basis: fitted float32 bases measure ~1e-6; a basis altered by a few
#: percent (or scaled) is far beyond it.
ORTHONORMAL_TOLERANCE = 1e-3
_GRAM_TABLE_MAX_K = 128  # (4096, k (k + 1) / 2) float32 outer-product table: 135 MB at k = 128
#: The refit steps stop early where ``z^T grad`` (preconditioned gradient) falls below this fraction of its first
#: value. 0: all the steps run (they are cheap; a block whose fit starts far from its optimum has a large first
#: value, and any fraction of it stopped such blocks short of the optimum, tests/test_observed.py)
REFIT_TOLERANCE = 0.0
_FAST_MAX_K = 256  # the compiled pass's per-thread scratch: two k x k matrices


def ridge_centre(c0: np.ndarray, shrink: float) -> tuple[np.ndarray, float]:
    """``(centre (N, k) float32, ridge)`` of the one ridge ``ridge * mean(w) |c - centre|^2`` that equals the
    encode's two: :data:`RIDGE` towards the plain codes ``c0`` ``(N, k)`` and ``shrink`` (>= 0) towards the zero
    code (their sum differs by a constant in ``c``). Why shrink: the reader's error is flat along the directions
    that only move voxels it truncates, and its exact optimum drifts along them to large codes that cost bits once
    quantised coarsely; a ridge towards zero picks the small code in that valley (the variable-rate writer asks
    for it at low rates: :data:`sdfcodec.core.varrate.SHRINK`)."""
    if not shrink > 0:
        return c0, RIDGE
    total = RIDGE + float(shrink)
    return np.ascontiguousarray(c0 * np.float32(RIDGE / total), dtype=np.float32), total


def _refit_rows(x: torch.Tensor, w: torch.Tensor, codes: torch.Tensor, fixed: torch.Tensor, mean: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """One basis step of weighted alternating least squares: with the codes ``(n, f + e)`` held, the ``e``
    components after the ``f`` ``fixed`` ones and the mean that minimise ``sum w (x - codes basis - mean)^2``,
    voxel by voxel (4096 small systems; a ridge of 1e-4 of their scale towards the current mean keeps voxels
    that no block weighs defined), made orthonormal and orthogonal to ``fixed``."""
    f = len(fixed)
    e = codes.shape[1] - f
    iu = torch.triu_indices(e + 1, e + 1)
    lhs = torch.zeros((_N, iu.shape[1]), dtype=torch.float64)
    rhs = torch.zeros((_N, e + 1), dtype=torch.float64)
    for i in range(0, len(x), 8192):  # normal equations of every voxel, accumulated over chunks of blocks
        c = torch.cat([codes[i:i + 8192, f:], torch.ones(len(codes[i:i + 8192]), 1)], dim=1)
        y = x[i:i + 8192] - codes[i:i + 8192, :f] @ fixed if f else x[i:i + 8192]
        wc = w[i:i + 8192]
        lhs += (wc.T @ (c[:, iu[0]] * c[:, iu[1]])).double()
        rhs += ((wc * y).T @ c).double()
    gram = torch.zeros((_N, e + 1, e + 1), dtype=torch.float64)
    gram[:, iu[0], iu[1]] = lhs
    gram[:, iu[1], iu[0]] = lhs
    lam = 1e-4 * gram.diagonal(dim1=1, dim2=2).mean(dim=1) + 1e-12
    gram.diagonal(dim1=1, dim2=2).add_(lam[:, None])
    rhs[:, e] += lam * mean.double()
    theta = torch.linalg.solve(gram, rhs[:, :, None])[:, :, 0]
    new = theta[:, :e].T.float()
    if f:
        new = new - (new @ fixed.T) @ fixed
    q, _ = torch.linalg.qr(new.T)
    return q.T.contiguous(), theta[:, e].float().contiguous()


def _top_eigenpairs(cov: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest eigenvalues (descending) and eigenvectors ``(k, n)`` of the symmetric ``cov``.

    Lanczos (ARPACK) first: it needs only products with ``cov``, where LAPACK's subset solver still reduces the
    whole 4096 x 4096 matrix to tridiagonal form (measured here: k=16 0.27 s vs 2.9 s, k=128 7.7 s vs 12.6 s,
    equal to 1e-12). A deterministic start vector keeps fits reproducible; should ARPACK not converge (clustered
    eigenvalues at the cut), the dense solver answers."""
    from scipy.sparse.linalg import ArpackNoConvergence, eigsh

    if k < cov.shape[0] - 1:
        try:
            vals, vecs = eigsh(cov, k=k, which="LA", tol=0, v0=np.full(cov.shape[0], cov.shape[0] ** -0.5))
            order = np.argsort(vals)[::-1]
            return vals[order], vecs[:, order].T
        except ArpackNoConvergence:
            pass
    vals, vecs = scipy_linalg.eigh(cov, subset_by_index=[cov.shape[0] - k, cov.shape[0] - 1])
    return vals[::-1], vecs[:, ::-1].T


class PCACodec(Codec):
    """PCA eigenshapes codec.

    Args:
        code_size: code length k (the paper uses 32, 64, 128).
        mean: ``"dataset"`` or ``"block"``: where the mean lives (see the module docstring).
        svd_solver: passed to :class:`sklearn.decomposition.PCA` (``"auto"``, ``"full"``, ``"randomized"``...).
        random_state: seed for the randomized solver, so fitting is reproducible.

    Learned state (``state_dict``): ``components`` ``(c, 4096)``, ``mean`` ``(4096,)``,
    ``explained_variance`` ``(c,)`` with ``c = k`` (dataset mean) or ``k - 1`` (block mean); float32.
    """

    codec_id = "pca"
    prefix_ordered = True
    requires_fit = True
    code_sizes = (32, 64, 128)
    # spec/codec-plugins.md, section 4a: every optional fast path, weighted encode and fit, shipped bases
    capabilities = frozenset({"decode_affine", "decode_into", "decode_tiles", "encode_truncated", "encode_weighted",
                              "fit_weighted", "numpy_path", "pretrained"})

    #: How the compiled pass (:meth:`encode_truncated`) refits for the reader's truncation: this many
    #: preconditioned conjugate-gradient steps on the reader's error per refit asked for
    #: (:func:`sdfcodec_pca.kernels.refine`: the writer's 3 refits are 6 steps), or, with 0, the exact active-set
    #: refits (each a Gram rebuilt from the flipped voxels and refactorised). The steps start from the fit without
    #: the bound voxels and reach the reader's optimum (0.02 % above it on the bench's blocks; the exact 3 refits
    #: stay 7 % above; kitchen half Chamfer 1.3-1.6 % below the steps from the fit with them, at about their
    #: cost). A class attribute, not a constructor argument: how a writer solves is no part of a map's codec
    #: configuration.
    cg_steps_per_refit = 2

    def __init__(self, code_size: int = 64, mean: str = "dataset", svd_solver: str = "auto",
                 random_state: int | None = 0):
        self.code_size = code_size
        self.mean = mean
        self.svd_solver = svd_solver
        self.random_state = random_state

    # -- learned state --------------------------------------------------------------------------------
    def _n_components(self) -> int:
        if self.mean not in ("dataset", "block"):
            raise InvalidValueError(f"pca mean must be 'dataset' or 'block', got {self.mean!r}")
        if not isinstance(self.code_size, int) or not 1 + (self.mean == "block") <= self.code_size <= _N:
            raise InvalidValueError(f"pca code_size must be an int in [{1 + (self.mean == 'block')}, {_N}], "
                                    f"got {self.code_size!r}")
        return self.code_size - (self.mean == "block")

    def _fit(self, blocks: np.ndarray) -> None:
        n_comp = self._n_components()
        x = blocks.reshape(len(blocks), _N)
        if self.mean == "block":
            x = x - x.mean(axis=1, keepdims=True)
        if len(x) < n_comp:
            raise ShapeError(f"pca-{self.code_size} needs at least {n_comp} blocks to fit, got {len(x)}; "
                             "fit on more data or use a trained model (--model)")
        pca = sklearn_decomposition.PCA(n_components=n_comp, svd_solver=self.svd_solver,
                                        random_state=self.random_state).fit(x)
        self.load_state_dict({"components": pca.components_, "mean": pca.mean_,
                              "explained_variance": pca.explained_variance_})

    def fit_weighted(self, blocks: np.ndarray, weights: np.ndarray) -> None:
        """The basis whose weighted least-squares codes (:meth:`encode_weighted`) fit ``blocks`` best in the
        weighted error: weighted alternating least squares from the plain PCA, grown in nested stages (the first
        ``k / 4``, then ``k / 2``, then all ``k`` components, each stage refitting only its new components with
        the earlier ones fixed, ``WEIGHTED_FIT_ITERATIONS`` times), so every code prefix stays a fitted basis
        of its own (``prefix_ordered``); each stage's new components are ordered by the variance of their codes
        (``explained_variance``: that variance when the stage was fitted, decreasing within each stage).
        Needs ``mean="dataset"``; memory: about three copies of the blocks."""
        if self.mean != "dataset":
            raise InvalidValueError("pca fits weights only with mean='dataset' (the block-mean slot is no "
                                    f"least-squares coefficient); got mean={self.mean!r}")
        self._fit(blocks)  # the start: plain PCA of the blocks as given
        n, k = len(blocks), self._n_components()
        x, w = torch.from_numpy(blocks.reshape(n, _N)), torch.from_numpy(weights.reshape(n, _N))
        comp = torch.from_numpy(self.components_.copy())
        mean = torch.from_numpy(self.mean_.copy())
        explained = torch.zeros(k)  # per stage: the variance of its new components' codes, when it was fitted
        fixed = 0
        for stop in sorted({max(1, k // 4), max(1, k // 2), k}):
            for _ in range(WEIGHTED_FIT_ITERATIONS):
                codes = self._weighted_codes(x, w, comp[:stop], mean)
                comp[fixed:stop], mean = _refit_rows(x, w, codes, comp[:fixed], mean)
            codes = self._weighted_codes(x, w, comp[:stop], mean)[:, fixed:stop]
            var, rot = torch.linalg.eigh(torch.cov(codes.T.double()).reshape(stop - fixed, stop - fixed))
            order = torch.argsort(var, descending=True)
            new = rot[:, order].T.float() @ comp[fixed:stop]
            signs = torch.sign(new[torch.arange(len(new)), new.abs().argmax(dim=1)])
            comp[fixed:stop] = new * signs[:, None]
            explained[fixed:stop] = var[order].float().clamp_min(0)
            fixed = stop
        self.load_state_dict({"components": comp.numpy(), "mean": mean.numpy(),
                              "explained_variance": explained.numpy()})

    def _weighted_codes(self, x: torch.Tensor, w: torch.Tensor, comp: torch.Tensor, mean: torch.Tensor
                        ) -> torch.Tensor:
        """Weighted least-squares codes ``(n, c)`` of blocks ``x`` under basis ``comp`` ``(c, 4096)``, ``mean``."""
        trial = PCACodec(code_size=len(comp))
        trial.load_state_dict({"components": comp.numpy(), "mean": mean.numpy(),
                               "explained_variance": np.ones(len(comp), np.float32)})
        return torch.cat([trial.encode_weighted(x[i:i + 8192], w[i:i + 8192]) for i in range(0, len(x), 8192)])

    def fit_batches(self, batches: Iterator[np.ndarray]) -> None:
        """One pass over the data accumulating the mean and the 4096 x 4096 second moment (float64), then the
        top eigenvectors of the covariance: exact PCA (as sklearn's full SVD) in bounded memory (~260 MB)."""
        n_comp = self._n_components()
        total = np.zeros(_N, dtype=np.float64)
        moment = np.zeros((_N, _N), dtype=np.float64)
        count = 0
        for b in batches:
            x = b.reshape(len(b), _N)
            if self.mean == "block":
                x = x - x.mean(axis=1, keepdims=True)
            t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
            moment += (t.T @ t).double().numpy()  # float32 product per batch, float64 accumulation across batches
            total += x.sum(axis=0, dtype=np.float64)
            count += len(x)
        if count < max(n_comp, 2):
            raise ShapeError(f"pca-{self.code_size} needs at least {max(n_comp, 2)} blocks to fit, got {count}")
        mu = total / count
        cov = (moment - count * np.outer(mu, mu)) / (count - 1)
        vals, vecs = _top_eigenpairs(cov, n_comp)
        # deterministic signs: the largest-magnitude entry of each component is positive
        signs = np.sign(vecs[np.arange(n_comp), np.abs(vecs).argmax(axis=1)])
        self.load_state_dict({"components": vecs * signs[:, None], "mean": mu, "explained_variance": vals})

    def state_dict(self) -> dict[str, np.ndarray]:
        if not hasattr(self, "components_"):
            return {}
        return {"components": self.components_, "mean": self.mean_, "explained_variance": self.explained_variance_}

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> "PCACodec":
        n_comp = self._n_components()
        missing = {"components", "mean", "explained_variance"} - set(state)
        if missing:
            raise InvalidValueError(f"pca state lacks array(s) {sorted(missing)}")
        comp = np.asarray(state["components"], dtype=np.float32)
        mean = np.asarray(state["mean"], dtype=np.float32)
        var = np.asarray(state["explained_variance"], dtype=np.float32)
        if comp.shape != (n_comp, _N) or mean.shape != (_N,) or var.shape != (n_comp,):
            raise ShapeError(f"pca-{self.code_size} (mean={self.mean!r}) state needs components ({n_comp}, {_N}), "
                             f"mean ({_N},), explained_variance ({n_comp},); got {comp.shape}, {mean.shape}, "
                             f"{var.shape}")
        if not (np.isfinite(comp).all() and np.isfinite(mean).all()):
            raise InvalidValueError("pca state holds NaN or infinite values")
        self.components_, self.mean_, self.explained_variance_ = comp, mean, var
        # the decode half now, the encode half on first use (_affine): a map's read decodes only, and the
        # encoder's float64 fold of a 128-component basis cost it ~1.5 ms per open
        self._dec, self._enc = self._build_decode(), None
        dec_w, dec_b = self._dec
        # |x_j| <= sum_i |code_i| max_j |D_ij| + max_j |d_j|: what decode_bound evaluates per batch (|.| and max
        # are exact in float32; the row maxima are summed in float64 there)
        self._row_max, self._bias_max = np.abs(dec_w).max(axis=1).astype(np.float64), float(np.abs(dec_b).max())
        self._device_cache: dict[Any, tuple[Any, ...]] = {}
        return self

    def validate_state(self) -> None:
        """The basis must be orthonormal (``C C^T = I`` within :data:`ORTHONORMAL_TOLERANCE`): every fit makes it
        so, encode and decode assume it, and a basis scaled or skewed under a recomputed digest would decode
        silently off (x3: centimetres)."""
        comp = self.components_
        with np.errstate(all="ignore"):  # an absurd basis overflows here: it is refused below, not warned about
            gram = comp @ comp.T  # float32: a (k, 4096) x (4096, k) product, ~1 ms at k = 128
            worst = float(np.abs(gram - np.eye(len(comp), dtype=np.float32)).max()) if len(comp) else 0.0
        if not worst <= ORTHONORMAL_TOLERANCE:
            raise InvalidValueError(f"pca state: the basis 'components' is not orthonormal (|C C^T - I| reaches "
                                    f"{worst:.3g}, tolerance {ORTHONORMAL_TOLERANCE:g}): it was altered or corrupted; "
                                    "restore the map or model from a copy, or re-fit the codec")

    @property
    def _affine(self) -> tuple[np.ndarray, ...]:
        """``(E, e, D, d)`` float32: the mean handling folded into ``code = x E + e`` and ``x = code D + d``."""
        if self._enc is None:
            self._enc = self._build_encode()
        return (*self._enc, *self._dec)

    def _build_decode(self) -> tuple[np.ndarray, np.ndarray]:
        """``(D, d)``: the basis (after a row of ones, the block mean's slot, for ``mean="block"``) and the mean,
        float32 as stored (no fold: no rounding)."""
        w = np.ascontiguousarray(self.components_, dtype=np.float32)  # (c, 4096)
        if self.mean == "block":
            w = np.concatenate([np.ones((1, _N), np.float32), w], axis=0)
        return w, np.ascontiguousarray(self.mean_, dtype=np.float32)

    def _build_encode(self) -> tuple[np.ndarray, np.ndarray]:
        """``(E, e)``, folded in float64."""
        w = self.components_.astype(np.float64)  # (c, 4096)
        mu = self.mean_.astype(np.float64)
        if self.mean == "dataset":
            enc_w, enc_b = w.T, -(mu @ w.T)
        else:
            # slot 0 = block mean; slots 1.. = (x - mean(x) 1 - mu_c) W^T = x (W^T - 1 colmean(W^T)) - mu_c W^T
            enc_w = np.concatenate([np.full((_N, 1), 1.0 / _N), w.T - w.T.mean(axis=0, keepdims=True)], axis=1)
            enc_b = np.concatenate([[0.0], -(mu @ w.T)])
        return tuple(np.ascontiguousarray(a, dtype=np.float32) for a in (enc_w, enc_b))  # type: ignore[return-value]

    def _on(self, device: torch.device) -> tuple[torch.Tensor, ...]:
        mats = self._device_cache.get(device)
        if mats is None:
            mats = tuple(torch.from_numpy(a).to(device) for a in self._affine)
            self._device_cache[device] = mats
        return mats

    def _decoder(self, device: torch.device, scale: float, offset: float) -> Any:
        """The decode layer with the output scaling folded in, cached: on the CPU :meth:`_folded` itself,
        elsewhere its tensors ``(scale d + offset, scale D)`` on ``device``."""
        mat = self._folded(scale, offset)
        if device.type == "cpu":
            return (mat,)
        key = (device, scale, offset)
        dec = self._device_cache.get(key)
        if dec is None:
            dec = tuple(torch.from_numpy(a).to(device) for a in (mat[0], mat[1:]))
            self._cache(key, dec)
        return dec

    def _folded(self, scale: float, offset: float) -> np.ndarray:
        """``[scale d + offset; scale D]`` ``(c + 1, 4096)`` float32 (the bias as the first row), each element
        scaled in float64 and rounded once (the rows a pinned mask's reader proves its margin for:
        spec/map-format.md section 6g), cached."""
        key = ("folded", scale, offset)
        dec = self._device_cache.get(key)
        if dec is None:
            dec_w, dec_b = self._dec
            mat = np.empty((len(dec_w) + 1, _N), np.float32)
            mat[0] = dec_b.astype(np.float64) * scale + offset
            # one pass, no float64 copy of the basis (2 MB at k = 64)
            np.multiply(dec_w, scale, out=mat[1:], dtype=np.float64, casting="same_kind")
            dec = self._cache(key, (mat,))
        return dec[0]

    def _cache(self, key: Any, value: tuple[Any, ...]) -> tuple[Any, ...]:
        if len(self._device_cache) > 8:  # a handful of truncations per process; never grow without bound
            self._device_cache.clear()
        self._device_cache[key] = value
        return value

    def prefix(self, code_size: int) -> "PCACodec":
        """The fitted codec that keeps only the first ``code_size`` code elements (its leading components):
        one 128-component basis serves pca-32 and pca-64 exactly as a prefix of its codes would."""
        self._check_fitted()
        if not 1 + (self.mean == "block") <= code_size <= self.code_size:
            raise InvalidValueError(f"prefix size must be in [{1 + (self.mean == 'block')}, {self.code_size}], "
                                    f"got {code_size}")
        c = code_size - (self.mean == "block")
        out = type(self)(code_size=code_size, mean=self.mean, svd_solver=self.svd_solver,
                         random_state=self.random_state)
        return out.load_state_dict({"components": self.components_[:c], "mean": self.mean_,
                                    "explained_variance": self.explained_variance_[:c]})

    @classmethod
    def pretrained(cls, code_size: int | None = None, **options: Any) -> "PCACodec":
        """The shipped eigenshapes (``models/pca-128.npz``) cut to their first ``code_size`` components
        (None: 64; 1..128); a fresh codec each call. ``options`` must be empty (the shipped basis fixes them).

        Raises:
            InvalidValueError: ``code_size`` outside 1..128, or options given.
            ModelNotFoundError: the model file is not installed.
        """
        if options:
            raise InvalidValueError(f"the shipped PCA model takes no options, got {sorted(options)}")
        base = load_shipped_model(__name__, SHIPPED_MODEL)
        k = 64 if code_size is None else code_size
        if not 1 <= k <= base.code_size:
            raise InvalidValueError(f"the shipped PCA model has {base.code_size} components; code_size must be in "
                                    f"1..{base.code_size}, got {k} (train a larger one with `sdfcodec train`)")
        return base.prefix(k)

    @classmethod
    def shipped_models(cls) -> dict[str, tuple[int, ...]]:
        """``{"pca-128": (1, ..., 128)}``: the shipped eigenshapes serve every prefix, each a different state
        (the first k components); ``{}`` when the file is not installed. Nothing is loaded."""
        try:
            shipped_model_file(__name__, SHIPPED_MODEL)
        except ModelNotFoundError:
            return {}
        return {SHIPPED_MODEL.removesuffix(".npz"): tuple(range(1, 129))}

    # -- encode / decode: one affine map each ---------------------------------------------------------
    def _encode(self, blocks: torch.Tensor) -> torch.Tensor:
        enc_w, enc_b, _, _ = self._on(blocks.device)
        return torch.addmm(enc_b, blocks.reshape(len(blocks), _N), enc_w)

    def _decode(self, codes: torch.Tensor) -> torch.Tensor:
        return self.decode_affine(codes, 1.0, 0.0)

    def encode_truncated(self, blocks: torch.Tensor, weights: torch.Tensor, rounds: int, shrink: float = 0.0
                         ) -> torch.Tensor | None:
        """What :func:`sdfcodec.map.observed.encode_truncated` computes from :meth:`encode_weighted` (the weighted
        fit, then at most ``rounds`` refits without the bound voxels a reader's truncation makes exact), in one
        compiled pass per block (:mod:`sdfcodec_pca.truncated`; its refits as :attr:`cg_steps_per_refit`
        conjugate-gradient steps per refit, by default): codes ``(N, k)`` float32 of blocks ``(N, 16, 16,
        16)`` float32 under checked weights of the same shape. None where that pass does not apply (not on the
        CPU, ``mean="block"``, numba not installed): the caller then runs its batched loop. ``shrink`` > 0 adds
        a ridge towards the zero code of that relative weight (:func:`ridge_centre`)."""
        if (blocks.device.type != "cpu" or self.mean != "dataset" or not truncated.available()
                or blocks.dtype != torch.float32 or self.code_size > _FAST_MAX_K):
            return None
        n = len(blocks)
        c0 = self._encode(blocks)
        w = weights if weights.dtype == torch.float32 else weights.float()
        steps = self.cg_steps_per_refit * rounds
        centre, ridge = ridge_centre(c0.numpy(), shrink)
        codes = truncated.truncated_codes(blocks.reshape(n, _N).numpy(), w.reshape(n, _N).numpy(),
                                          self._affine[2].T, self._affine[3], centre, ridge, rounds, steps,
                                          REFIT_TOLERANCE, self._gram_pieces())
        return torch.from_numpy(codes)

    def _gram_pieces(self) -> np.ndarray:
        """:func:`sdfcodec_pca.truncated.gram_pieces` of this basis, cached (computed in tens of milliseconds)."""
        pieces = self._device_cache.get("gram-pieces")
        if pieces is None:
            pieces = self._device_cache["gram-pieces"] = (truncated.gram_pieces(self._affine[2].T),)
        return pieces[0]

    def numpy_path(self) -> "_NumpyPCA | None":
        """The affine encode and decode in numpy, and :meth:`encode_truncated`'s compiled pass (searches: no
        torch import)."""
        if not self.is_fitted:
            return None
        path = self._device_cache.get("numpy")
        if path is None:
            path = self._device_cache["numpy"] = _NumpyPCA(self)
        return path  # type: ignore[return-value]

    def encode_weighted(self, blocks: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """The weighted least-squares code of each block: ``c = argmin sum_j w_j (x_j - (c D + d)_j)^2 +
        lam |c - c0|^2`` with ``c0`` the plain projection and ``lam = RIDGE * mean(w)`` (a block of zero weights
        keeps ``c0``; the ridge keeps the normal equations well posed when few voxels are observed).

        Batched: the Gram matrices ``D diag(w) D^T`` of all blocks, the weighted bias terms and the weight sums
        come from one matrix product of the weights with a precomputed table (the outer products of the basis
        columns, lower triangles only, beside ``D^T diag(d)`` and a column of ones), then one batched Cholesky
        solve; no loop over blocks. The Gram product is ``(n, 4096) @ (4096, k (k + 1) / 2)``: ``(k + 1) / 2``
        times the plain projection's work. On the CPU the compiled pass of :meth:`encode_truncated` (no refits)
        solves the same systems with Grams built from the voxels whose weight differs from 0 or 1 only."""
        fast = self.encode_truncated(blocks, weights, 0)
        if fast is not None:
            return fast
        n = len(blocks)
        x = blocks.reshape(n, _N)
        w = weights.reshape(n, _N)
        c0 = self._encode(blocks)
        dec_w = self._on(blocks.device)[2]
        k = c0.shape[1]
        out = torch.empty_like(c0)
        step = max(1, min(n, (64 << 20) // (4 * k * k)))  # Gram matrices of one batch: <= 64 MiB
        for i in range(0, n, step):
            sl = slice(i, i + step)
            gram, bias, w_sum = self._normal_terms(w[sl], blocks.device)
            lam = (RIDGE / _N) * w_sum.clamp_min(1e-12)
            gram.diagonal(dim1=1, dim2=2).add_(lam[:, None])
            rhs = torch.addmm(lam[:, None] * c0[sl] - bias, w[sl] * x[sl], dec_w.T)  # D diag(w) (x - d) + lam c0
            chol, info = torch.linalg.cholesky_ex(gram)  # reads the lower triangle only
            half = torch.linalg.solve_triangular(chol, rhs[:, :, None], upper=False)
            sol = torch.linalg.solve_triangular(chol.mT, half, upper=True)[:, :, 0]  # faster than cholesky_solve here
            # a numerically singular system (never seen; guard anyway): keep the plain projection there
            out[sl] = torch.where((info == 0)[:, None] & torch.isfinite(sol).all(dim=1, keepdim=True), sol, c0[sl])
        return out

    def _normal_terms(self, w: torch.Tensor, device: torch.device) -> tuple[torch.Tensor, ...]:
        """For weights ``w`` ``(n, 4096)``: the Gram matrices ``D diag(w_i) D^T`` ``(n, k, k)`` (lower triangles
        with the diagonal, all :func:`torch.linalg.cholesky_ex` reads; the einsum path gives whole matrices), the
        bias terms ``D diag(w_i) d`` ``(n, k)`` and the weight sums ``(n,)``."""
        dec_w, dec_b = self._on(device)[2:]
        k = dec_w.shape[0]
        if k > _GRAM_TABLE_MAX_K:  # the outer-product table would be too large: one product per block
            return torch.einsum("ki,ni,li->nkl", dec_w, w, dec_w), w @ (dec_w * dec_b).T, w.sum(dim=1)
        key = ("normal-terms", device)
        cached = self._device_cache.get(key)
        if cached is None:
            iu = torch.triu_indices(k, k, device=device)
            ones = torch.ones((_N, 1), dtype=dec_w.dtype, device=device)
            cached = (torch.cat([(dec_w[iu[0]] * dec_w[iu[1]]).T, (dec_w * dec_b).T, ones], dim=1).contiguous(), iu)
            self._device_cache[key] = cached  # (4096, k (k + 1) / 2 + k + 1)
        table, iu = cached
        g = w @ table
        t = iu.shape[1]
        # the upper triangle stays 0: one scatter, not two
        gram = torch.zeros((len(w), k, k), dtype=w.dtype, device=w.device)
        gram[:, iu[1], iu[0]] = g[:, :t]
        return gram, g[:, t:t + k], g[:, t + k]

    def decode_affine(self, codes: torch.Tensor, scale: float, offset: float) -> torch.Tensor:
        # the output scaling (map readers: normalised -> metres) is folded into the decode layer: no extra pass
        out = empty((len(codes), _N), codes.device)
        self.decode_into(codes, out, scale, offset)
        return out.reshape(len(codes), 16, 16, 16)

    def decode_into(self, codes: torch.Tensor, out: torch.Tensor, scale: float, offset: float) -> None:
        # one matrix product straight into the caller's buffer, the output scaling folded into the decode layer
        n, k = codes.shape
        dec = self._decoder(codes.device, scale, offset)
        if codes.device.type == "cpu":
            # numpy's BLAS is 15-40% faster than torch's for this thin (N, k) x (k, 4096) product here, and
            # folding the bias in as a row (codes get a leading 1) saves a pass over the 16 KiB-per-block output
            c1 = np.empty((n, k + 1), dtype=np.float32)
            c1[:, 0] = 1.0
            c1[:, 1:] = codes.numpy()
            np.matmul(c1, dec[0][: k + 1], out=out.numpy().reshape(n, _N))
            return
        dec_b, dec_w = dec
        torch.addmm(dec_b, codes, dec_w[:k], out=out.view(n, _N))

    def decode_tiles(self, codes: torch.Tensor, scale: float, offset: float, clip: tuple[float, float],
                     each: Callable[[int, int, torch.Tensor], None] | None = None, out: torch.Tensor | None = None
                     ) -> None:
        # on the CPU: cache-sized tiles on every core, each a one-threaded product (bias row folded in, as in
        # decode_into) into the thread's own scratch tile, clipped from there into `out` (the clip's write is the
        # only write to memory; the product's stays in cache, a tile being four L2s: tiling.TILE_ROWS) and handed
        # to `each`. One product with all BLAS threads and a clip pass after it read the 16 KiB per block back from
        # memory, and a product straight into `out` wrote it there twice (measured: docs/results.md)
        if codes.device.type != "cpu":
            super().decode_tiles(codes, scale, offset, clip, each, out)
            return
        n, k = codes.shape
        dec = self._decoder(codes.device, scale, offset)[0][: k + 1]
        src = codes.numpy()
        dst = None if out is None else out.numpy().reshape(n, _N)
        lo, hi = clip

        def work(a: int, b: int) -> None:
            c1 = scratch("pca-codes", (b - a, k + 1))
            c1[:, 0] = 1.0
            c1[:, 1:] = src[a:b]
            made = scratch("pca-tile", (b - a, _N))
            np.matmul(c1, dec, out=made)
            tile = dst[a:b] if dst is not None else made
            np.clip(made, lo, hi, out=tile)
            if each is not None:
                each(a, b, torch.from_numpy(tile).view(b - a, 16, 16, 16))

        run_tiles(n, work)

    def decode_bound(self, codes: torch.Tensor) -> float:
        # max |code| * sum_i max_j |D_ij| + max |d|: one min/max pass over the codes, no temporaries
        if not len(codes):
            return 0.0
        if codes.device.type == "cpu":  # numpy's: torch's threaded reduction waits for BLAS threads still spinning
            a = codes.numpy()
            lo, hi = a.min(), a.max()
        else:
            lo, hi = torch.aminmax(codes)
        return max(-float(lo), float(hi)) * float(self._row_max[: codes.shape[1]].sum()) + self._bias_max


class _NumpyPCA:
    """:class:`sdfcodec.codec.NumpyPath` of a fitted :class:`PCACodec`: the same affine maps and compiled pass
    as its torch hooks on the CPU, on numpy arrays."""

    def __init__(self, codec: PCACodec):
        self.codec = codec
        dec_w, dec_b = codec._dec  # the encode half is folded on first encode
        self.dec = np.ascontiguousarray(np.concatenate([dec_b[None], dec_w]))  # [d; D]: the bias as a leading row

    def encode(self, blocks: np.ndarray) -> np.ndarray:
        enc_w, enc_b = self.codec._affine[:2]
        out = blocks @ enc_w
        out += enc_b
        return out

    def decode(self, codes: np.ndarray) -> np.ndarray:
        return self._product(codes, self.dec)  # as decode_into on the CPU

    def decode_affine(self, codes: np.ndarray, scale: float, offset: float) -> np.ndarray:
        return self._product(codes, self.codec._folded(scale, offset))  # as decode_into on the CPU, rows alike

    @staticmethod
    def _product(codes: np.ndarray, dec: np.ndarray) -> np.ndarray:
        n, k = codes.shape
        c1 = np.empty((n, k + 1), dtype=np.float32)
        c1[:, 0] = 1.0
        c1[:, 1:] = codes
        return c1 @ dec[: k + 1]

    def encode_truncated(self, blocks: np.ndarray, weights: np.ndarray, rounds: int, shrink: float = 0.0
                         ) -> np.ndarray | None:
        c = self.codec
        if c.mean != "dataset" or not truncated.available() or c.code_size > _FAST_MAX_K:
            return None  # as PCACodec.encode_truncated
        # the solver the torch hook runs (its refits as conjugate-gradient steps by default), so that query shapes
        # encode as map blocks do and shipped calibrations hold on both paths
        centre, ridge = ridge_centre(self.encode(blocks), shrink)
        return truncated.truncated_codes(blocks, weights, c._affine[2].T, c._affine[3], centre, ridge,
                                         rounds, c.cg_steps_per_refit * rounds, REFIT_TOLERANCE, c._gram_pieces())

