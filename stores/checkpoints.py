"""Training checkpoints and shippable fp16 weights, written atomically and read with clear errors.

A checkpoint is the whole training state (torch.save of a dict of tensors and plain values); it is
published by rename, so a crash while saving leaves the previous checkpoint intact. Exported
weights hold only the networks, cast to float16 (half the bytes), plus the metadata a user needs
to check compatibility (architecture, transform spec, patch size). Both load with
weights_only=True: no arbitrary code runs when opening a downloaded file.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from admc.common.layout import branch_of
from admc.errors import AdmcError
from admc.stores.atomic import publishing

CHECKPOINT_NAME = "checkpoint.pt"
"""A training run's whole state, in its run folder (workdir/train/<stage>/): what a resume reads."""
WEIGHTS_NAME = "weights-fp16.pt"
"""A training run's shippable fp16 weights, beside its checkpoint: what denoise, eval and fine-tuning read."""

CHECKPOINT_FORMAT = "admc-checkpoint"
WEIGHTS_FORMAT = "admc-weights"
FORMAT_VERSION = 1


class CheckpointError(AdmcError, ValueError):
    """A checkpoint or weights file is missing, unreadable, or not what the caller needs."""


def _save(path: Path, obj: dict) -> None:
    with publishing(Path(path)) as tmp, tmp.open("wb") as stream:  # through Python: a full disk raises OSError
        torch.save(obj, stream)


def _unreadable(head: bytes, exc: Exception) -> str:
    """Why torch could not read a file starting with `head`, for a user, without torch's advice to retry
    with weights_only=False: unpickling a file from elsewhere that way can run arbitrary code."""
    if not head:
        return "the file is empty"
    unsafe = re.search(r"GLOBAL (\S+)", str(exc))
    if unsafe:  # torch's weights-only unpickler refused a Python object: what a malicious file smuggles in
        return (
            f"it holds Python objects ({unsafe.group(1)}) besides tensors and plain values: not a weights file "
            "admc wrote (admc does not unpickle objects)"
        )
    if head.startswith(b"\x80"):  # a bare pickle's protocol opcode
        return "it is a bare Python pickle, not a weights file admc wrote (admc does not unpickle objects)"
    if head.startswith(b"PK"):  # torch's own zip format
        return "it starts like a torch file but is truncated or damaged"
    return "its content is not in torch's save format (text or other data?)"


def _load(path: Path, *formats: str) -> dict:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such file")
    if not path.is_file():
        raise CheckpointError(f"{path}: is a directory, not a checkpoint or weights file")
    try:
        with path.open("rb") as file:
            head = file.read(4)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot be read ({exc.strerror})") from None
    try:
        with warnings.catch_warnings():  # e.g. a pickle protocol note: noise before the real error
            warnings.simplefilter("ignore")
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except MemoryError:
        raise
    except Exception as exc:  # foreign data makes torch raise anything: KeyError: 101 for a text file
        raise CheckpointError(f"{path}: not a readable torch file: {_unreadable(head, exc)}") from None
    if not isinstance(obj, dict) or obj.get("format") not in formats:
        found = obj.get("format") if isinstance(obj, dict) else type(obj).__name__
        raise CheckpointError(f"{path}: not an {' or '.join(formats)} file (format={found!r})")
    if obj.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: {obj['format']} format_version {obj.get('format_version')!r}, this code reads {FORMAT_VERSION}"
        )
    return obj


def load_network(net: torch.nn.Module, state: dict, where: str, architecture: str) -> None:
    """net.load_state_dict(state), after checking that `state` has exactly the net's tensors and shapes;
    a mismatch is one short CheckpointError naming `where` (file, branch, network) and `architecture`."""
    expected = net.state_dict()
    state = state if isinstance(state, dict) else {}
    shape = {k: list(getattr(v, "shape", [])) for k, v in state.items()}
    reshaped = [k for k in expected if k in state and shape[k] != list(expected[k].shape)]
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    problems = []
    if reshaped:
        first = reshaped[0]
        problems.append(
            f"{len(reshaped)} tensor(s) of another shape (first {first}: {shape[first]} in the file, "
            f"{list(expected[first].shape)} in the model)"
        )
    if missing:
        problems.append(f"{len(missing)} missing (first {missing[0]})")
    if unexpected:
        problems.append(f"{len(unexpected)} not in the model (first {unexpected[0]})")
    if problems:
        raise CheckpointError(f"{where} weights do not fit {architecture}: {'; '.join(problems)}")
    for name, tensor in state.items():  # NaN weights would run and write black images without a word
        if torch.is_tensor(tensor) and tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            count = int((~torch.isfinite(tensor)).sum())
            raise CheckpointError(
                f"{where} weights hold {count} non-finite value(s) (NaN or Inf) in tensor {name}: "
                "the file is damaged or comes from a diverged training; use other weights"
            )
    net.load_state_dict(state)


def save_checkpoint(path: str | os.PathLike, state: dict[str, Any]) -> None:
    """Write the training state atomically (temp file, fsync, rename)."""
    _save(Path(path), {**state, "format": CHECKPOINT_FORMAT, "format_version": FORMAT_VERSION})


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The state saved by save_checkpoint, on the CPU; CheckpointError naming the file otherwise."""
    return _load(Path(path), CHECKPOINT_FORMAT)


def _half(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {
        k: v.detach().to("cpu", torch.float16) if v.is_floating_point() else v.detach().cpu()
        for k, v in state_dict.items()
    }


def export_weights(
    path: str | os.PathLike,
    branches: dict[str, dict[str, dict[str, torch.Tensor]]],
    metadata: dict[str, Any],
    oidn_networks: dict[str, dict[str, torch.Tensor]] | None = None,
) -> None:
    """Write {branch: {"generator": state_dict, "critic": state_dict}} as float16, atomically.

    `metadata` (model settings, transform spec, patch size, provenance) is stored alongside and
    returned by load_weights; it must be plain values (dicts, lists, str, numbers, bools).
    `oidn_networks` ({branch: state_dict}: OIDN's networks fine-tuned beside them, train.oidn_minutes) go
    along, float16 too.
    """
    for name, nets in branches.items():
        missing = {"generator", "critic"} - set(nets)
        if missing:
            raise ValueError(f"export_weights {path}: branch {name!r} lacks {sorted(missing)}")
    _save(
        Path(path),
        {
            "format": WEIGHTS_FORMAT,
            "format_version": FORMAT_VERSION,
            "metadata": metadata,
            "branches": {name: {net: _half(sd) for net, sd in nets.items()} for name, nets in branches.items()},
            **({OIDN_NETWORKS: {b: _half(sd) for b, sd in oidn_networks.items()}} if oidn_networks else {}),
        },
    )


def load_weights(path: str | os.PathLike) -> dict[str, Any]:
    """{"branches": {branch: {"generator", "critic"}}, "metadata": {...}}; tensors float16 on the CPU
    (load_state_dict casts them to the model's dtype)."""
    obj = _load(Path(path), WEIGHTS_FORMAT)
    return {"branches": obj["branches"], "metadata": obj["metadata"]}


OIDN_BLEND = "oidn_blend"
"""The weights metadata key of the shares of each branch's output blended with OIDN's (train.oidn_blend)."""


def read_blend(path: str | os.PathLike) -> dict[str, float]:
    """{branch: the share of the network's output kept when blended with OIDN's} a weights file ships, or
    {} (the network's output alone: checkpoints, and weights trained without train.oidn_blend)."""
    return _blend_of(_load(Path(path), CHECKPOINT_FORMAT, WEIGHTS_FORMAT), path)


def _blend_of(obj: dict, path: str | os.PathLike) -> dict[str, float]:
    blend = obj.get("metadata", {}).get(OIDN_BLEND, {}) if obj["format"] == WEIGHTS_FORMAT else {}
    if not (isinstance(blend, dict) and all(isinstance(w, (int, float)) and 0 <= w <= 1 for w in blend.values())):
        raise CheckpointError(f"{path}: its {OIDN_BLEND} metadata {blend!r} is not shares in [0, 1] per branch")
    return {str(b): float(w) for b, w in blend.items()}


OIDN_NETWORKS = "oidn_networks"
"""The weights file's key of OIDN's networks fine-tuned with the model (train.oidn_minutes): the blend's partner."""


def read_oidn_networks(path: str | os.PathLike) -> dict[str, dict[str, torch.Tensor]]:
    """{branch: OIDN network state dict} a weights file ships, or a checkpoint's partner holds (its best
    validated step's); {} where OIDN was not fine-tuned (the blend then runs the OIDN library)."""
    return _oidn_networks_of(_load(Path(path), CHECKPOINT_FORMAT, WEIGHTS_FORMAT), path)


def _oidn_networks_of(obj: dict, path: str | os.PathLike) -> dict[str, dict[str, torch.Tensor]]:
    if obj["format"] == WEIGHTS_FORMAT:
        nets = obj.get(OIDN_NETWORKS, {})
    else:
        partner = obj.get("partner") or {}
        nets = {}
        for name, state in partner.get("nets", {}).items():  # a branch's candidates: "diffuse", "diffuse raw"
            branch = branch_of(name)
            nets[branch] = partner.get("best", {}).get(branch, state)
    if not (isinstance(nets, dict) and all(isinstance(state, dict) for state in nets.values())):
        raise CheckpointError(f"{path}: its {OIDN_NETWORKS} entry is not a state dict per branch")
    return nets


def read_networks(path: str | os.PathLike) -> tuple[dict, dict, dict]:
    """(branch -> {"generator", "critic"} state dicts, model settings, transform spec) from either a
    training checkpoint or exported fp16 weights: whatever a user points fine-tuning or denoising at. A
    checkpoint of a run with a moving average (train.ema) gives that average: what the run ships."""
    return _networks_of(_load(Path(path), CHECKPOINT_FORMAT, WEIGHTS_FORMAT), path)


def _networks_of(obj: dict, path: str | os.PathLike) -> tuple[dict, dict, dict]:
    try:
        if obj["format"] == WEIGHTS_FORMAT:
            return obj["branches"], obj["metadata"]["model"], obj["metadata"]["transform"]
        nets = {
            b: {"generator": s.get("average", s["generator"]), "critic": s["critic"]}
            for b, s in obj["branches"].items()
        }
        return nets, obj["model"], obj["transform"]
    except (KeyError, TypeError, AttributeError) as exc:
        raise CheckpointError(f"{path}: a malformed {obj['format']} file (no {exc} entry where expected)") from None


def read_denoiser(path: str | os.PathLike, blend: bool) -> tuple[tuple[dict, dict, dict], dict | None, dict | None]:
    """(read_networks, read_blend, read_oidn_networks) of one file, read once: what a denoiser is built from.
    Without `blend` the last two are None, unread and unchecked, as for a denoiser that runs no OIDN blend."""
    obj = _load(Path(path), CHECKPOINT_FORMAT, WEIGHTS_FORMAT)
    if not blend:
        return _networks_of(obj, path), None, None
    return _networks_of(obj, path), _blend_of(obj, path), _oidn_networks_of(obj, path)
