"""`admc-pipe`: the command line. Thin: parse, call pipeline functions, print."""

from __future__ import annotations

import functools
import os
import signal
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from admc.common.layout import ENGINE_CHOICES, ENSEMBLES
from admc.errors import AdmcError, user_os_error
from admc.pipeline import config as config_mod

app = typer.Typer(
    help="admc: render a scene corpus, train an adversarial Monte Carlo denoiser, evaluate it.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(soft_wrap=True)  # long paths and Markdown rows stay whole lines in logs and pipes
err = Console(stderr=True, soft_wrap=True)

ConfigOpt = Annotated[
    Optional[list[Path]],
    typer.Option(
        "--config",
        "-c",
        help="TOML config overlaying configs/default.toml (repeatable: each file overlays the ones before it).",
    ),
]
SetOpt = Annotated[
    Optional[list[str]], typer.Option("--set", "-s", help="Override a value: section.key=value (repeatable).")
]
SchedulerOpt = Annotated[Optional[str], typer.Option(help="sync | threads | processes | a dask scheduler address.")]


def _user_errors(fn):
    """A user-fixable failure (any admc.errors.AdmcError, or a file system that refuses a write: see
    user_os_error) prints its one message and exits 2; anything else is a bug and keeps its traceback.
    ADMC_DEBUG=1 shows the traceback of user errors too."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (AdmcError, OSError) as exc:
            message = str(exc) if isinstance(exc, AdmcError) else user_os_error(exc)
            if message is None or os.environ.get("ADMC_DEBUG"):
                raise
            err.print(Text.assemble(("error: ", "bold red"), message))
            raise typer.Exit(2)

    return wrapper


def _load(config: Optional[list[Path]], overrides: Optional[list[str]], scheduler: Optional[str] = None):
    """The checked config. Commands call this before importing their stage, so a missing config file or a
    bad key is named in well under a second, before torch and Mitsuba load."""
    items = list(overrides or [])
    if scheduler:
        items.append(f"run.scheduler={scheduler}")
    return config_mod.load_config(config, items)


@app.command()
@_user_errors
def render(config: ConfigOpt = None, set_: SetOpt = None, scheduler: SchedulerOpt = None) -> None:
    """Render the scene corpus: one multi-layer EXR + JSON sidecar per (scene, spp), plus a reference."""
    cfg = _load(config, set_, scheduler)
    from admc.pipeline.stages.render import render_corpus

    result = render_corpus(cfg)
    for note in result.notes:
        console.print(note, markup=False)
    table = Table(title=f"rendered {len(result.sidecars)} images of {len(result.scenes)} scenes")
    for column in ("scene", "spp", "specular", "seconds", "Msamples/s", "non-finite"):
        table.add_column(column)
    for s in result.sidecars:
        bad = sum(sum(counts.values()) for counts in s["nonfinite"].values())
        table.add_row(
            s["scene_id"],
            f"{s['spp']}{' (ref)' if s['reference'] else ''}",
            "yes" if s["has_specular"] else "no (skipped)",
            f"{s['render_seconds']:.2f}",
            f"{s['samples_per_second'] / 1e6:.2f}",
            str(bad),
        )
    console.print(table)
    no_spec = sorted({s["scene_id"] for s in result.sidecars if not s["has_specular"]})
    if no_spec:
        console.print(f"no glossy, conductor or dielectric BSDF, so no specular buffer: {', '.join(no_spec)}")
    console.print(f"EXRs: {result.renders_dir}  ({result.executed} rendered now, {result.cached} cached)")


def _print_dataset(result, workdir: str) -> None:
    from admc.pipeline.tiler.report import contact_sheet, contact_sheet_path
    from admc.stores.patches import store_summary

    for note in result.notes:
        console.print(note, markup=False)
    summary = store_summary(result.store)
    table = Table(title=f"patch store {result.store}")
    for column in ("split", "scenes", "diffuse rows", "specular rows", "rows per spp"):
        table.add_column(column)
    for split, entry in summary["splits"].items():
        per_spp = ", ".join(f"{spp}: {n}" for spp, n in sorted(entry["rows_per_spp"].items()))
        table.add_row(
            split, str(len(entry["scenes"])), str(entry["rows"]["diffuse"]), str(entry["rows"]["specular"]), per_spp
        )
    console.print(table)
    ranges = Table(title="stored value ranges (transformed, all splits)")
    for column in ("array", "min", "max"):
        ranges.add_column(column)
    merged: dict = {}
    for entry in summary["splits"].values():
        for name, (lo, hi) in entry["ranges"].items():
            old = merged.get(name, (lo, hi))
            merged[name] = (min(old[0], lo), max(old[1], hi))
    for name, (lo, hi) in sorted(merged.items()):
        ranges.add_row(name, f"{lo:.4g}", f"{hi:.4g}")
    console.print(ranges)
    handled = {k: v for k, v in summary["sanitization"].items() if any(n for n in v.values() if isinstance(n, int))}
    console.print(f"sanitized values: {handled if handled else 'none'}")
    for split in ("train", "val", "test"):
        if not summary["splits"][split]["scenes"]:
            console.print(f"[yellow]warning:[/] split {split!r} has no scenes (add scenes or change tile.split)")
    sheet = contact_sheet(result.store, contact_sheet_path(Path(workdir), result.store))
    if sheet:
        console.print(f"contact sheet (noisy | reference | albedo | normal): {sheet}")


@app.command()
@_user_errors
def dataset(
    config: ConfigOpt = None,
    set_: SetOpt = None,
    scheduler: SchedulerOpt = None,
    summary: Annotated[bool, typer.Option("--summary", help="Only summarise the existing store.")] = False,
) -> None:
    """Render + tile as one graph: the corpus into the 128x128 FP16 Zarr patch store (cached, incremental)."""
    cfg = _load(config, set_, scheduler)
    from admc.pipeline.stages.dataset import build_dataset, existing_dataset

    result = existing_dataset(cfg) if summary else build_dataset(cfg)
    if not summary:
        console.print(f"{result.executed} tasks run, {result.cached} cached; renders in {result.renders_dir}")
    _print_dataset(result, cfg.run.workdir)


@app.command()
@_user_errors
def tile(config: ConfigOpt = None, set_: SetOpt = None, scheduler: SchedulerOpt = None) -> None:
    """Tile already-rendered EXR sets into the patch store (renders nothing: run `render` first)."""
    cfg = _load(config, set_, scheduler)
    from admc.pipeline.stages.dataset import build_dataset

    result = build_dataset(cfg, render_missing=False)
    console.print(f"{result.executed} tile tasks run, {result.cached} cached")
    _print_dataset(result, cfg.run.workdir)


class Stage(str, Enum):
    pretrain = "pretrain"
    finetune = "finetune"


@app.command()
@_user_errors
def train(
    config: ConfigOpt = None,
    set_: SetOpt = None,
    scheduler: SchedulerOpt = None,
    stage: Annotated[
        Stage, typer.Option(help="pretrain on the corpus, or finetune from pretrained weights.")
    ] = Stage.pretrain,
    init: Annotated[
        Optional[Path],
        typer.Option(
            help="finetune from this checkpoint or weights file "
            "(default: the shipped weights matching the model config)."
        ),
    ] = None,
    restart: Annotated[
        bool, typer.Option("--restart", help="discard this stage's existing run and start over.")
    ] = False,
    nproc: Annotated[
        int,
        typer.Option(
            min=1,
            help="data-parallel training in N processes on this machine (one per GPU, "
            "or sharing the CPU); under torchrun leave it out.",
        ),
    ] = 1,
) -> None:
    """Train the CFM generator and WGAN-GP critic of both branches (builds the patch store first if needed).

    An interrupted or shorter run resumes exactly from its checkpoint (raise train.steps or train.minutes
    to train longer).
    Several processes (--nproc N, or `torchrun --nproc_per_node N -m admc.cli train ...`) split each batch."""
    cfg = _load(config, set_, scheduler)
    from admc.pipeline.stages.train import interrupted_note, run_training

    try:
        result = run_training(cfg, stage.value, init_from=init, restart=restart, nproc=nproc)
    except KeyboardInterrupt:
        err.print(interrupted_note(cfg, stage.value), markup=False, highlight=False)
        raise typer.Exit(130) from None
    if result.rank:
        return  # under torchrun, rank 0 reports the run
    for note in result.notes:
        console.print(note, markup=False)
    if result.last_losses:
        console.print(_train_table(stage.value, result))
    else:  # the checkpoint already held every step: say so rather than print an empty table
        chosen = ", ".join(
            f"{b} step {s['step']} (" + ", ".join(f"{k} {v:.4g}" for k, v in s.items() if k != "step") + ")"
            for b, s in result.selected.items()
        )
        console.print(
            f"{stage.value}: complete at step {result.step}, nothing to train (raise train.steps or "
            f"train.minutes to train longer)" + (f"; the weights hold {chosen}" if chosen else ""),
            markup=False,
        )
    if result.skipped_branches:
        console.print(f"skipped branches (no patches): {', '.join(result.skipped_branches)}")
    console.print(f"checkpoint: {result.checkpoint}\nweights: {result.weights}\nlogs: {result.out_dir}")


def _train_table(stage: str, result) -> Table:
    """The run's last losses and validation per branch."""
    table = Table(title=f"{stage}: step {result.step}")
    for column in ("branch", "last losses", "validation"):
        table.add_column(column)
    for branch in result.branches:
        losses = ", ".join(f"{k} {v:.4g}" for k, v in result.last_losses.get(branch, {}).items())
        val = ", ".join(f"{k} {v:.4g}" for k, v in result.validation.get(branch, {}).items())
        table.add_row(branch, losses, val)
    return table


WeightsOpt = Annotated[
    Optional[Path],
    typer.Option(
        help="Weights or checkpoint (default: this config's finetune, else pretrain run, else the shipped weights)."
    ),
]
DeviceOpt = Annotated[str, typer.Option(help="auto | cpu | cuda")]


@app.command()
@_user_errors
def denoise(
    inputs: Annotated[
        list[Path],
        typer.Argument(
            help="EXR(s): admc's, Blender's, pbrt-v4's or Mitsuba's "
            "layers, or OIDN-style NAME.hdr.exr (+ NAME.alb.exr, "
            "NAME.nrm.exr)."
        ),
    ],
    output: Annotated[
        Optional[Path],
        typer.Option("--output", "-o", help="Output EXR (one input only; default: INPUT.denoised.exr beside it)."),
    ] = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = "auto",
    tile: Annotated[
        Optional[int],
        typer.Option(
            min=1,
            help="Tile size in pixels (bounds memory; in float32 "
            "the result is the same at any size, in bf16 "
            "within its rounding). Default: 320 on a CPU (640 in "
            "OpenVINO), 512 on a GPU, at least 8 "
            "halos.",
        ),
    ] = None,
    ensemble: Annotated[
        int,
        typer.Option(
            help="Average the networks over 1, 2, 4 or 8 flips/transposes "
            "of the input: less error, that many times the time."
        ),
    ] = 1,
    dark_pass: Annotated[
        bool,
        typer.Option(
            help="Denoise dark regions again at 64x the exposure and take "
            "them from there (Table 1's admc-ens4+dark row): up to twice the "
            "time."
        ),
    ] = False,
    engine: Annotated[
        Optional[str],
        typer.Option(
            help="What runs the networks: auto (openvino on a CPU, "
            "torch on a GPU) | torch | onnxruntime | openvino "
            "(docs/engines.md). Default: the config's "
            "eval.engine."
        ),
    ] = None,
    layers: Annotated[
        Optional[list[str]],
        typer.Option(
            "--layers",
            help="Where admc's layers are in a file it does not recognise: ROLE=LAYER or "
            "ROLE=CH1,CH2,CH3 (repeatable; roles: colour, diffuse, specular, albedo, normal, "
            "depth, diffuse_var, specular_var), or a .toml file of them.",
        ),
    ] = None,
    normal_space: Annotated[
        str,
        typer.Option(
            help="The normals' frame: auto (known from the renderer, else detected) | camera | world (needs a "
            "camera matrix)."
        ),
    ] = "auto",
    world_to_camera: Annotated[
        Optional[str],
        typer.Option(
            help="The camera for world-space normals: the renderer's world-to-camera matrix, 16 numbers row by "
            "row (docs/usage.md says how to print it in Blender and Mitsuba)."
        ),
    ] = None,
    oidn_blend: Annotated[
        bool,
        typer.Option(
            help="Blend with OIDN's output at the shares fine-tuned weights "
            "ship (train.oidn_blend); --no-oidn-blend: the networks' "
            "output alone."
        ),
    ] = True,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Denoise your own EXR renders (admc's, Blender's, pbrt-v4's, Mitsuba's, OIDN file sets): the final image
    plus the denoised diffuse and specular layers."""
    from admc.pipeline.stages.denoise import DenoiseInputError, check_output_path, load_denoise_input, output_paths
    from admc.pipeline.stages.denoise_formats import NORMAL_SPACES, LayerMap, LayerMapError
    from admc.pipeline.stages.denoise_layers import NormalSpaceError
    from admc.stores.exr import ExrError

    if output is not None and len(inputs) > 1:
        raise typer.BadParameter("--output names one file; give one input, or leave it out")
    if ensemble not in ENSEMBLES:
        raise typer.BadParameter(f"--ensemble must be one of {', '.join(map(str, ENSEMBLES))}, got {ensemble}")
    if engine is not None and engine not in ENGINE_CHOICES:
        raise typer.BadParameter(f"--engine must be one of {', '.join(ENGINE_CHOICES)}, got {engine!r}")
    if normal_space not in NORMAL_SPACES:
        raise typer.BadParameter(f"--normal-space must be one of {', '.join(NORMAL_SPACES)}, got {normal_space!r}")
    mapping = LayerMap.parse(layers, normal_space, world_to_camera)
    cfg, model, written, failed = _load(config, set_), None, [], []
    for path, target in zip(inputs, output_paths(inputs, output)):
        try:
            source = load_denoise_input(path, mapping)
            check_output_path(target, source)
            if model is None:  # after the first input checks out, so a bad one is named without loading torch
                from admc.pipeline.weights import load_model
                from admc.model.inference.options import DenoiserOptions

                model = load_model(
                    cfg,
                    weights,
                    DenoiserOptions(
                        device=device,
                        tile=tile,
                        ensemble=ensemble,
                        dark_pass=dark_pass,
                        engine=engine or cfg.eval.engine,
                        keep_resolved=cfg.eval.keep_resolved,
                    ),
                    oidn_blend=oidn_blend,
                )
                console.print(f"weights: {model.source} ({model.name})", markup=False)
            missing = model.missing_layers(source.layers)
            if missing:
                raise DenoiseInputError(
                    f"{path}: lacks layer(s) {', '.join(missing)}, which the weights "
                    f"{model.source} read (model.noise_input: the variance of each pixel's "
                    "mean, as `admc-pipe render` writes in its multi-layer EXRs); without "
                    "it, use weights without that input (--set model.noise_input=false "
                    "picks the shipped ones)"
                )
            _denoise_one(model, path, source, target)
        except (DenoiseInputError, ExrError, LayerMapError, NormalSpaceError, OSError) as exc:  # this input's fault:
            if len(inputs) == 1 or _input_failure(exc) is None:  # the others still get denoised
                raise
            failed.append((path, _input_failure(exc)))
            continue
        written.append(target)
    if failed:
        raise DenoiseInputError(_batch_summary(failed, written, len(inputs)))


def _denoise_one(model, path: Path, source, target: Path) -> None:
    """Denoise one checked input into `target` and say what was done to it."""
    from admc.pipeline.stages.denoise import write_denoised

    result = model(source.layers)
    write_denoised(target, result, source=source)
    for note in source.notes + result.notes:
        console.print(f"  {note}", markup=False)
    console.print(
        f"{path} -> {target}  ({'+'.join(result.branches)}, {result.seconds:.2f} s on {model.device})", markup=False
    )


def _input_failure(exc: Exception) -> str | None:
    """What went wrong with one input of a batch, or None for a failure that is not the input's (a bug)."""
    return str(exc) if isinstance(exc, AdmcError) else user_os_error(exc)


def _batch_summary(failed: list[tuple[Path, str]], written: list[Path], total: int) -> str:
    """Which inputs of a batch failed and why, and what was written, as one message."""
    lines = [f"{len(failed)} of {total} inputs not denoised:"]
    for path, why in failed:
        lines.append(f"  {why}" if why.startswith(str(path)) else f"  {path}: {why}")
    lines.append(f"written: {', '.join(map(str, written))}" if written else "nothing written")
    return "\n".join(lines)


@app.command("eval")
@_user_errors
def eval_(
    config: ConfigOpt = None,
    set_: SetOpt = None,
    scheduler: SchedulerOpt = None,
    weights: Annotated[
        Optional[list[str]],
        typer.Option(
            help="Weights or checkpoint: PATH or NAME=PATH, repeatable to compare checkpoints or ablations in "
            "one table (default: this config's finetune, else pretrain run, else the shipped weights)."
        ),
    ] = None,
    device: DeviceOpt = "auto",
    no_model: Annotated[
        bool, typer.Option("--no-model", help="Leave this model out (noisy input, OIDN, and OptiX where CUDA runs).")
    ] = False,
) -> None:
    """Table 1 on the test split's full images (noisy input, OIDN, OptiX where CUDA runs, this model), error vs
    time, an HTML page."""
    cfg = _load(config, set_, scheduler)
    if no_model and weights:
        raise typer.BadParameter("--no-model and --weights contradict each other; give one")
    from admc.pipeline.stages.evaluate import learned_denoisers, run_eval

    extra = [] if no_model else learned_denoisers(cfg, weights, device)
    for model in extra:
        console.print(f"weights{'' if model.name == 'admc' else ' ' + model.name}: {model.source}")
    outcome = run_eval(cfg, extra=extra)
    console.print(outcome.result.files["table1_md"].read_text(), markup=False, highlight=False)
    console.print(f"test scenes: {', '.join(outcome.scene_ids)}")
    console.print(f"HTML report: {outcome.report}")
    console.print(f"tables and plots: {outcome.report.parent}")


@app.command()
@_user_errors
def export(
    weights: Annotated[Path, typer.Argument(help="Weights or checkpoint file to export.")],
    out_dir: Annotated[
        Path,
        typer.Option(
            "--output", "-o", help="Folder for {branch}.onnx and admc.json (created; other files in it are kept)."
        ),
    ],
) -> None:
    """Both branches' generators as ONNX graphs (dynamic height and width) and admc.json, what runs around
    them: to run admc in a renderer without Python (docs/engines.md)."""
    from admc.pipeline.stages.export import export_onnx

    for path in export_onnx(weights, out_dir):
        console.print(f"wrote {path}", markup=False)


@app.command()
@_user_errors
def cache(
    config: ConfigOpt = None,
    set_: SetOpt = None,
    clear: Annotated[bool, typer.Option("--clear", help="Remove cached outputs.")] = False,
    stage: Annotated[Optional[str], typer.Option(help="Only this stage: render or tile.")] = None,
) -> None:
    """Show what is cached (per stage: entries and size), or clear it."""
    cfg = _load(config, set_)
    from admc.pipeline.stages.corpus import check_cached_stage, open_cache

    check_cached_stage(stage)
    store = open_cache(cfg)
    if clear:
        removed = store.clear(stage)
        console.print(
            f"removed {removed} cached entr{'y' if removed == 1 else 'ies'} from {store.root}"
            f"{f' (stage {stage})' if stage else ''}"
        )
        return
    entries = [e for e in store.entries() if stage is None or e["stage"] == stage]
    table = Table(title=f"cache at {store.root}")
    for column in ("stage", "entries", "MiB", "newest"):
        table.add_column(column)
    for name in sorted({e["stage"] for e in entries}):
        rows = [e for e in entries if e["stage"] == name]
        table.add_row(
            name, str(len(rows)), f"{sum(e['bytes'] for e in rows) / 2**20:.1f}", max(str(e["created"]) for e in rows)
        )
    console.print(table if entries else f"cache at {store.root} is empty")


@app.command("config")
@_user_errors
def show_config(config: ConfigOpt = None, set_: SetOpt = None) -> None:
    """Print the resolved configuration (defaults, your config file and --set overrides merged)."""
    typer.echo(config_mod.config_toml(_load(config, set_)), nl=False)


def _terminated(signum, frame) -> None:
    """SIGTERM (kill, a batch system's time limit) unwinds like Ctrl-C: a file being written is removed
    rather than left half-written under its temporary name."""
    raise SystemExit(128 + signum)


def main() -> None:
    signal.signal(signal.SIGTERM, _terminated)
    app()
