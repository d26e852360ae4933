"""The commands that read and write map files: codecs, info, encode, decode, mesh, search, verify, compare."""

from __future__ import annotations

import errno
import json
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import numpy as np
import typer
from ..errors import InputNotFoundError, InvalidValueError, SDFCodecError
from .common import reads_maps
from .common import (app, check_code_size, check_device_flag, cli, err, fail, human_bytes, load_volume, parse_region,
                     parse_truncation, parse_triple, PlainWriter, print_json, print_table, progress_bar,
                     refuse_existing, report, working, write_output)
from .common import json_option, overwrite_option  # the --json and --overwrite every command shares
from .common import finished_cleanly

if TYPE_CHECKING:
    from ..codec import Codec
    from ..map.facade import Map

__all__: list[str] = []  # commands register on the app; nothing to import from here

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")  # what open3d writes


@app.command("codecs")
@cli
def codecs_cmd(as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
               verbose: bool = typer.Option(False, "--verbose", "-v",
                                            help="Also the capabilities each codec declares (fast paths, weights, "
                                                 "shipped models: spec/codec-plugins.md, section 4a).")) -> None:
    """List installed codecs: id, code sizes, prefix-ordered, needs fitting, providing package."""
    from ..codec import capabilities
    from ..registry import get_codec_class, list_codecs

    rows = []
    for entry in list_codecs():
        row: dict[str, Any] = {"id": entry.id, "package": entry.package, "version": entry.version}
        try:
            cls = get_codec_class(entry.id)
            shipped = cls.shipped_models()
            row.update(code_sizes=list(cls.code_sizes), prefix_ordered=cls.prefix_ordered,
                       requires_fit=cls.requires_fit, shipped_models=None if shipped is None else {
                           k: list(v) for k, v in shipped.items()}, capabilities=sorted(capabilities(cls)),
                       status="ok")
            row["sizes"] = _sizes_text(cls, shipped)
        except SDFCodecError as e:  # one broken plugin is reported, the rest still listed
            row.update(code_sizes=None, prefix_ordered=None, requires_fit=None, shipped_models=None, sizes="?",
                       capabilities=None, status=f"failed: {e}")
        rows.append(row)
    if as_json:
        print_json(rows)
        return
    yn = {True: "yes", False: "no", None: "?"}
    caps = ("capabilities",) if verbose else ()
    print_table(("id", "code sizes", "prefix-ordered", "needs fitting", *caps, "package", "status"),
                [(r["id"], r["sizes"], yn[r["prefix_ordered"]], yn[r["requires_fit"]],
                  *((", ".join(r["capabilities"]) if r["capabilities"] is not None else "?",) if verbose else ()),
                  f"{r['package'] or '(run time)'} {r['version'] or ''}".strip(), r["status"])
                 for r in rows], title="installed sdfcodec codecs")


def _sizes_text(cls: Any, shipped: dict | None) -> str:
    """The code sizes column of ``codecs``: what ships trained and what only ``--fit`` makes, a mixture as its
    parts (``64 + 64``, as the README names it, not its 129 code elements)."""
    import inspect

    params = inspect.signature(cls.__init__).parameters
    if "pca_size" in params and "ae_size" in params:  # a mixture: a PCA part and an autoencoder part
        parts = f"{params['pca_size'].default} + {params['ae_size'].default}"
        return f"{parts} shipped ({', '.join(shipped)})" if shipped else f"{parts} (with --fit)"
    sizes = list(cls.code_sizes)
    if not cls.requires_fit or shipped is None:
        return ", ".join(map(str, sizes)) or "?"
    have = sorted({k for v in shipped.values() for k in v})
    ready = [k for k in sizes if k in have]
    text = ", ".join(map(str, ready)) + (f" shipped ({', '.join(shipped)})" if ready else "")
    if cls.prefix_ordered and len(have) > len(ready):  # a shipped basis cut to any length (pca)
        text += f", any prefix 1-{have[-1]}"
    fit = [k for k in sizes if k not in have]
    return "; ".join(t for t in (text, f"{', '.join(map(str, fit))} with --fit" if fit else "") if t)


@app.command("info")
@cli
@reads_maps
def info_cmd(map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
             as_json: bool = typer.Option(False, "--json", help="Machine-readable output.")) -> None:
    """Show a map's header, blocks by state, bytes on disk and ratio to a dense float32 volume."""
    from ..map.summary import local_info

    info = local_info(map_path)  # a local map directory without importing Zarr (0.2-0.4 s of this command)
    if info is None:  # anything else, or anything that light reader is not sure of: the ordinary reader
        from ..map import open_map

        info = open_map(map_path).info()
    if as_json:
        print_json(info)
        return
    b = info["blocks"]
    rows = [
        ("format version", str(info["format_version"])),
        ("codec", json.dumps(info["codec"])),
        ("code", f"{info['code_size']} x {info['code_dtype']} (levels {info['levels']})"
                 + (", metres as written (metric-codes)" if info.get("code_units") == "metres" else "")
                 + {"variable-rate": ", variable-rate: each block keeps the prefix its rate buys, entropy-coded "
                                     "(variable-rate-codes)",
                    "quantised": ", quantised with a step per element, entropy-coded"}.get(info.get("code_storage"), "")),
        ("layout", f"{info['chunk_blocks']}^3-block chunks of codes" + (
            f" in {info['shard_blocks']}^3-block shards (sharded-codes)" if info["shard_blocks"] else "")),
        ("voxel size", f"{info['voxel_size']} m"),
        ("truncation", f"[{info['truncation'][0]}, {info['truncation'][1]}] m"),
        ("origin", f"{info['origin']} m"),
        ("extent", f"{info['shape_voxels']} voxels, {info['grid_blocks']} blocks"),
        ("blocks", f"{b['coded']} coded, {b['empty']} empty, {b['unobserved']} unobserved"),
        ("dense float32", human_bytes(info["dense_float32_bytes"])),
        ("codes (uncompressed)", human_bytes(info["code_bytes_raw"])),
    ]
    bound = _field_bound(info)
    if bound is not None:  # the codec's config keeps it in normalised units: the user gave (and reads) metres
        rows.insert(2, ("error bound", bound))
    cs = info["codec_state"]
    embedded = cs["stored"] == "embedded" and cs["sha256"] is not None  # else codec/ holds only its metadata
    if info["bytes_on_disk"] is not None:
        rows += [("on disk", human_bytes(info["bytes_on_disk"]) + (
                     f" (codec state {human_bytes(info['codec_state_bytes'])})" if embedded else "")),
                 ("ratio dense : disk", f"{info['ratio_dense_to_disk']:.1f} : 1")]
        if embedded:
            rows.append(("ratio dense : disk without codec state", f"{info['ratio_dense_to_codes']:.1f} : 1"))
    else:
        rows.append(("on disk", "not known for a remote map (a server does not list its files); "
                                "`sdfcodec info` on a local copy shows it"))
    rows.append(("codec state", f"not stored: the shipped model {cs['model']} at code size {info['code_size']}, "
                                f"by reference (sha256 {cs['sha256'][:16]}...)"
                 if cs["stored"] == "reference" else "none (the codec learns nothing)" if cs["sha256"] is None
                 else f"embedded (sha256 {cs['sha256']})"))
    if info.get("observation_mask") is not None:
        kind = info["observation_mask"]
        rows.append(("observation mask", ("stored at the voxels its codes pin (pinned-observation-mask)"
                                          if kind.startswith("pinned") else
                                          "context-coded (coded-observation-mask)" if kind.startswith("context-coded")
                                          else "Blosc-compressed") + (", exact only where it decides the surface "
                                          "(approximate-observation-mask)" if kind.endswith("approximate") else "")))
    if info.get("refinement") is not None:
        rows.append(("surface refinement", f"corrections in steps of {info['refinement']['step'] * 1000:.3g} mm within "
                                           f"{info['refinement']['band'] * 1000:.3g} mm of the surface "
                                           "(surface-refinement)"))
    if info["residual"] is not None:
        rows.append(("residual (residual-bound)", _residual_line(info["residual"])))
    if info.get("integrity") is not None:
        from ..map.summary import integrity_line

        rows.append(("integrity", integrity_line(info["integrity"])))
    if info["state_warning"]:
        rows.append(("warning", info["state_warning"]))
    print_table(None, rows, title=f"map {map_path}")


@app.command("encode")
@cli
def encode_cmd(
    input: str = typer.Argument(..., metavar="INPUT", help=".npy/.npz dense TSDF in metres, or a map to transcode."),
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Map to write (a directory, e.g. room.sdfz)."),
    codec_id: Optional[str] = typer.Option(None, "--codec", help="Codec id (see `sdfcodec codecs`); default pca."),
    code_size: Optional[int] = typer.Option(None, "--code-size", help="Code length (e.g. 32, 64, 128)."),
    model: Optional[Path] = typer.Option(None, "--model", help="Trained codec (.npz from `sdfcodec train`)."),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="Voxel edge in metres (volumes)."),
    truncation: Optional[str] = typer.Option(None, "--truncation", help="d_min,d_max in metres [-0.04,0.1]."),
    origin: Optional[str] = typer.Option(None, "--origin", help="x,y,z metres of voxel (0,0,0) [0,0,0]."),
    key: Optional[str] = typer.Option(None, "--key", help="Array name inside an .npz input."),
    code_dtype: str = typer.Option("float32", "--code-dtype", help="float32, float16 or int8 code storage (int8: per-block offset and scale, a quarter of float32)."),
    fit: bool = typer.Option(False, "--fit", help="Fit the codec on the input instead of the shipped model."),
    fit_max_blocks: int = typer.Option(100_000, "--fit-max-blocks", help="Blocks sampled to fit a codec."),
    codec_state: Optional[str] = typer.Option(None, "--codec-state", help="reference (default for a shipped model): only the name and digest of the shipped model (readers need the plugin version that ships it); embedded (default for a fitted or trained codec): the map stores the codec's learned state (self-contained)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUTPUT if it exists."),
    device: str = typer.Option("cpu", "--device", help="Torch device to encode on (cpu, cuda)."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
    step: Optional[float] = typer.Option(None, "--step", help="Quantise the codes with this step (int16 codes, entropy-coded; |error| <= step/2 per element; pca, raw)."),
    target_bytes: Optional[float] = typer.Option(None, "--target-bytes", help="Make the map take B stored bytes per coded block, every file counted (a referenced shipped model excepted): variable-rate codes (pca-128 prefixes chosen per block, unless --code-size), or with --code-dtype int16 fixed-length int16 codes."),
    target_error: Optional[float] = typer.Option(None, "--target-error", help="The smallest variable-rate map whose surface stays within E metres: 99% of the observed voxels touching a surface crossing decode within E (the codes alone or beside a surface refinement, whichever takes fewer bytes), measured on a sample of 2048 coded blocks (docs/variable-rate.md)."),
    variable_rate: Optional[bool] = typer.Option(None, "--variable-rate/--fixed-rate", help="Variable-rate codes (prefix per block, entropy-coded; default with --target-bytes/--target-error) or fixed-length int16 codes (default with --step)."),
    max_error: Optional[float] = typer.Option(None, "--max-error", help="Absolute error bound in metres on observed voxels: with --codec sz3 SZ3's own bound (field compression), with block codecs (pca, ae...) a residual stage on top of the codes (full level only)."),
    sign_exact: bool = typer.Option(False, "--sign-exact", help="Every voxel touching a surface crossing of the input decodes with its sign (a residual stage on top of the codes; block codecs)."),
    chunk_blocks: Optional[int] = typer.Option(None, "--chunk-blocks", help="Blocks per axis of a chunk of codes (default: 16 for pca-64; smaller chunks transfer less per small remote region)."),
    shard_blocks: Optional[int] = typer.Option(None, "--shard-blocks", help="Store the chunks of codes in Zarr shards of N blocks per axis (a multiple of --chunk-blocks dividing 64, e.g. 32): objects of megabytes for maps of millions of blocks on object storage (readers before the extension sharded-codes refuse the map)."),
    keep_weights: bool = typer.Option(False, "--keep-weights", help="Carry the input map's fusion weights (uint8 counts in a lossy map, float16 with raw); by default only its observation mask is kept."),
    exact_mask: bool = typer.Option(False, "--exact-mask", help="Variable-rate maps: keep the observation mask exact. By default it is exact only where it decides the decoded surface and stored only there (the same surface, a smaller mask; extensions approximate-observation-mask and, for pca, pinned-observation-mask; docs/variable-rate.md)."),
    refine_step: Optional[float] = typer.Option(None, "--refine-step", help="Variable-rate pca maps: correct the voxels next to the decoded surface in steps of this many metres (extension surface-refinement; --target-bytes of 160 B or more does so on its own, sharing its bytes; docs/variable-rate.md)."),
    refine: bool = typer.Option(True, "--refine/--no-refine", help="Variable-rate maps: let --target-bytes spend bytes on a surface refinement (default) or on the codes alone."),
    exact: bool = typer.Option(False, "--exact", help="With --codec raw: store the voxels' own float32 metres (and float32 weights), read back bit for bit; without it raw is exact to (d_max - d_min) x 2^-24 m. Readers before the extension metric-codes refuse such maps."),
) -> None:
    """Encode a dense TSDF volume (or transcode a map) into a compressed map.

    The codec comes from --model, else the model its plugin ships at --code-size (pca: the eigenshapes cut to
    it, default 64; ae: ae-64; parallel, sequential: 64 + 64), else it is fitted on the input's non-empty
    blocks (also with --fit). The map stores the codec's state, or with --codec-state reference only a
    reference to the shipped model.
    """
    # the flags first: a mistyped one is refused before the map machinery loads (torch and Zarr, 2-3 s)
    trunc_flag = parse_truncation(truncation) if truncation else None
    org_flag = parse_triple(origin, "--origin")
    if codec_state not in (None, "embedded", "reference"):
        raise InvalidValueError(f"--codec-state must be embedded or reference, got {codec_state!r}")
    if code_size is not None and model is None:  # 0 or -1 is an error, never the default 64
        code_size = check_code_size(codec_id or "pca", code_size)
    vr = _variable_rate_wanted(variable_rate, step, target_bytes, target_error, code_dtype)
    if vr and code_size is None and model is None and (codec_id or "pca") == "pca" and not fit:
        code_size = 128  # the longest shipped eigenshapes: each block keeps the prefix its rate buys
    refuse_existing(output, overwrite, map_output=True)
    check_device_flag(device)
    from ..core.blocks import normalise, split_blocks
    from ..map import create_map, open_map
    from ..map.format import check_volume
    from ..model import load_model
    from ..registry import choose_codec

    src_map = None
    in_path = Path(input)
    if "://" in input or in_path.is_dir():
        src_map = open_map(input)
        vs, trunc, org = src_map.voxel_size, src_map.truncation, src_map.origin
        if keep_weights and not src_map.has_weights:
            fail(f"--keep-weights: {input} stores no fusion weights (only a map written with them has any); drop "
                 "the flag")
    else:
        if not in_path.exists():
            raise InputNotFoundError(errno.ENOENT, "no such input file", str(in_path))
        if keep_weights:
            fail(f"--keep-weights carries the fusion weights of a map; {in_path} is a volume, which has none")
        vol, meta = load_volume(in_path, key)
        vs = voxel_size if voxel_size is not None else meta.get("voxel_size")
        if vs is None:
            fail(f"{in_path} does not record its voxel size: pass --voxel-size (metres)")
        trunc = trunc_flag or tuple(meta.get("truncation", (-0.04, 0.1)))
        org = org_flag or tuple(meta.get("origin", (0.0, 0.0, 0.0)))
        vol = check_volume(vol, trunc)

    why_fit = "the model given needs fitting"
    if model is not None:
        codec = load_model(model)
        if codec_id and codec_id != codec.codec_id:
            raise InvalidValueError(f"--codec {codec_id} contradicts the model {model} (codec {codec.codec_id})")
        if code_size and code_size != codec.code_size:
            raise InvalidValueError(f"--code-size {code_size} contradicts the model {model} "
                                    f"(code size {codec.code_size})")
    elif max_error is not None and codec_id == "sz3":
        codec = _bounded_codec(codec_id, max_error, trunc)
    else:  # the shipped model at that size, unless --fit or the plugin ships none (then why_fit says so)
        codec, why_fit = choose_codec(codec_id or "pca", code_size, fit=fit)
        if why_fit is not None and not fit and codec.shipped_models():  # it ships models, not at this size
            raise InvalidValueError(f"{why_fit}, or pass --fit to fit one on the input (slow; the map then stores "
                                    "the fitted state)")
        if codec_id == "sz3" and max_error is None and not as_json:  # a bound the user did not choose: said
            err.print(f"note: --codec sz3 without --max-error: error bound "
                      f"{codec.get_config()['max_error'] * (trunc[1] - trunc[0]) * 1000:.3g} mm (the codec's "
                      "default); pass --max-error METRES to choose it", markup=False, highlight=False)

    if codec_state is None:  # a shipped model by reference (every byte a map needs is counted with it)
        codec_state = "reference" if codec.is_fitted and model is None and _ships(codec) else "embedded"
    if codec_state == "reference" and not codec.is_fitted:  # refused before spending the fit
        raise InvalidValueError(f"--codec-state reference needs a shipped model, but {codec!r} must be fitted "
                                f"({why_fit}); drop --fit, pick a shipped size, or store the state "
                                "(--codec-state embedded)")
    if vr:
        from ..map.varrate import check_variable_rate
        check_variable_rate(codec)  # before a fit, which may take long
        if max_error is not None or sign_exact:
            raise InvalidValueError("variable-rate codes carry no residual stage: drop --max-error/--sign-exact, or "
                                    "use --fixed-rate")
    else:
        _check_quantised_options(codec, step, target_bytes, code_dtype)
    residual_kw = {} if codec.field_compression() is not None and not sign_exact else {
        "max_error": max_error, "sign_exact": sign_exact}  # sz3's --max-error is its own bound
    if residual_kw:
        from ..map.residual import residual_spec

        residual_spec(codec, "int16" if step or target_bytes else code_dtype, vs, trunc, max_error, sign_exact) \
            if not vr else None
    fitted_on = None
    if not codec.is_fitted:
        # asked to (--fit), or no shipped model: learn from the input's blocks as the map will encode them
        from ..map.observed import fit_codec
        sample, observed = np.zeros((0, 16, 16, 16), np.float32), None
        if src_map is None:
            sample = split_blocks(vol).reshape(-1, 16, 16, 16)
        elif pairs := list(src_map.iter_blocks()):
            sample, coords = np.concatenate([b for _, b in pairs]), np.concatenate([c for c, _ in pairs])
            observed = src_map.read_observed(coords) if src_map.records_observation else None
        fitted_on = fit_codec(codec, normalise(sample, *trunc), observed, trunc, vs, max_blocks=fit_max_blocks, log=lambda n:
                              err.print(f"fitting {codec!r} on {n} non-empty blocks of the input: {why_fit}", markup=False))

    shape = src_map.shape_voxels if src_map is not None else (0, 0, 0)

    def write(code_step: Optional[Any] = None, again: bool = False) -> Any:
        # again: the one rate-control correction pass replaces the map this command just wrote
        with progress_bar() as prog, create_map(output, codec=codec, voxel_size=vs, truncation=trunc, origin=org,
                                             shape_voxels=shape, overwrite=overwrite or again, device=device,
                                             code_dtype="int16" if code_step is not None else code_dtype,
                                             code_step=code_step, tool="sdfcodec encode", source=str(input),
                                             codec_state=codec_state, chunk_blocks=chunk_blocks,
                                             shard_blocks=shard_blocks, variable_rate=vr_kw,
                                             keep_weights=keep_weights or None, exact=exact, **residual_kw) as m:
            if src_map is not None:
                total = src_map.count_states()["coded"]
                task = prog.add_task("transcoding", total=total, rate="")
                m.write_map(src_map, progress=lambda n: prog.advance(task, n), keep_weights=keep_weights)
            else:
                nblocks = int(np.prod([-(-n // 16) for n in vol.shape]))
                task = prog.add_task("encoding", total=nblocks, rate="")
                m.write_volume(vol, progress=lambda n: prog.advance(task, n))
        return m

    vr_kw = None
    if vr:
        vr_kw = {k: v for k, v in (("step", step), ("target_bytes", target_bytes), ("target_error", target_error))
                 if v is not None} | ({"exact_mask": True} if exact_mask else {}) | (
            {"refine_step": refine_step} if refine_step is not None else {}) | ({} if refine else {"refine": False})
        m, quant = write(), None
        quant = _variable_rate_summary(m, output, target_bytes, target_error)
    else:
        if target_error is not None:
            raise InvalidValueError("--target-error chooses variable-rate codes: drop --fixed-rate/--code-dtype")
        if refine_step is not None:
            raise InvalidValueError("--refine-step refines variable-rate codes: add --variable-rate (or drop "
                                    "--fixed-rate/--code-dtype)")
        m, quant = _encode_quantised(write, codec, step, target_bytes, code_dtype,
                                     lambda: _rate_sample(codec, None if src_map is not None else vol, src_map,
                                                          trunc, vs, device), output)
    info = m.info()
    if info["state_warning"] and not as_json:  # --json carries it in the summary, stdout stays one document
        err.print(f"warning: {output}: {info['state_warning']}", markup=False)
    summary = {"output": str(output), "codec": codec.get_config(), "fitted_on_blocks": fitted_on,
               "codec_state": info["codec_state"], "state_warning": info["state_warning"],
               "blocks": info["blocks"], "bytes_on_disk": info["bytes_on_disk"],
               "ratio_dense_to_disk": info["ratio_dense_to_disk"]}
    if quant is not None:
        summary["quantisation"] = quant
    if info["residual"] is not None:
        summary["residual"] = info["residual"]
    report(summary, as_json, lambda: (
        f"wrote {output} with {_codec_words(codec, info, model, fitted_on, vr)}: "
        f"{info['blocks']['coded']} coded blocks, {human_bytes(info['bytes_on_disk'])} on disk, "
        f"{info['ratio_dense_to_disk']:.1f}:1 against dense float32" + ("" if quant is None else
        f"; codes quantised with step {quant['step']:.4g}: {quant['bytes_per_coded_block']:.1f} stored bytes per "
        f"coded block ({quant['codes_bytes_per_coded_block']:.1f} of codes" + (
            f", {quant['refinement']['bytes_per_coded_block']:.1f} of surface refinement at "
            f"{quant['refinement']['step'] * 1000:.3g} mm" if quant.get("refinement") else "") + ")" +
        (f", target {quant['target_bytes']:g} B ({quant['passes']} {'pass' if quant['passes'] == 1 else 'passes'})" if quant.get("target_bytes") else "")
        + (f", target error {quant['target_error'] * 1000:g} mm at 99% of the voxels that place the surface (sampled)"
           if quant.get("target_error") else ""))
        + ("" if info["residual"] is None else f"; {_residual_line(info['residual'])}")))


def _codec_words(codec: Codec, info: dict, model: Optional[Path], fitted_on: Optional[int], vr: bool) -> str:
    """What ``encode`` chose, said (no silent choice): ``pca-64 (shipped model, by reference)``,
    ``pca-128 prefixes (...)`` for variable-rate codes, ``sz3 (7 mm bound)``, ``ae-64 (fitted on N blocks)``."""
    bound = _field_bound(info)
    if bound is not None:
        return f"{codec.codec_id} ({bound.split(' on ')[0]} bound)"
    sized = len(type(codec).code_sizes) > 1  # raw has one size (its 4,096 voxels): no choice to state
    name = (f"{codec.codec_id}-{codec.code_size}" if sized else codec.codec_id) + (" prefixes" if vr else "")
    where = (f"from {model}" if model is not None else f"fitted on {fitted_on} blocks" if fitted_on else
             "shipped model" if info["codec_state"]["stored"] == "reference" or _ships(codec) else None)
    if where is not None and info["codec_state"]["stored"] == "reference":
        where += ", by reference"
    return name + (f" ({where})" if where else "")


def _field_bound(info: dict) -> str | None:
    """``info``'s line for a field compressor's error bound (sz3: ``max_error`` in its config is in normalised
    units, 1 = d_max - d_min), in millimetres; None for a codec without one."""
    normalised = info["codec"].get("max_error") if info["codec"].get("id") == "sz3" else None
    if normalised is None:
        return None
    d_min, d_max = info["truncation"]
    return (f"{normalised * (d_max - d_min) * 1000:.3g} mm on every observed voxel "
            f"(max_error {normalised:.4g} of the truncation range in the codec's config)")


def _variable_rate_wanted(flag: Optional[bool], step: Optional[float], target_bytes: Optional[float],
                          target_error: Optional[float], code_dtype: str) -> bool:
    """Whether ``encode`` writes variable-rate codes: ``--variable-rate``, else a byte or error target with float32
    codes (the default ``--code-dtype``; ``--code-dtype int16`` keeps the fixed-length int16 codes)."""
    from ..map.rate import check_target

    if target_bytes is not None:
        check_target(target_bytes)
    if target_error is not None and not (np.isfinite(target_error) and target_error > 0):
        raise InvalidValueError(f"--target-error must be a finite number of metres > 0, got {target_error}")
    if target_error is not None and (step is not None or target_bytes is not None):
        given = " and ".join(f for f, v in (("--step", step), ("--target-bytes", target_bytes)) if v is not None)
        raise InvalidValueError(f"--target-error chooses the codes' step and their bytes itself: drop {given}")
    if flag is not None:
        if flag and code_dtype != "float32":
            raise InvalidValueError(f"--variable-rate stores its own codes; --code-dtype {code_dtype} contradicts it")
        if flag and sum(v is not None for v in (step, target_bytes, target_error)) != 1:
            raise InvalidValueError("--variable-rate needs one of --step, --target-bytes or --target-error")
        return flag
    return (target_bytes is not None or target_error is not None) and code_dtype == "float32" and step is None


def _ships(codec: Codec) -> bool:
    """Whether ``codec`` holds the state of a model its plugin ships (then a map references it by default)."""
    from ..errors import SDFCodecError
    from ..map.codec_state import shipped_reference

    try:
        return bool(codec.state_dict()) and shipped_reference(codec) is not None
    except SDFCodecError:
        return False


def _variable_rate_summary(m: Map, output: Path, target: Optional[float], error: Optional[float]) -> dict:
    """The ``quantisation`` summary of a variable-rate map: its step, bytes per coded block (every file, and the
    code streams alone), the mean prefix length, the target met."""
    from ..map.rate import stored_bytes

    got = stored_bytes(output)
    vr = m.header.codes.variable_rate
    _, codes = m.read_codes()
    nz = codes != 0
    mean_len = float(np.where(nz.any(1), codes.shape[1] - np.argmax(nz[:, ::-1], axis=1), 0).mean()) if len(codes) else 0.0
    out = {"variable_rate": True, "step": vr.step[0] if len(vr.step) == 1 else vr.step,
           "bytes_per_coded_block": got["total"], "codes_bytes_per_coded_block": got["codes"],
           "mean_prefix_length": mean_len}
    if target is not None:
        out["target_bytes"], out["passes"] = target, 1
    if error is not None:
        out["target_error"] = error
    if vr.refinement is not None:  # spec 6h: its step and band in metres, its streams' bytes
        out["refinement"] = {"step": vr.refinement.step * 2.0 ** -24, "band": vr.refinement.tau * 2.0 ** -24,
                             "bytes_per_coded_block": got["refinement"]}
    return out


def _residual_line(r: dict) -> str:
    """One phrase for a map's residual stage (``info()["residual"]``)."""
    what = " and ".join(([f"max error {r['max_error'] * 1000:g} mm"] if r["max_error"] is not None else [])
                        + (["sign-exact"] if r["sign_exact"] else []))
    per = "" if r["bytes_per_coded_block"] is None else f", {r['bytes_per_coded_block']:.1f} B per coded block"
    return f"residual stage ({what}; step {r['step'] * 1000:.4g} mm{per}; holds at {r['holds_at']})"


def _bounded_codec(codec_id: Optional[str], max_error: float, trunc: tuple[float, float]) -> Codec:
    """The codec ``--codec sz3 --max-error`` (metres) asks for: sz3 at that bound in normalised units (other codecs
    get the bound as a residual stage, :mod:`sdfcodec.map.residual`)."""
    from ..registry import get_codec

    if not (np.isfinite(max_error) and max_error > 0):
        raise InvalidValueError(f"--max-error must be a positive number of metres, got {max_error}")
    return get_codec("sz3", max_error=float(max_error) / (trunc[1] - trunc[0]))


def _rate_sample(codec: Codec, vol: Any, src_map: Map | None, trunc: tuple[float, float], vs: float,
                 device: str) -> tuple[np.ndarray, Any, int]:
    """Codes (and packed observation masks, or None) of up to ``SAMPLE_BLOCKS`` coded blocks of the input (a
    volume ``vol``, or the map ``src_map``), encoded as the map writer encodes them: the rate model's sample;
    and the number of blocks the map will code."""
    from ..core.blocks import normalise, split_blocks
    from ..map.format import free_space
    from ..map.observed import SURFACE_WEIGHT, encode_blocks, pack_mask
    from ..map.rate import SAMPLE_BLOCKS

    obs = None
    if src_map is None:
        v = normalise(split_blocks(vol).reshape(-1, 16, 16, 16), *trunc)
        v = v[~free_space(v)]
        n_coded = len(v)
        v = v[np.unique(np.linspace(0, len(v) - 1, min(len(v), SAMPLE_BLOCKS)).astype(int))] if len(v) else v
    else:
        parts, masks, n, n_coded = [], [], 0, src_map.count_states()["coded"]
        for coords, blocks in src_map.iter_blocks():
            parts.append(normalise(np.clip(blocks, *trunc), *trunc))
            if src_map.records_observation:
                masks.append(src_map.read_observed(coords))
            n += len(coords)
            if n >= SAMPLE_BLOCKS:
                break
        v = np.concatenate(parts)[:SAMPLE_BLOCKS] if parts else np.zeros((0, 16, 16, 16), np.float32)
        obs = np.concatenate(masks)[:SAMPLE_BLOCKS] if masks else None
    codes = encode_blocks(codec, v, obs, trunc, vs, SURFACE_WEIGHT, device)
    return codes, None if obs is None else pack_mask(obs), n_coded


def _check_quantised_options(codec: Codec, step: Optional[float], target: Optional[float], code_dtype: str) -> None:
    """Refuse bad ``--step`` / ``--target-bytes`` input (checked before any fit or encode)."""
    if step is None and target is None:
        return
    from ..map.rate import check_target
    from ..core.quantize import check_quantisable, check_step

    if step is not None and target is not None:
        raise InvalidValueError("--step and --target-bytes both choose the step: pass one of them")
    if code_dtype not in ("float32", "int16"):
        raise InvalidValueError(f"--step/--target-bytes store int16 codes; --code-dtype {code_dtype} contradicts "
                                "them (leave --code-dtype out)")
    if step is not None:
        check_step(step, codec.code_size, "--step")
    else:
        check_target(target)
    check_quantisable(codec)


def _encode_quantised(write: Any, codec: Codec, step: Optional[float], target: Optional[float], code_dtype: str,
                      sample: Any, output: Path) -> tuple[Any, Optional[dict]]:
    """``encode --step S`` / ``--target-bytes B``: int16 codes at step S, or at the step a rate model fitted on a
    sample of the input's blocks gives for B stored bytes per coded block, rewritten once with a corrected step
    when the written map misses B by more than 5 %. Neither: ``write()`` as it is. Returns ``(map, summary)``."""
    if step is None and target is None:
        return write(), None
    from ..map.format import code_layout, mask_compressors
    from ..map.rate import (codes_rate_model, correct_step, mask_bytes_estimate, metadata_bytes_estimate,
                            plan_step, stored_bytes)

    _check_quantised_options(codec, step, target, code_dtype)
    if step is not None:
        m = write(step)
        got = stored_bytes(output)
        return m, {"step": float(step), "bytes_per_coded_block": got["total"],
                   "codes_bytes_per_coded_block": got["codes"]}
    t = float(target)
    codes, packed, n_coded = sample()
    if not len(codes):
        raise InvalidValueError("the input has no coded blocks (all free space): there are no codes to rate-control")
    layout = code_layout(codec, "float16", None, None)  # the chunk shape of int16 codes (same item size)
    model = codes_rate_model(codes, layout.chunk_code, layout.chunk_blocks)
    other = (mask_bytes_estimate(packed, layout.chunk_blocks, mask_compressors()[0])
             + metadata_bytes_estimate(codec.code_size) / max(n_coded, 1))
    s1 = plan_step(t, model, other)
    m = write(s1)
    got, passes, s = stored_bytes(output), 1, s1
    first = {"step": s1, "bytes_per_coded_block": got["total"]}
    s2 = correct_step(t, model, s1, got)
    if s2 is not None:
        m = write(s2, again=True)
        got, passes, s = stored_bytes(output), 2, s2
    return m, {"step": s, "target_bytes": t, "bytes_per_coded_block": got["total"],
               "codes_bytes_per_coded_block": got["codes"], "passes": passes,
               "model_bytes_per_coded_block": model.bytes_at(s1) + other, "first_pass": first}


@app.command("decode")
@cli
@reads_maps
def decode_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    output: Path = typer.Argument(..., metavar="OUTPUT", help="Dense TSDF (metres) to write: .npy (the array), or "
                                  ".npz (tsdf, voxel_size, origin, truncation: `encode` reads it back without flags)."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    region: Optional[str] = typer.Option(None, "--region", help="x0:x1,y0:y1,z0:z1 (half-open voxels, or metres)."),
    units: str = typer.Option("voxels", "--units", help="Units of --region: voxels or m."),
    device: str = typer.Option("cpu", "--device", help="Torch device to decode on."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUTPUT if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary."),
) -> None:
    """Decode a map (or a region of it) to a dense volume in metres, free space where nothing is coded.

    Metre regions are half-open like voxel ones: the voxels whose centres lie in [x0, x1) x [y0, y1) x [z0, z1).
    """
    from ..map import open_map
    from ..map.format import region_voxels

    if output.suffix not in (".npy", ".npz"):
        fail(f"OUTPUT must end in .npy or .npz, got {output}")
    refuse_existing(output, overwrite)
    check_device_flag(device)
    m = open_map(map_path)
    _warn_lossy_level(m, level)
    box = parse_region(region)
    lo = [a for a, _ in region_voxels(box, units, m.shape_voxels, m.origin, m.voxel_size)]
    origin = [float(o + a * m.voxel_size) for o, a in zip(m.origin, lo)]  # where voxel (0, 0, 0) of OUTPUT lies
    with working("decoding"):
        vol = m.decode_region(box, units=units, level=level, device=None if device == "cpu" else device)
    if not isinstance(vol, np.ndarray):
        vol = vol.cpu().numpy()
    def save(tmp: Path) -> bool:
        with open(tmp, "wb") as f:
            if output.suffix == ".npz":  # the names encode reads back (load_volume)
                np.savez(f, tsdf=vol, voxel_size=np.float64(m.voxel_size), origin=np.array(origin),
                         truncation=np.array(m.truncation, dtype=np.float64))
            else:
                # through Python's write, not numpy's C-level tofile: a short write then raises OSError with its
                # errno (ENOSPC, EFBIG...) instead of numpy's errno-less "requested and written"
                np.save(PlainWriter(f), vol)
        return True

    write_output(output, save)
    summary = {"output": str(output), "shape": list(vol.shape), "level": level or m.code_size,
               "voxel_size": m.voxel_size, "origin": origin, "truncation": list(m.truncation)}
    from ..evaluation.compare import level_text

    report(summary, as_json, lambda: (
        f"wrote {output}: {' x '.join(map(str, vol.shape))} voxels of float32 metres "
        f"({level_text(summary['level'], m.code_size)}, "
        f"voxel {m.voxel_size} m, origin {tuple(round(o, 6) for o in origin)} m)"))


def _warn_lossy_level(m: Map, level: Optional[int]) -> None:
    """A warning when ``--level`` drops the guarantee of a map's residual stage (``--max-error``/``--sign-exact``
    hold at the full level only): the decode is then the codes' alone."""
    r = m.header.residual
    if r is None or level is None or level >= m.code_size:
        return
    held = ([f"the {r.max_error * 1000:g} mm error bound"] if r.max_error is not None else []) + (
        ["the exact signs"] if r.sign_exact else [])
    verb, it = ("no longer hold", "them") if len(held) > 1 or not r.max_error else ("no longer holds", "it")
    err.print(f"warning: {m.location}: --level {level} decodes without the residual stage, so {' and '.join(held)} "
              f"of the full level ({m.code_size}) {verb}; leave --level out to keep {it}", markup=False,
              highlight=False)


@app.command("mesh")
@cli
@reads_maps
def mesh_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    output: Path = typer.Argument(..., metavar="OUT.ply", help="Triangle mesh to write (.ply, .obj, .stl...)."),
    level: Optional[int] = typer.Option(None, "--level", help="Decode only the first K code elements."),
    region: Optional[str] = typer.Option(None, "--region", help="x0:x1,y0:y1,z0:z1: mesh only the blocks touching it (half-open voxels, or metres with --units m)."),
    units: str = typer.Option("voxels", "--units", help="Units of --region: voxels or m."),
    overwrite: bool = overwrite_option("OUT.ply"),
    as_json: bool = json_option(),
) -> None:
    """Extract the zero level set of a map (or of the blocks touching --region) as a triangle mesh (marching
    cubes on the decoded blocks)."""
    if output.suffix.lower() not in MESH_SUFFIXES:  # before any work: open3d would say only that it failed
        fail(f"could not write {output}: unsupported extension; use .ply, .obj or .stl")
    box = parse_region(region)
    refuse_existing(output, overwrite)
    import open3d as o3d

    from ..fusion.tsdf import mesh_from_blocks
    from ..map import open_map

    m = open_map(map_path)
    _warn_lossy_level(m, level)
    coords, blocks = [], []
    for c, b in m.iter_decoded(box, units=units, level=level):
        coords.append(c)
        blocks.append(b)
    if not coords:
        fail(f"{map_path} has no coded blocks{' touching ' + region if region else ''}: nothing to mesh")
    mesh = mesh_from_blocks(np.concatenate(coords), np.concatenate(blocks), origin=m.origin,
                            voxel_size=m.voxel_size, truncation=m.truncation)
    def write_mesh(tmp: Path) -> bool:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            return False
        # open3d reports success even when the disk filled up under it (a truncated file): read it back
        back = o3d.io.read_triangle_mesh(str(tmp))
        return len(back.vertices) == len(mesh.vertices) and len(back.triangles) == len(mesh.triangles)

    # open3d reports only failure, not why: with a known format it is the file system (write_output says so)
    write_output(output, write_mesh, "writing the mesh")
    summary = {"output": str(output), "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}
    report(summary, as_json, lambda: (
        f"wrote {output}: {summary['vertices']} vertices, {summary['triangles']} triangles (metres, in the map's "
        "frame)"))


@app.command("search")
@cli
@reads_maps
def search_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    query: str = typer.Option("floor", "--query", help="floor, ceiling, wall, edge, corner, pole, like:X,Y,Z[;X,Y,Z] (blocks like these), or a saved query (.npz)."),
    level: Optional[int] = typer.Option(None, "--level", help="Match only the first K code elements."),
    threshold: Optional[float] = typer.Option(None, "--threshold", help="Select blocks scoring at most this."),
    top: Optional[int] = typer.Option(None, "--top", help="Select the K best-scoring blocks."),
    behind: Optional[str] = typer.Option(None, "--behind", help="solid (exact SDF) or unobserved (fused); default: what the map records."),
    up: Optional[str] = typer.Option(None, "--up", help="Up direction x,y,z in the map's grid; default: the map's header, else 0,0,1."),
    tilt: Optional[float] = typer.Option(None, "--tilt", help="Also match surfaces tilted up to DEG degrees from level."),
    shape_only: bool = typer.Option(False, "--shape-only", help="Floor, ceiling, wall: select by shape score alone, without the map-level stage (lowest level, closing ceiling, large walls)."),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Write the picture (and mesh of the selection) here."),
    device: Optional[str] = typer.Option(None, "--device", help="Torch device for scoring (default: cuda if present)."),
    no_mesh: bool = typer.Option(False, "--no-mesh", help="Do not write the mesh of the expanded blocks."),
    overwrite: bool = overwrite_option("search.png and expanded.ply in --out"),
    as_json: bool = typer.Option(False, "--json", help="Print every selected block's coordinates and score."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Also print how the threshold was chosen, what the "
                                 "map says about itself and what the map-level stage and plane check kept."),
) -> None:
    """Search a compressed map in code space and decompress only the blocks that match (the paper's Fig. 7).

    The first search of a map with a codec builds the query and calibrates its threshold for the map's up
    direction (about a second for a floor, a few seconds for walls on 2 cores; said on stderr) and caches them
    (sdfcodec.search.cache); later searches reuse them. The plane check's calibrations ship with sdfcodec for
    the shipped pca sizes."""
    if out_dir is not None:
        refuse_existing(out_dir, overwrite, files=("search.png", "expanded.ply"))
    check_device_flag(device)
    from ..search.cache import announce_builds, cache_dir
    from ..view.search import format_summary, search_command

    said: set[str] = set()

    def tell(what: str) -> None:  # once per kind of work (a wall search calibrates one plane check per wall)
        kind = " ".join(what.split()[:4])
        if kind not in said:
            said.add(kind)
            where = cache_dir()
            err.print(f"{what} (once; {f'cached in {where}' if where else 'the disk cache is off'})", markup=False,
                      highlight=False)

    # with --json, stdout is one document and stderr only errors: no notes, no progress lines
    with (nullcontext() if as_json else announce_builds(tell)), \
            (nullcontext() if as_json else working(f"searching {map_path} for {query}")):
        summary = search_command(map_path, query, level, threshold, top, out_dir, as_json, device, mesh=not no_mesh,
                                 overwrite=overwrite, behind=behind, up=up, tilt=tilt, scene=not shape_only)
    # the line says whether the time includes building the query (nothing is listened for with --json)
    report(summary, as_json, lambda: format_summary(dict(summary, built=sorted(said)), verbose=verbose))
    finished_cleanly()  # its files are written and closed: the process may end without Python's teardown


@app.command("verify")
@cli
@reads_maps
def verify_cmd(
    map_path: str = typer.Argument(..., metavar="MAP", help="Map path or URL."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable report."),
    # 4096 = sdfcodec.map.verify.DEFAULT_DECODE_BLOCKS (not imported here: --help stays light)
    decode_blocks: int = typer.Option(4096, "--decode-blocks", min=0, help="Coded blocks to decode as a check "
                                      "(0: none; every other check still runs, and torch is never imported)."),
) -> None:
    """Check a map: header, every chunk's checksum, codec state digest, states against codes, a decode, and
    every object against the map's integrity manifest (and its signature)."""
    from ..map.verify import verify_command

    raise typer.Exit(verify_command(map_path, as_json, decode_blocks=decode_blocks))


@app.command("compare")
@cli
@reads_maps
def compare_cmd(original: str = typer.Argument(..., metavar="ORIGINAL", help="The original: a lossless map, or the .npy/.npz volume DECODED was encoded from."),
                decoded: str = typer.Argument(..., metavar="DECODED", help="The map to judge, on the same grid."),
                level: Optional[int] = typer.Option(None, "--level", help="Decode DECODED at this prefix level."),
                key: Optional[str] = typer.Option(None, "--key", help="Array name inside an .npz ORIGINAL."),
                as_json: bool = typer.Option(False, "--json", help="Machine-readable output (metres).")) -> None:
    """Surface fidelity of DECODED against ORIGINAL: Chamfer-L1, F-score, near-surface error (docs/surface.md).

    A volume ORIGINAL lies on DECODED's grid (its voxel size and origin) and is truncated as the map was."""
    from ..evaluation.compare import compare_command, metrics_rows, metrics_sentence, metrics_title

    volume = None
    if key is not None and Path(original).suffix != ".npz":
        fail(f"--key names an array of an .npz ORIGINAL; {original} is not one")
    if Path(original).suffix in (".npy", ".npz") and Path(original).is_file():
        volume = load_volume(Path(original), key)
    summary = compare_command(original, decoded, level=level, quiet=as_json, volume=volume)
    if as_json:
        print_json(summary)
        return
    print_table(("metric", "value"), metrics_rows(summary), title=metrics_title(summary))
    report(summary, False, lambda: metrics_sentence(summary))


@app.command("sign")
@cli
def sign_cmd(map_path: Path = typer.Argument(..., metavar="MAP", help="Local map directory to sign."),
             key: Path = typer.Option(..., "--key", metavar="KEY", help="Ed25519 private key: PEM (`sdfcodec keygen`, "
                                      "`openssl genpkey -algorithm ed25519`) or its raw 32-byte seed."),
             as_json: bool = typer.Option(False, "--json", help="Print a JSON summary.")) -> None:
    """Sign a map with an Ed25519 key (its manifest and header), atomically; readers trust it with --trusted-key."""
    from ..map.sign import sign_map

    kid = sign_map(map_path, key)
    report({"map": str(map_path), "key": kid}, as_json, lambda: f"signed {map_path} with key {kid}")


@app.command("keygen")
@cli
def keygen_cmd(key: Path = typer.Argument(..., metavar="KEY", help="Private key file to write (PEM); the public key "
                                          "goes to KEY.pub."),
               overwrite: bool = typer.Option(False, "--overwrite", help="Replace KEY and KEY.pub if they exist."),
               as_json: bool = typer.Option(False, "--json", help="Print a JSON summary.")) -> None:
    """Make an Ed25519 key pair for `sdfcodec sign` (KEY, mode 0600) and `--trusted-key` (KEY.pub)."""
    from ..map.signing import key_id, keygen

    priv, pub = keygen(key, overwrite=overwrite)
    kid = key_id(pub)
    report({"private_key": str(priv), "public_key": str(pub), "key": kid}, as_json,
           lambda: f"wrote {priv} (keep it secret) and {pub} (give it to readers: --trusted-key); key {kid}")
