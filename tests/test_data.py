"""Training data: symmetry augmentation (normals transformed with the image), the seeded resumable
batch stream, and DataLoader batches from a real patch store with and without workers."""

import signal
import sys
import threading
import time
from multiprocessing import resource_sharer

import numpy as np
import pytest
import torch

from conftest import build_tiny_store
from admc.model.symmetry import N_SYMMETRIES, apply
from admc.model.training.data import (
    BatchStream,
    PatchDataset,
    load_rows,
    loader_worker_init,
    quiet_closed_pipes,
    spread_rows,
    train_loader,
)
from admc.stores.patches import PatchReader, fingerprint as store_fingerprint


@pytest.fixture(scope="module")
def store(tmp_path_factory, variant):
    tmp = tmp_path_factory.mktemp("data_store")
    return build_tiny_store(tmp, size=32, patch=32)


def sphere_features(height: int, width: int, cy: float, cx: float, radius: float) -> np.ndarray:
    """(7, H, W) features of a sphere seen head-on: encoded view-space normal, depth ramp, albedo ramp.

    Pixel (row r, column c) lies at view-space x = (c - cx) / radius, y = -(r - cy) / radius (rows run
    down, y runs up); on the sphere n = (x, y, sqrt(1 - x^2 - y^2)); outside it n = (0, 0, 1).
    """
    r, c = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = (c - cx) / radius, -(r - cy) / radius
    inside = x**2 + y**2 < 1
    z = np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))
    n = np.where(inside, np.stack([x, y, z]), np.array([0.0, 0.0, 1.0])[:, None, None])
    depth = np.where(inside, 1 - z / 2, 1.0)[None]
    albedo = np.stack([r / height, c / width, np.full_like(r, 0.5)])
    return np.concatenate([(n + 1) / 2, depth, albedo]).astype(np.float32)


def moved_pixel(code: int, height: int, width: int, r: float, c: float) -> tuple[float, float, int, int]:
    """Where a point at (r, c) lands under augmentation `code`, and the output size."""
    if code & 1:
        r, c, height, width = c, r, width, height
    if code & 2:
        r = height - 1 - r
    if code & 4:
        c = width - 1 - c
    return r, c, height, width


def augment(array: np.ndarray, code: int, normals: bool = False) -> np.ndarray:
    """model.symmetry on a (C, H, W) array, as the dataset applies it to each item."""
    return apply(torch.from_numpy(array), code, normals).numpy()


@pytest.mark.parametrize("code", range(N_SYMMETRIES))
def test_augmented_sphere_normals_equal_the_normals_of_the_moved_sphere(code):
    """An off-centre sphere flipped/transposed must be exactly the sphere rendered at the moved centre."""
    height, width, cy, cx, radius = 12, 16, 4.0, 10.0, 5.5
    features = sphere_features(height, width, cy, cx, radius)
    new_cy, new_cx, new_h, new_w = moved_pixel(code, height, width, cy, cx)
    expected = sphere_features(new_h, new_w, new_cy, new_cx, radius)
    got = augment(features, code, normals=True)
    assert got.shape == expected.shape
    np.testing.assert_allclose(got[:4], expected[:4], atol=1e-6)  # normal and depth
    assert np.abs(features[:2] - 0.5).max() > 0.4  # the normals really vary: the test can fail


def test_normal_rules_as_stated():
    v = np.random.default_rng(0).random((7, 5, 5)).astype(np.float32)
    np.testing.assert_allclose(augment(v, 4, normals=True)[0], 1 - v[0, :, ::-1])  # columns: nx -> -nx
    np.testing.assert_allclose(augment(v, 4, normals=True)[1], v[1, :, ::-1])
    np.testing.assert_allclose(augment(v, 2, normals=True)[1], 1 - v[1, ::-1, :])  # rows: ny -> -ny
    t = augment(v, 1, normals=True)  # transpose
    np.testing.assert_allclose(t[0], 1 - v[1].T)
    np.testing.assert_allclose(t[1], 1 - v[0].T)
    np.testing.assert_allclose(t[2:], v[2:].transpose(0, 2, 1))


@pytest.mark.parametrize("code", range(N_SYMMETRIES))
def test_every_channel_moves_with_the_same_geometry(code):
    image = np.arange(3 * 4 * 6, dtype=np.float32).reshape(3, 4, 6)
    out = augment(image, code)
    for r in range(4):
        for c in range(6):
            nr, nc, _, _ = moved_pixel(code, 4, 6, r, c)
            np.testing.assert_array_equal(out[:, int(nr), int(nc)], image[:, r, c])


def test_augment_leaves_its_input_alone_and_rejects_bad_codes():
    image = np.random.default_rng(1).random((7, 4, 4)).astype(np.float32)
    before = image.copy()
    augment(image, 7, normals=True)
    np.testing.assert_array_equal(image, before)
    with pytest.raises(ValueError, match="code"):
        augment(image, 8)


def test_batch_stream_is_seeded_covers_each_epoch_and_resumes_mid_stream():
    def take(stream, n):
        it = iter(stream)
        return [next(it) for _ in range(n)]

    full = take(BatchStream(10, 3, seed=5), 12)
    assert full == take(BatchStream(10, 3, seed=5), 12)
    assert full != take(BatchStream(10, 3, seed=6), 12)
    assert take(BatchStream(10, 3, seed=5, start_batch=7), 5) == full[7:]
    flat = [row for batch in full for row, _ in batch]
    assert sorted(flat[:10]) == list(range(10)) and sorted(flat[10:20]) == list(range(10))
    assert flat[:10] != flat[10:20]  # a new permutation each epoch
    codes = {code for batch in full for _, code in batch}
    assert codes <= set(range(N_SYMMETRIES)) and len(codes) > 4


def test_rank_shards_together_are_the_single_stream_and_resume_alike():
    def take(stream, n):
        it = iter(stream)
        return [next(it) for _ in range(n)]

    full = take(BatchStream(10, 4, seed=5), 8)
    shards = [take(BatchStream(10, 4, seed=5, shard=(rank, 2)), 8) for rank in range(2)]
    assert [a + b for a, b in zip(*shards)] == full  # each rank its half of every global batch, in order
    for rank in range(2):
        assert take(BatchStream(10, 4, seed=5, start_batch=5, shard=(rank, 2)), 3) == shards[rank][5:]
    with pytest.raises(ValueError, match="no shard"):
        BatchStream(10, 3, seed=5, shard=(0, 2))


def test_dataset_items_are_augmented_store_rows(store):
    reader = PatchReader(store, "train")
    dataset = PatchDataset(reader)
    raw = reader[2]
    item = dataset[(2, 5)]
    np.testing.assert_array_equal(item["noisy"].numpy(), augment(raw["noisy"], 5))
    np.testing.assert_array_equal(item["reference"].numpy(), augment(raw["reference"], 5))
    np.testing.assert_array_equal(item["features"].numpy(), augment(raw["features"], 5, normals=True))
    assert item["noisy"].dtype == torch.float32 and item["noisy"].shape == (3, 32, 32)


def test_loader_batches_do_not_depend_on_workers(store):
    reader = PatchReader(store, "train")

    def batches(workers, start):
        it = iter(train_loader(reader, batch_size=4, seed=3, start_batch=start, num_workers=workers))
        return [next(it) for _ in range(3)]

    torch.manual_seed(0)
    serial = batches(0, 0)
    assert torch.equal(torch.get_rng_state(), torch.manual_seed(0).get_state())  # global RNG untouched
    parallel = batches(2, 0)
    resumed = batches(0, 1)
    for a, b in zip(serial, parallel):
        for key in ("noisy", "features", "reference"):
            assert torch.equal(a[key], b[key])
    assert torch.equal(serial[1]["noisy"], resumed[0]["noisy"])
    assert serial[0]["noisy"].shape == (4, 3, 32, 32)
    assert all(torch.isfinite(b[k]).all() for b in serial for k in b)


def test_validation_rows_and_fingerprint(store):
    val = PatchReader(store, "val")  # whole 32x32 frames: one crop per val scene and spp
    assert len(val) >= 2
    rows = load_rows(val, 2)
    assert rows["features"].shape == (2, 7, 32, 32)
    assert load_rows(val, 100)["features"].shape == (len(val), 7, 32, 32)  # at most every row
    reader = PatchReader(store, "train")
    scenes = {reader.locate(i)[0] for i in range(len(reader))}
    assert len(scenes) >= 2  # the test can fail: the first rows would all be one scene's
    picked = spread_rows(len(reader), len(scenes))
    assert {reader.locate(i)[0] for i in picked} == scenes
    np.testing.assert_array_equal(load_rows(reader, len(scenes))["noisy"][-1], reader[len(reader) - 1]["noisy"])
    with pytest.raises(ValueError, match="split 'test' has no diffuse patches"):
        load_rows(PatchReader(store, "test"), 5)
    assert store_fingerprint(store) == store_fingerprint(store)
    assert len(store_fingerprint(store)) == 64


def test_spread_rows_are_evenly_spaced_and_never_repeat():
    assert spread_rows(10, 4) == [0, 3, 6, 9]
    assert spread_rows(3, 5) == [0, 1, 2]
    assert spread_rows(7, 1) == [0]
    assert spread_rows(0, 5) == []
    picked = spread_rows(1000, 64)
    assert len(set(picked)) == 64 and picked[-1] == 999


def test_a_loader_worker_does_not_print_a_closed_pipe_but_prints_other_errors(monkeypatch):
    # Ctrl-C during train: the main process stops reading while a worker's resource_sharer thread still
    # serves a batch's file descriptor; that thread hands its BrokenPipeError to sys.excepthook, whose
    # traceback must not print under the CLI's one-line message (test_user_errors_cli's Ctrl-C test met
    # it now and then). The real resource_sharer thread, serving a request whose asker hung up.
    printed = []
    monkeypatch.setattr(sys, "excepthook", lambda exc_type, exc, tb: printed.append(exc_type))
    quiet_closed_pipes()
    handled = threading.Event()

    def serve(error):
        asked = threading.Event()

        def send(conn, _pid):
            asked.wait(10)
            try:
                if error is BrokenPipeError:
                    conn.send_bytes(b"x" * (1 << 22))  # the asker closed its end
                raise error("a worker's own bug")
            finally:
                handled.set()

        handled.clear()
        conn = resource_sharer._resource_sharer.get_connection(
            resource_sharer._resource_sharer.register(send, lambda: None)
        )
        conn.close()
        asked.set()
        assert handled.wait(10)
        time.sleep(0.2)  # the hook runs after send returns

    serve(BrokenPipeError)
    assert printed == []
    serve(ValueError)
    assert printed == [ValueError]


def _sigint_handler(_index):
    return int(signal.getsignal(signal.SIGINT) is signal.SIG_IGN)


def test_loader_workers_leave_ctrl_c_to_the_main_process():
    before = signal.getsignal(signal.SIGINT)
    loader = torch.utils.data.DataLoader(
        [0, 1], batch_size=None, num_workers=1, worker_init_fn=loader_worker_init, collate_fn=_sigint_handler
    )
    assert list(loader) == [1, 1]
    assert signal.getsignal(signal.SIGINT) is before
