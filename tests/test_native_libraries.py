"""Every native library admc loads, in one process, each run on a small input: what `eval` does, and what
the one-process test suite does.

The suite used to die here with a SIGSEGV that not even faulthandler reported (docs/design-decisions.md):
each openvino.Core made a CPU plugin that put an alternate signal stack of its own on the main thread and
unmapped it when released; two released first-in first-out left the thread's alternate stack pointing at
unmapped memory, and the next signal with a Python handler (torch's DataLoader installs one for SIGCHLD)
killed the process. The check runs in a fresh interpreter, so that a crash fails this test instead of
ending the session.
"""

import subprocess
import sys

SCRIPT = r"""
import ctypes, faulthandler, os, signal, subprocess, sys, traceback

import numpy as np
import torch


def main():
    faulthandler.enable()  # what pytest does: Python's own alternate signal stack on the main thread
    handled = []
    signal.signal(signal.SIGCHLD, lambda *_: handled.append("SIGCHLD"))  # as torch's DataLoader does with workers
    signal.signal(signal.SIGUSR1, lambda *_: handled.append("SIGUSR1"))
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    image = rng.uniform(0.0, 1.0, (16, 16, 3)).astype(np.float32)

    # OIDN (pyoidn) and HDR-FLIP (flip-evaluator, OpenMP), as evaluation calls them
    from admc.common.metrics import hdr_flip
    from admc.common.oidn import denoise

    denoised = denoise(image, image, image * 2 - 1, quality="high")
    assert denoised.shape == image.shape and np.isfinite(denoised).all()
    assert 0.0 < hdr_flip(image * 0.9, image) < 1.0

    # Mitsuba (Dr.Jit's LLVM back end): a tiny render
    import mitsuba as mi

    from admc.pipeline.render.variants import use_variant

    use_variant("auto")
    scene = mi.load_dict(mi.cornell_box() | {"sensor": {**mi.cornell_box()["sensor"],
                                                        "film": {"type": "hdrfilm", "width": 8, "height": 8}}})
    assert np.isfinite(np.array(mi.render(scene, spp=2))).all()

    # torch, OpenVINO and ONNX Runtime on one generator; two engines of each, let go in the order they were made
    from admc.model.inference.engines import onnx_generators
    from admc.model.nets.generator import Generator
    from admc.model.nets.settings import ModelSettings

    tiny = ModelSettings(channels=4, blocks=1, cond_channels=4, encoder_channels=4)
    torch.manual_seed(0)
    nets = {branch: Generator(tiny).eval() for branch in ("diffuse", "specular")}
    noisy, features = torch.rand(1, 3, 16, 16), torch.rand(1, 7, 16, 16)
    with torch.no_grad():
        expected = {branch: net(noisy, features) for branch, net in nets.items()}
    for engine in ("openvino", "onnxruntime"):
        generators = onnx_generators(nets, engine, torch.float32)
        for branch, generator in generators.items():  # OpenVINO makes its CPU plugin at the first compile
            torch.testing.assert_close(generator(noisy, features), expected[branch], atol=1e-4, rtol=1e-4)
        del generator, generators  # diffuse's engine first, then specular's

    class Stack(ctypes.Structure):
        _fields_ = [("sp", ctypes.c_void_p), ("flags", ctypes.c_int), ("size", ctypes.c_size_t)]

    stack = Stack()
    assert ctypes.CDLL(None).sigaltstack(None, ctypes.byref(stack)) == 0
    maps = [line.split()[:2] for line in open("/proc/self/maps")]
    mapped = any(int(span.split("-")[0], 16) <= stack.sp and stack.sp + stack.size <= int(span.split("-")[1], 16)
                 and perms.startswith("rw") for span, perms in maps)
    assert stack.sp is None or mapped, f"the main thread's alternate signal stack {stack.sp:#x} is not mapped memory"

    subprocess.run(["true"], check=True)  # SIGCHLD, handled on the alternate stack
    os.kill(os.getpid(), signal.SIGUSR1)
    assert "SIGCHLD" in handled and "SIGUSR1" in handled, handled


try:
    main()
except BaseException:  # fail at once: a process left in this state may hang on its way out
    traceback.print_exc()
    sys.stderr.flush()
    os._exit(1)
print("survived", flush=True)
"""


def test_oidn_openvino_onnxruntime_flip_mitsuba_and_torch_in_one_process():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip().endswith("survived"), (
        f"exit {out.returncode}\n{out.stdout[-2000:]}\n{out.stderr[-4000:]}"
    )


def test_every_openvino_generator_shares_one_core():
    """One Core, one CPU plugin, kept to the end of the process: no plugin is let go while the process runs."""
    import torch

    from admc.model.inference.engines import onnx_generators, openvino_core
    from admc.model.nets.generator import Generator
    from admc.model.nets.settings import ModelSettings

    net = Generator(ModelSettings(channels=4, blocks=1, cond_channels=4, encoder_channels=4)).eval()
    first = onnx_generators({"diffuse": net}, "openvino", torch.float32)["diffuse"]
    second = onnx_generators({"diffuse": net}, "openvino", torch.float32)["diffuse"]
    assert first._core is second._core is openvino_core()
