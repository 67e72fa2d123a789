"""OIDN's networks fine-tuned on a domain (train.oidn_minutes), run on whole images: the blend's partner.

Where a weights file ships them, the blend (denoiser._blend_with_oidn) takes their output per branch in place
of OIDN's shipped networks'. They run in the OIDN library itself, which takes other weights for its network as a
TZA archive: the same code and speed as OIDN, and the archive is what `admc-pipe export` hands a renderer. With
an ensemble they run over the same symmetries as admc's networks (symmetry.py; normals follow the geometry).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from admc.common import oidn
from admc.stores.oidn_archives import read_archive, write_archive

from ..nets.oidn_unet import INPUT_CHANNELS, network_for, uses_clean_guides
from ..symmetry import ENSEMBLE_CODES, apply, undo


def partner_archives(states: dict[str, dict], where: str) -> dict[str, bytes]:
    """{branch: TZA archive} of the state dicts a weights file ships, checked as every network is."""
    from admc.stores.checkpoints import load_network

    archives = {}
    for branch, state in states.items():
        net = network_for(state, INPUT_CHANNELS[branch])
        load_network(net, {k: v.float() for k, v in state.items()}, f"{where}: {branch} OIDN network", "OIDN's U-Net")
        archives[branch] = write_archive({k: v.numpy() for k, v in net.state_dict().items()})
    return archives


@functools.lru_cache(maxsize=8)
def takes_clean_guides(archive: bytes) -> bool:
    """Whether a partner archive holds OIDN's large network, which runs on prefiltered guides: parsed once per
    archive (7 ms for the large one), not at every image and ensemble pass that asks."""
    return uses_clean_guides(read_archive(archive))


def partner_bases(
    archives: dict[str, bytes], clean: dict[str, np.ndarray], branches: tuple[str, ...], ensemble: int = 1
) -> dict[str, np.ndarray]:
    """{branch: (H, W, 3) float32 linear output} for sanitised layers, as oidn_base.oidn_bases gives OIDN's
    own (negatives and non-finite values set to 0). A large network gets its guides prefiltered by OIDN."""
    out = {}
    for branch in branches:
        guides = branch == "diffuse"
        prefiltered = guides and takes_clean_guides(archives[branch])
        total = np.zeros_like(clean[branch], dtype=np.float32)
        for code in ENSEMBLE_CODES[ensemble]:
            color = _image(apply(_tensor(clean[branch]), code))
            albedo = _image(apply(_tensor(clean["albedo"]), code)) if guides else None
            normal = _image(apply((_tensor(clean["normal"]) + 1) * 0.5, code, normals=True) * 2 - 1) if guides else None
            if prefiltered:
                albedo, normal = oidn.prefilter("albedo", albedo), oidn.prefilter("normal", normal)
            denoised = oidn.denoise_with_weights(color, albedo, normal, weights=archives[branch], clean_aux=prefiltered)
            total += _image(undo(_tensor(denoised), code))
        total /= len(ENSEMBLE_CODES[ensemble])
        out[branch] = np.clip(np.nan_to_num(total, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
    return out


def _tensor(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32).transpose(2, 0, 1))


def _image(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.numpy().transpose(1, 2, 0))
