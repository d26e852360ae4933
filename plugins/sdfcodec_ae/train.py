"""Training the autoencoder: the paper's batch gradient descent and mini-batch Adam, early stopping on the
validation reconstruction error, resumable checkpoints of plain arrays, learning curves as JSON and PNG.

The paper (section IV-C) trained with "batch gradient descent with the change in reconstruction error on a
validation data-set as a stopping criterion", the data split into 400 batches of 500 (300 train, 50
validation, 50 test). :class:`TrainConfig` offers that setting (``optimizer="gd"``: one gradient step per
epoch over the whole training split, with momentum) and a much faster modern one (``optimizer="adam"``:
mini-batches of 500 in a seeded random order), both stopping when the validation MSE has not improved by
``min_improvement`` (relative) for ``patience`` epochs and returning the best epoch's weights.

Determinism: weights are initialised from a ``torch.Generator`` seeded with ``seed``; the validation
hold-out and each epoch's batch order come from ``numpy.random.default_rng([seed, ...])`` keyed by the
epoch number, so they need no saved generator state and a resumed run sees the same batches as an
uninterrupted one. Computation is float32; on a given machine and thread count the result is bit-for-bit
reproducible (other BLAS kernels or GPUs round differently).

Checkpoints (``checkpoint="run.ckpt"``) are two files written after every ``checkpoint_every`` epochs:
``run.ckpt.npz`` (current weights ``model.*``, best weights ``best.*``, optimizer moments ``opt.<i>.<key>``,
all plain arrays, read with ``allow_pickle=False``) and ``run.ckpt.json`` (epoch, optimizer step counts
and hyper-parameters, early-stopping state, history, a fingerprint of the data). Nothing is pickled: the
optimizer's tensors travel as arrays, its hyper-parameters as JSON. Resuming restores the Adam/momentum
moments exactly, so a resumed run ends with the same weights as one that was never interrupted.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from sdfcodec.errors import FormatError, InvalidValueError, SDFCodecWarning, ShapeError
from sdfcodec.plugin import lazy_module, load_state_file, save_state_file

from .network import LAYERS, N_VOXELS, build_module, export_state, module_state

torch = lazy_module("torch")  # imported on first use: listing codecs and reading headers never need it

__all__ = ["TrainConfig", "TrainResult", "train_autoencoder", "write_curves", "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT, CHECKPOINT_VERSION = "sdfcodec-ae-checkpoint", 1

# per-optimizer defaults of the settings left at None (see TrainConfig)
_DEFAULTS = {
    "adam": {"lr": 1e-3, "batch_size": 100, "max_epochs": 200, "patience": 2},
    "gd": {"lr": 2.0, "batch_size": None, "max_epochs": 5000, "patience": 50},
}


@dataclass
class TrainConfig:
    """Every hyper-parameter of :func:`train_autoencoder`, with its default.

    Attributes
    ----------
    optimizer : {"adam", "gd"}
        ``"adam"``: mini-batch Adam (fast; the default). ``"gd"``: the paper's batch gradient descent, one
        step per epoch on the gradient of the whole training split (accumulated in chunks of
        ``eval_batch``), with classical momentum.
    lr : float or None
        Learning rate; None: 1e-3 (adam), 2.0 (gd; the loss is a per-voxel mean, so its gradients are small).
    batch_size : int or None
        Blocks per optimizer step; None: 100 (adam: per epoch, batches of 100 converged about twice as fast
        as the paper's 500 on AE-64, at 1.5x the time) or the whole training split (gd).
    momentum : float
        Momentum of ``"gd"`` (ignored by adam).
    max_epochs : int or None
        Upper bound on epochs; None: 200 (adam), 5000 (gd).
    patience : int or None
        Stop after this many epochs without a significant validation improvement; None: 2 (adam), 50 (gd).
    min_improvement : float
        Relative decrease of the validation MSE (against the last significant one) that counts as
        significant. Smaller decreases do not reset the patience, but the best epoch's weights are kept
        whatever the size of its improvement. The default (1 % within ``patience`` epochs) stops AE-64 on
        68,500 blocks in about half an hour on 2 CPU cores; it is then still improving by about 0.5 % per
        epoch, and a stricter setting (e.g. 0.002 and patience 4) trades hours for a few per cent.
    seed : int
        Seeds the initial weights, the validation hold-out and the batch order.
    val_fraction : float
        Share of the given blocks held out for validation when no validation set is given.
    device : str
        Torch device to train on; ``"auto"``: ``cuda`` when available, else ``cpu``.
    eval_batch : int
        Blocks per chunk when evaluating the validation error (and accumulating gd gradients).
    checkpoint : str or None
        Path prefix of resumable checkpoints (``.npz`` + ``.json``); None: no checkpoints.
    checkpoint_every : int
        Epochs between checkpoints.
    progress : bool
        Show rich progress bars on stderr.
    standardise : bool
        Train on centred, unit-variance inputs (``(x - mean block) / std``), folded into the first layer
        afterwards, so the stored network is unchanged in form; converges several times faster than raw
        blocks, which sit mostly at 1.0.
    threads : int or None
        CPU threads torch may use while training (restored afterwards); None: torch's current setting. On a
        machine whose cores are busy with other work, 1 thread can be several times faster than 2 (the
        threads of a parallel kernel wait for each other; measured 3000 vs 800 blocks/s for AE-64 steps).
    """

    optimizer: str = "adam"
    lr: float | None = None
    batch_size: int | None = None
    momentum: float = 0.9
    max_epochs: int | None = None
    patience: int | None = None
    min_improvement: float = 1e-2
    seed: int = 0
    val_fraction: float = 0.125
    device: str = "auto"
    eval_batch: int = 2000
    checkpoint: str | None = None
    checkpoint_every: int = 1
    progress: bool = True
    threads: int | None = None
    standardise: bool = True

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "TrainConfig":
        """Build from a JSON dict of overrides, naming unknown keys in the error."""
        d = dict(d or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InvalidValueError(f"unknown ae training setting(s) {unknown}; known: {sorted(known)}")
        return cls(**d)

    def resolved(self) -> "TrainConfig":
        """A copy with the per-optimizer defaults filled in and every value checked."""
        if self.optimizer not in _DEFAULTS:
            raise InvalidValueError(f"ae training optimizer must be 'adam' or 'gd', got {self.optimizer!r}")
        d = asdict(self)
        for k, v in _DEFAULTS[self.optimizer].items():
            if d[k] is None:
                d[k] = v
        c = TrainConfig(**d)
        for name in ("max_epochs", "patience", "eval_batch", "checkpoint_every"):
            v = getattr(c, name)
            if not isinstance(v, int) or v < 1:
                raise InvalidValueError(f"ae training {name} must be an int >= 1, got {v!r}")
        if c.threads is not None and (not isinstance(c.threads, int) or c.threads < 1):
            raise InvalidValueError(f"ae training threads must be an int >= 1 or None, got {c.threads!r}")
        if c.batch_size is not None and (not isinstance(c.batch_size, int) or c.batch_size < 1):
            raise InvalidValueError(f"ae training batch_size must be an int >= 1 or None, got {c.batch_size!r}")
        if not (isinstance(c.lr, (int, float)) and c.lr > 0 and math.isfinite(c.lr)):
            raise InvalidValueError(f"ae training lr must be a positive number, got {c.lr!r}")
        if not 0 < c.val_fraction < 1:
            raise InvalidValueError(f"ae training val_fraction must be in (0, 1), got {c.val_fraction!r}")
        if not 0 <= c.momentum < 1:
            raise InvalidValueError(f"ae training momentum must be in [0, 1), got {c.momentum!r}")
        return c


@dataclass
class TrainResult:
    """What :func:`train_autoencoder` returns.

    Attributes
    ----------
    state : dict of str to np.ndarray
        The best epoch's weights, float32, named as in :mod:`sdfcodec_ae.network`.
    history : list of dict
        One record per epoch: ``epoch``, ``train_mse`` (mean of the epoch's batch losses, per voxel),
        ``val_mse`` (per voxel, after the epoch), ``seconds`` (wall time since the start, resumed runs
        included), ``lr``.
    best_epoch : int
        Epoch (1-based) whose weights were kept; 0 means the initial weights.
    stopped : str
        ``"early stopping"`` or ``"max_epochs"``.
    config : dict
        The resolved :class:`TrainConfig`.
    n_train, n_val : int
        Blocks trained and validated on.
    initial_val_mse : float
        Validation MSE of the initial weights (the training mean block, see the initialisation).
    """

    state: dict[str, np.ndarray]
    history: list[dict]
    best_epoch: int
    stopped: str
    config: dict
    n_train: int
    n_val: int
    initial_val_mse: float

    def summary(self) -> dict:
        """JSON-ready summary (the curves without the weights)."""
        return {"history": self.history, "best_epoch": self.best_epoch, "stopped": self.stopped,
                "config": self.config, "n_train": self.n_train, "n_val": self.n_val,
                "initial_val_mse": self.initial_val_mse,
                "best_val_mse": min((h["val_mse"] for h in self.history), default=None),
                "seconds": self.history[-1]["seconds"] if self.history else 0.0}


# -- helpers ---------------------------------------------------------------------------------------------
def _as_rows(x: Any, what: str) -> torch.Tensor:
    """``(N, 16, 16, 16)`` or ``(N, 4096)`` float array -> contiguous float32 CPU tensor ``(N, 4096)``."""
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x)
    if not t.is_floating_point():
        raise InvalidValueError(f"{what} must be floating point, got {t.dtype}")
    if t.ndim == 4 and tuple(t.shape[1:]) == (16, 16, 16):
        t = t.reshape(len(t), N_VOXELS)
    if t.ndim != 2 or t.shape[1] != N_VOXELS:
        raise ShapeError(f"{what} must have shape (N, 16, 16, 16) or (N, 4096), got {tuple(t.shape)}")
    t = t.detach().to("cpu", torch.float32).contiguous()
    if not bool(torch.isfinite(t).all()):
        raise InvalidValueError(f"{what} holds NaN or infinite values")
    return t


def _replay(vals: list[float], initial: float, cfg: TrainConfig) -> tuple[float, int, int | None]:
    """Early-stopping state after the validation errors ``vals``: ``(reference error, epochs without a
    significant improvement, epoch at which the criterion stops or None)``."""
    ref, bad, stop = initial, 0, None
    for epoch, v in enumerate(vals, start=1):
        if v < ref * (1 - cfg.min_improvement):
            ref, bad = v, 0
        else:
            bad += 1
        if bad >= cfg.patience and stop is None:
            stop = epoch
    return ref, bad, stop


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as e:
        raise InvalidValueError(f"ae training device {name!r} is not a torch device ({e})") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InvalidValueError("ae training device 'cuda' asked for, but torch sees no CUDA device; use 'cpu'")
    return dev


def _init(net: torch.nn.Module, seed: int, x: torch.Tensor, output: str, standardise: bool) -> None:
    """Glorot-uniform weights (suited to sigmoid units), zero biases, and an output bias that makes the
    untrained network emit the training mean: it starts from the mean block instead of 0.5 everywhere.
    With ``standardise``, the input shift/scale buffers get the training mean block and 1 / global std."""
    gen = torch.Generator().manual_seed(seed)
    mean_row = x.mean(dim=0)
    with torch.no_grad():
        if standardise:
            net.in_shift.copy_(mean_row)
            net.in_scale.fill_(1.0 / max(float((x - mean_row).pow(2).mean().sqrt()), 1e-6))
        for name in LAYERS:
            layer = getattr(net, name)
            torch.nn.init.xavier_uniform_(layer.weight, generator=gen)
            layer.bias.zero_()
        # output bias: the pre-activation that gives the mean block, minus what the (random) last hidden
        # layer adds on average, so the untrained network starts near the mean block, not at noise around it
        if output == "tanh":
            target = torch.atanh(mean_row.clamp(-0.99, 0.99))
        else:
            m = mean_row.clamp(0.01, 0.99)
            target = torch.log(m / (1 - m))
        h = torch.sigmoid(net.dec1(net.encode(x[:2000]))).mean(dim=0)
        net.dec2.bias.copy_(target - net.dec2.weight @ h)


def _val_mse(net: torch.nn.Module, val: torch.Tensor, dev: torch.device, chunk: int) -> float:
    total = 0.0
    with torch.no_grad():
        for i in range(0, len(val), chunk):
            x = val[i:i + chunk].to(dev)
            total += float(((net(x) - x) ** 2).sum(dtype=torch.float64))
    return total / (len(val) * N_VOXELS)


def _fingerprint(train: torch.Tensor, val: torch.Tensor) -> dict:
    """Cheap identity of the data, so a checkpoint is not resumed on other blocks by mistake."""
    return {"n_train": len(train), "n_val": len(val),
            "sum_train": float(train.sum(dtype=torch.float64)), "sum_val": float(val.sum(dtype=torch.float64))}


def _atomic_write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def _ckpt_paths(prefix: str | os.PathLike) -> tuple[Path, Path]:
    p = Path(prefix)
    return p.with_name(p.name + ".npz"), p.with_name(p.name + ".json")


def _save_checkpoint(prefix: str, net, best_state, opt, meta: dict) -> None:
    npz, js = _ckpt_paths(prefix)
    arrays = {f"model.{k}": v for k, v in module_state(net).items()}
    arrays.update({f"best.{k}": v for k, v in best_state.items()})
    osd = opt.state_dict()
    for idx, st in osd["state"].items():
        for key, val in st.items():
            arrays[f"opt.{idx}.{key}"] = (val.detach().cpu().numpy() if torch.is_tensor(val)
                                          else np.asarray(val))
    arrays["epoch"] = np.asarray(meta["epoch"], dtype=np.int64)
    meta = dict(meta, format=CHECKPOINT_FORMAT, version=CHECKPOINT_VERSION, param_groups=osd["param_groups"])
    # arrays first, then the JSON that points at them: a crash between the two leaves the previous JSON,
    # whose epoch no longer matches the arrays, and the resume refuses rather than mixing epochs
    save_state_file(npz, arrays)
    _atomic_write_text(js, json.dumps(meta, indent=1))


def _load_checkpoint(prefix: str, net, opt, expect: dict) -> tuple[dict, dict[str, np.ndarray]]:
    npz, js = _ckpt_paths(prefix)
    try:
        meta = json.loads(js.read_text())
    except json.JSONDecodeError as e:
        raise FormatError(f"{js}: checkpoint metadata is not valid JSON ({e}); delete it to start afresh") from e
    if meta.get("format") != CHECKPOINT_FORMAT or meta.get("version") != CHECKPOINT_VERSION:
        raise FormatError(f"{js}: not an ae checkpoint of version {CHECKPOINT_VERSION}")
    arrays = load_state_file(npz)
    if int(arrays.get("epoch", -1)) != meta["epoch"]:
        raise FormatError(f"{npz} holds epoch {int(arrays.get('epoch', -1))} but {js} says {meta['epoch']} "
                          "(interrupted while writing?); delete both to start afresh")
    for key in ("shape", "data", "optimizer"):
        if meta.get(key) != expect[key]:
            raise InvalidValueError(f"checkpoint {prefix} was written for {key} {meta.get(key)}, this run has "
                                    f"{expect[key]}; use another checkpoint path or resume=False")
    net.load_state_dict({k[6:]: torch.from_numpy(v.copy()) for k, v in arrays.items() if k.startswith("model.")})
    best = {k[5:]: v for k, v in arrays.items() if k.startswith("best.")}
    state: dict[int, dict[str, torch.Tensor]] = {}
    for k, v in arrays.items():
        if k.startswith("opt."):
            _, idx, key = k.split(".", 2)
            state.setdefault(int(idx), {})[key] = torch.from_numpy(v.copy())
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    return meta, best


def write_curves(summary: Mapping[str, Any], prefix: str | os.PathLike, title: str = "") -> list[Path]:
    """Write learning curves next to a model: ``<prefix>.curves.json`` and (with matplotlib) ``.curves.png``.

    Parameters
    ----------
    summary : mapping
        :meth:`TrainResult.summary` output (or a dict with ``history`` and ``best_epoch``).
    prefix : path
        Path prefix, e.g. the model path without ``.npz``.

    Returns
    -------
    list of Path
        The files written (the PNG only when matplotlib is installed).
    """
    p = Path(prefix)
    p.parent.mkdir(parents=True, exist_ok=True)
    js = p.with_name(p.name + ".curves.json")
    _atomic_write_text(js, json.dumps(summary, indent=1))
    written = [js]
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # plotting is an extra (sdfcodec[plot]); the JSON holds the same numbers
        return written
    hist = summary["history"]
    fig, ax = plt.subplots(figsize=(6, 4))
    ep = [h["epoch"] for h in hist]
    ax.semilogy(ep, [h["train_mse"] for h in hist], label="training")
    ax.semilogy(ep, [h["val_mse"] for h in hist], label="validation")
    if summary.get("best_epoch"):
        ax.axvline(summary["best_epoch"], color="gray", ls=":", label=f"kept (epoch {summary['best_epoch']})")
    ax.set_xlabel("epoch")
    ax.set_ylabel("per-voxel MSE (normalised)")
    ax.set_title(title or "autoencoder learning curves")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    png = p.with_name(p.name + ".curves.png")
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return written + [png]


def _progress_bar(enabled: bool):
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("{task.fields[info]}"), console=Console(stderr=True), transient=True,
                    disable=not enabled)


# -- the loop -------------------------------------------------------------------------------------------
def train_autoencoder(train: Any, validation: Any | None = None, *, code_size: int, hidden: int = 512,
                      output: str = "sigmoid", config: TrainConfig | None = None, resume: bool = False,
                      on_epoch: Callable[[dict], None] | None = None) -> TrainResult:
    """Train a ``4096 - hidden - code_size - hidden - 4096`` autoencoder to reproduce its input.

    Parameters
    ----------
    train : array_like
        ``(N, 16, 16, 16)`` or ``(N, 4096)`` float blocks (numpy or torch, any device; copied to CPU
        float32). For the sequential codec these are residuals in ``[-1, 1]``.
    validation : array_like or None
        Blocks for early stopping; None: a seeded random ``config.val_fraction`` of ``train`` is held out.
    code_size, hidden : int
        Code and hidden layer widths.
    output : {"sigmoid", "tanh"}
        Output activation (tanh for zero-centred residuals).
    config : TrainConfig or None
        Hyper-parameters (defaults: :class:`TrainConfig`).
    resume : bool
        Continue from ``config.checkpoint`` when its files exist (same data, shapes and optimizer).
    on_epoch : callable or None
        Called with each epoch's history record (used by tests to interrupt a run).

    Returns
    -------
    TrainResult
        The best epoch's weights (float32 numpy) and the learning curves.
    """
    cfg = (config or TrainConfig()).resolved()
    threads = torch.get_num_threads()
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    try:
        return _train(train, validation, code_size, hidden, output, cfg, resume, on_epoch)
    finally:
        torch.set_num_threads(threads)


def _train(train: Any, validation: Any | None, code_size: int, hidden: int, output: str, cfg: TrainConfig,
           resume: bool, on_epoch: Callable[[dict], None] | None) -> TrainResult:
    dev = _device(cfg.device)
    x = _as_rows(train, "training blocks")
    if validation is None:
        n_val = max(1, int(round(len(x) * cfg.val_fraction)))
        if len(x) - n_val < 1:
            raise ShapeError(f"need at least 2 blocks to train with a held-out validation set, got {len(x)}")
        perm = torch.from_numpy(np.random.default_rng([cfg.seed, 1]).permutation(len(x)))
        x, val = x[perm[n_val:]], x[perm[:n_val]]
    else:
        val = _as_rows(validation, "validation blocks")
        if len(x) < 1 or len(val) < 1:
            raise ShapeError(f"need training and validation blocks, got {len(x)} and {len(val)}")

    net = build_module(code_size, hidden, output)
    _init(net, cfg.seed, x, output, cfg.standardise)
    net.to(dev)
    if cfg.optimizer == "adam":
        opt: torch.optim.Optimizer = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    else:
        opt = torch.optim.SGD(net.parameters(), lr=cfg.lr, momentum=cfg.momentum)
    batch = cfg.batch_size or len(x)
    expect = {"shape": {"code_size": code_size, "hidden": hidden, "output": output},
              "data": _fingerprint(x, val), "optimizer": {"optimizer": cfg.optimizer, "batch_size": batch,
                                                           "standardise": cfg.standardise}}

    history: list[dict] = []
    start_epoch, best_epoch, bad, elapsed0 = 1, 0, 0, 0.0
    best_val = ref_val = initial_val = _val_mse(net, val, dev, cfg.eval_batch)
    best_state = module_state(net)
    if resume and cfg.checkpoint and all(p.exists() for p in _ckpt_paths(cfg.checkpoint)):
        meta, best_state = _load_checkpoint(cfg.checkpoint, net, opt, expect)
        net.to(dev)
        history, best_epoch, best_val = meta["history"], meta["best_epoch"], meta["best_val"]
        initial_val = meta["initial_val"]
        # the early-stopping state is a function of the history and the criterion: recomputed, so a run
        # resumed with another patience / min_improvement continues exactly as a fresh run with them would
        ref_val, bad, stop_at = _replay([h["val_mse"] for h in history], initial_val, cfg)
        if stop_at is not None and stop_at < len(history):
            warnings.warn(f"checkpoint {cfg.checkpoint} ran to epoch {len(history)}, past epoch {stop_at} where this "
                          f"run's early-stopping settings stop; its best weights (epoch {best_epoch}) are returned",
                          SDFCodecWarning, stacklevel=3)
        start_epoch = meta["epoch"] + 1
        elapsed0 = history[-1]["seconds"] if history else 0.0
        # a run that stopped early returns at once below (bad >= patience); one that hit an earlier
        # max_epochs continues up to this run's max_epochs
    # a resumed run whose criterion already stopped it (or whose max_epochs is already reached) trains no
    # further; its reason is the criterion's when that holds
    stopped = "early stopping" if bad >= cfg.patience else "max_epochs"
    t0 = time.perf_counter()
    steps_per_epoch = -(-len(x) // batch)
    with _progress_bar(cfg.progress) as prog:
        t_ep = prog.add_task(f"training ae-{code_size} ({cfg.optimizer}, {len(x)} blocks)",
                             total=cfg.max_epochs, completed=start_epoch - 1, info=f"val {best_val:.3e}")
        t_b = prog.add_task("  epoch", total=steps_per_epoch, info="")
        for epoch in range(start_epoch, cfg.max_epochs + 1):
            if bad >= cfg.patience:
                stopped = "early stopping"
                break
            net.train()
            prog.reset(t_b, total=steps_per_epoch if cfg.optimizer == "adam" else -(-len(x) // cfg.eval_batch))
            sq_sum = 0.0
            if cfg.optimizer == "adam":
                order = torch.from_numpy(np.random.default_rng([cfg.seed, 2, epoch]).permutation(len(x)))
                for i in range(0, len(x), batch):
                    xb = x[order[i:i + batch]].to(dev)
                    opt.zero_grad(set_to_none=True)
                    loss = torch.mean((net(xb) - xb) ** 2)
                    loss.backward()
                    opt.step()
                    sq_sum += float(loss.detach()) * len(xb)
                    prog.advance(t_b)
            else:
                # batch gradient descent: the gradient of the mean loss over the whole training split, summed
                # chunk by chunk (memory stays at one chunk), then a single step
                opt.zero_grad(set_to_none=True)
                for i in range(0, len(x), cfg.eval_batch):
                    xb = x[i:i + cfg.eval_batch].to(dev)
                    loss = torch.sum((net(xb) - xb) ** 2) / (len(x) * N_VOXELS)
                    loss.backward()
                    sq_sum += float(loss.detach()) * len(x)
                    prog.advance(t_b)
                opt.step()
            net.eval()
            v = _val_mse(net, val, dev, cfg.eval_batch)
            if not math.isfinite(v):
                raise InvalidValueError(f"ae training diverged at epoch {epoch} (validation error {v}); lower lr "
                                        f"(now {cfg.lr})")
            rec = {"epoch": epoch, "train_mse": sq_sum / len(x), "val_mse": v,
                   "seconds": elapsed0 + time.perf_counter() - t0, "lr": cfg.lr}
            history.append(rec)
            if v < best_val:  # the weights kept are those of the lowest validation error
                best_val, best_epoch = v, epoch
                best_state = module_state(net)
            if v < ref_val * (1 - cfg.min_improvement):  # a significant improvement resets the patience
                ref_val, bad = v, 0
            else:
                bad += 1
            prog.update(t_ep, advance=1, info=f"val {v:.3e} (best {best_val:.3e} @ {best_epoch})")
            done = bad >= cfg.patience or epoch == cfg.max_epochs
            if cfg.checkpoint and (epoch % cfg.checkpoint_every == 0 or done):
                _save_checkpoint(cfg.checkpoint, net, best_state, opt,
                                 {**expect, "epoch": epoch, "best_epoch": best_epoch, "best_val": best_val,
                                  "bad": bad, "history": history, "config": asdict(cfg),
                                  "initial_val": initial_val, "ref_val": ref_val})
            if on_epoch:
                on_epoch(rec)
            if bad >= cfg.patience:
                stopped = "early stopping"
                break
    return TrainResult(state=export_state(best_state), history=history, best_epoch=best_epoch, stopped=stopped,
                       config=asdict(cfg), n_train=len(x), n_val=len(val), initial_val_mse=initial_val)
