"""What a user already has is never lost, and a file system that refuses a write (a read-only folder, a full
disk) ends in one message naming the file, exit 2, with every other input of a batch still done.

A read-only folder: chmod for a normal user; root ignores permissions, so as root it is a read-only bind
mount (skipped where root may not mount). A full disk: a file-size limit (RLIMIT_FSIZE) on the command,
which makes the kernel refuse the write (EFBIG) on any file system and for any user, as ENOSPC would.
"""

import contextlib
import os
import pickle
import resource
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from test_cli import ADMC, _oidn_style_input, run
from test_train_stage import flags, settings
from test_user_errors_cli import SHIPPED, refused

from admc.pipeline.config import ConfigError, load_config
from admc.pipeline.tiler.report import contact_sheet_path
from admc.stores import patches
from admc.stores.checkpoints import export_weights, load_weights
from admc.stores.exr import read_exr, write_exr

WRITE_REFUSED = ("Read-only file system", "Permission denied")


@contextlib.contextmanager
def read_only(folder: Path):
    """`folder` refuses writes while inside the block."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(0o755)
        return
    mounted = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"as root a read-only folder needs a bind mount, refused here: {mounted.stderr.decode()}")
    try:
        subprocess.run(["mount", "-o", "remount,ro,bind", str(folder)], check=True, capture_output=True)
        yield
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def with_file_size_limit(limit: int, *args: str) -> subprocess.CompletedProcess:
    """Run admc-pipe with every file it writes limited to `limit` bytes: writes beyond fail as on a full disk."""

    def limit_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return subprocess.run([ADMC, *args], capture_output=True, text=True, timeout=600, preexec_fn=limit_files)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A workdir with a finished tiny pretraining (checkpoint and weights)."""
    workdir = tmp_path_factory.mktemp("finished")
    out = subprocess.run(
        [ADMC, "train", *flags(settings(workdir, steps=2))], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    return workdir


# ---- nothing a user has is lost -------------------------------------------------------------------------


def test_train_without_its_checkpoint_keeps_the_finished_weights(finished_run):
    run_dir = finished_run / "train" / "pretrain"
    weights = run_dir / "weights-fp16.pt"
    (run_dir / "checkpoint.pt").rename(run_dir / "moved-checkpoint.pt")
    before = weights.read_bytes()
    try:
        out = subprocess.run(
            [ADMC, "train", *flags(settings(finished_run, steps=2))], capture_output=True, text=True, timeout=600
        )
        refused(out, f"{weights}: holds the finished weights of an earlier run", "--restart")
        assert weights.read_bytes() == before
    finally:
        (run_dir / "moved-checkpoint.pt").rename(run_dir / "checkpoint.pt")


def test_a_store_is_never_made_in_a_folder_of_other_files(tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("my notes")
    out = run("dataset", *flags(settings(tmp_path / "w") + [f"tile.store='{folder}'"]))
    refused(out, f"{folder}: exists and is not a patch store", "tile.store")
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]
    assert not (tmp_path / "w" / "cache").exists(), "refused before anything is rendered"


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_weights_holding_non_finite_values_are_refused(tmp_path, value):
    shipped = load_weights(SHIPPED)
    generator = shipped["branches"]["diffuse"]["generator"]
    name = next(k for k, v in generator.items() if v.is_floating_point())
    generator[name] = torch.full_like(generator[name], value)
    bad = tmp_path / "bad.pt"
    export_weights(bad, shipped["branches"], shipped["metadata"])
    frame = _oidn_style_input(tmp_path)
    refused(
        run("denoise", str(frame), "--weights", str(bad)),
        f"{bad}: diffuse generator weights hold ",
        f"non-finite value(s) (NaN or Inf) in tensor {name}",
    )
    assert not (tmp_path / "frame.denoised.exr").exists()


def test_two_inputs_of_a_batch_never_write_the_same_output(tmp_path):
    colour = _oidn_style_input(tmp_path)  # frame.hdr.exr (+ .alb, .nrm)
    plain = tmp_path / "frame.exr"
    shutil.copy(colour, plain)
    out = run("denoise", str(plain), str(colour), "--weights", str(SHIPPED))
    refused(out, f"{plain} and {colour} would both be written to {tmp_path / 'frame.denoised.exr'}")
    assert not (tmp_path / "frame.denoised.exr").exists()
    earlier = tmp_path / "frame.denoised.exr"
    shutil.copy(colour, earlier)  # an input whose name is another input's output
    refused(
        run("denoise", str(colour), str(earlier), "--weights", str(SHIPPED)),
        f"{earlier}: the output for {colour} is also an input of this batch",
    )
    assert earlier.read_bytes() == colour.read_bytes()


def test_two_stores_in_one_folder_get_their_own_contact_sheets_in_the_workdir(tmp_path):
    workdir = tmp_path / "w"
    sheets = {contact_sheet_path(workdir, tmp_path / "stores" / name) for name in ("a.zarr", "b.zarr")}
    assert len(sheets) == 2 and all(workdir in sheet.parents for sheet in sheets)


# ---- a file system that refuses a write --------------------------------------------------------------------


def test_denoise_beside_a_read_only_input_and_a_batch_that_goes_on(tmp_path):
    good = [_oidn_style_input(_folder(tmp_path / name)) for name in ("a", "c")]
    locked = _oidn_style_input(_folder(tmp_path / "b"))
    with read_only(locked.parent):
        out = run("denoise", str(locked), "--weights", str(SHIPPED))
        refused(out, f"{locked.with_name('frame.denoised.exr')}: cannot be written (")
        assert any(reason in out.stderr for reason in WRITE_REFUSED), out.stderr
        out = run("denoise", str(good[0]), str(locked), str(good[1]), "--weights", str(SHIPPED))
    written = [path.with_name("frame.denoised.exr") for path in good]
    refused(
        out,
        "1 of 3 inputs not denoised",
        f"{locked.with_name('frame.denoised.exr')}: cannot be written (",
        f"written: {written[0]}, {written[1]}",
    )
    assert all(path.is_file() for path in written)
    assert sorted(p.name for p in locked.parent.iterdir()) == ["frame.alb.exr", "frame.hdr.exr", "frame.nrm.exr"]


def _folder(path: Path) -> Path:
    path.mkdir(parents=True)
    return path


def test_denoise_onto_a_full_disk(tmp_path):
    frame = _oidn_style_input(tmp_path)
    # torch runs the networks in process: the ONNX engines write their graphs first, and those would fail
    out = with_file_size_limit(100, "denoise", str(frame), "--weights", str(SHIPPED), "--engine", "torch")
    refused(out, f"{tmp_path / 'frame.denoised.exr'}: cannot be written (File too large)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.alb.exr", "frame.hdr.exr", "frame.nrm.exr"]


def test_a_training_checkpoint_onto_a_full_disk(finished_run):
    checkpoint = finished_run / "train" / "pretrain" / "checkpoint.pt"
    before = checkpoint.read_bytes()
    out = with_file_size_limit(checkpoint.stat().st_size // 2, "train", *flags(settings(finished_run, steps=4)))
    refused(out, f"{checkpoint}: cannot be written (File too large)")
    assert checkpoint.read_bytes() == before, "the last checkpoint stays whole"
    assert not list(checkpoint.parent.glob(".*tmp*"))


def test_a_read_only_or_file_valued_workdir(tmp_path):
    workdir = _folder(tmp_path / "w")
    tiny = [
        "run.scheduler=sync",
        "corpus.n_scenes=1",
        "render.resolution=[32, 32]",
        "render.spp=[2]",
        "render.reference_spp=4",
    ]
    with read_only(workdir):
        out = run("render", *flags([f"run.workdir='{workdir}'", *tiny]))
    refused(out, str(workdir))
    assert any(reason in out.stderr for reason in WRITE_REFUSED), out.stderr
    file = tmp_path / "file"
    file.write_text("not a folder")
    refused(
        run("render", *flags([f"run.workdir='{file}'", *tiny])),
        f"config key 'run.workdir': {file} is a file; it must name a folder",
    )


def test_an_invalid_zarr_json_at_the_store_root(tmp_path):
    store = _folder(tmp_path / "store.zarr")
    (store / "zarr.json").write_text('{"zarr_format": 3, "node_ty')
    out = run("dataset", "--summary", *flags([f"run.workdir='{tmp_path}'", f"tile.store='{store}'"]))
    refused(out, f"{store / 'zarr.json'}: the store's root metadata cannot be read", "move the store away")
    assert not patches.exists(tmp_path / "nothing")


# ---- values and names that lead nowhere ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "override, message",
    [
        ("render.resolution=[200000, 200000]", "config key 'render.resolution': width and height must be in 1..16384"),
        ("tile.split=[inf, 0, 0]", "config key 'tile.split[0]': must be a finite number, got inf"),
        (
            "tile.split=[0.5, 0.5, 0.5]",
            "config key 'tile.split': the train, val and test fractions must be >= 0 and "
            "sum to 1, got [0.5, 0.5, 0.5] (sum 1.5)",
        ),
    ],
)
def test_config_values_that_would_fail_later_are_named_now(override, message):
    with pytest.raises(ConfigError) as caught:
        load_config(None, [override])
    assert message in str(caught.value)
    refused(run("config", "--set", override), message)


def test_cache_clear_of_a_stage_it_does_not_know(tmp_path):
    refused(
        run("cache", "--clear", "--stage", "renders", "--set", f"run.workdir='{tmp_path}'"),
        "--stage 'renders': not a cached stage; the stages are render, tile",
    )


@pytest.mark.parametrize("spec", ["=", "name=", "=path.pt", ""])
def test_eval_weights_without_a_name_or_a_file(tmp_path, spec):
    refused(run("eval", "--weights", spec, "--set", f"run.workdir='{tmp_path}'"), f"--weights {spec!r}: ")


class _Payload:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_a_malicious_pickle_is_called_what_it_is(tmp_path):
    frame = _oidn_style_input(tmp_path)
    zipped = tmp_path / "evil.pt"
    torch.save({"format": "admc-weights", "payload": _Payload()}, zipped)
    bare = tmp_path / "evil.pkl"
    bare.write_bytes(pickle.dumps(_Payload()))
    for path in (zipped, bare):
        out = run("denoise", str(frame), "--weights", str(path))
        refused(out, f"{path}: not a readable torch file: ", "not a weights file admc wrote")
        assert "pwned" not in out.stdout + out.stderr and "truncated" not in out.stderr


def test_a_damaged_cached_render_is_rendered_again(tmp_path):
    items = [
        f"run.workdir='{tmp_path}'",
        "run.scheduler=sync",
        "corpus.n_scenes=1",
        "render.resolution=[32, 32]",
        "render.spp=[2]",
        "render.reference_spp=4",
        "tile.patch_size=32",
        "tile.crops_per_scene=1",
        "tile.split=[1.0, 0.0, 0.0]",
    ]
    out = run("render", *flags(items))
    assert out.returncode == 0, out.stderr
    first, second = sorted((tmp_path / "cache" / "render").glob("*/render.json"))
    first.unlink()
    (exr,) = second.parent.glob("*.exr")
    exr.write_bytes(exr.read_bytes()[: exr.stat().st_size // 2])
    out = run("dataset", *flags(items))
    assert out.returncode == 0, out.stderr
    assert "3 tasks run, 0 cached" in out.stdout, "both damaged renders again, and the tile"
    assert first.is_file() and exr.stat().st_size > 0
    out = run("dataset", *flags(items))
    assert out.returncode == 0 and "0 tasks run, 3 cached" in out.stdout, out.stdout


def test_a_denoise_batch_killed_while_writing_leaves_no_partial_file(tmp_path):
    """SIGTERM while an output is being written (its temporary file seen): the outputs already written stay
    whole and readable, and nothing half-written is left, not even under the temporary name."""
    rng = np.random.default_rng(0)
    frames = []
    for i in range(3):
        for role, lo in (("hdr", 0.0), ("alb", 0.0), ("nrm", 0.0)):  # normals facing the camera
            write_exr(tmp_path / f"f{i}.{role}.exr", {"": rng.uniform(lo, 1, (512, 512, 3)).astype(np.float32)})
        frames.append(tmp_path / f"f{i}.hdr.exr")
    process = subprocess.Popen(
        [ADMC, "denoise", *map(str, frames), "--weights", str(SHIPPED)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    caught = False
    while process.poll() is None and not caught:
        caught = any(name.endswith(".tmp.exr") for name in os.listdir(tmp_path))
    if caught:
        process.send_signal(signal.SIGTERM)
    stderr = process.communicate(timeout=300)[1]
    if not caught:
        pytest.skip("every output was written between two looks at the folder: no write was interrupted")
    assert process.returncode == 128 + signal.SIGTERM and "Traceback" not in stderr, stderr
    assert not [name for name in os.listdir(tmp_path) if "tmp" in name]
    for output in tmp_path.glob("*.denoised.exr"):
        assert read_exr(output)[""].shape == (512, 512, 3)
