"""Intel Open Image Denoise's U-Net in torch, started from the weights OIDN itself runs: a denoiser that is
OIDN's to the last digit before fine-tuning and can be fine-tuned on a user's domain after.

The network is OIDN's `UNet` (RenderKit/oidn `training/model.py`, Apache-2.0): five levels, 3x3 convs, max
pooling, nearest upsampling, skips by concatenation. Its input is OIDN's HDR path: the colour times an
autoexposure, through the PU transfer function normalised at 65504; albedo in [0, 1]; the normal mapped from
[-1, 1] to [0, 1]. Two of OIDN's networks are used, as admc runs OIDN per branch (model/inference/oidn_base.py):
"diffuse" (colour, albedo, normal: `rt_hdr_alb_nrm`) and "specular" (colour alone: `rt_hdr`).

The diffuse branch can instead start from OIDN's final-frame route (train.oidn_network = "large"): its `large`
U-Net for clean guides (`rt_hdr_calb_cnrm_large`, 4.2x the parameters, 2.5x the arithmetic a pixel) on albedo
and normal that OIDN's own large networks have denoised first (`clean_guides`): what OIDN documents for final
frames and Blender runs by default (prefilter "Accurate"). OIDN has no large colour-only network.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from admc.stores.oidn_archives import ArchiveError, library_archives

INPUT_CHANNELS = {"diffuse": 9, "specular": 3}
ALIGNMENT = 16  # four 2x2 poolings
MATCH_TOLERANCE = 0.03  # mean relative difference from OIDN's own output that identifies its weights (oidn_unet)
HDR_MAX = 65504.0

# OIDN's fit of the PU2 curve (Aydin et al. 2008), normalised at 100 cd/m^2: training/color.py
_PU = dict(
    a=1.41283765e03,
    b=1.64593172e00,
    c=4.31384981e-01,
    d=-2.94139609e-03,
    e=1.92653254e-01,
    f=6.26026094e-03,
    g=9.98620152e-01,
    y0=1.57945760e-06,
    y1=3.22087631e-02,
    x0=2.23151711e-03,
    x1=3.70974749e-01,
)


def _pu(y: Tensor) -> Tensor:
    p = _PU
    return torch.where(
        y <= p["y0"],
        p["a"] * y,
        torch.where(
            y <= p["y1"], p["b"] * y.clamp(min=p["y0"]).pow(p["c"]) + p["d"], p["e"] * torch.log(y + p["f"]) + p["g"]
        ),
    )


def _pu_inverse(x: Tensor) -> Tensor:
    p = _PU
    return torch.where(
        x <= p["x0"],
        x / p["a"],
        torch.where(
            x <= p["x1"],
            ((x - p["d"]) / p["b"]).clamp(min=0).pow(1 / p["c"]),
            torch.exp((x - p["g"]) / p["e"]) - p["f"],
        ),
    )


_PU_NORM = 1.0 / float(_pu(torch.tensor(HDR_MAX)))


def transfer(radiance: Tensor) -> Tensor:
    """Exposed linear radiance (>= 0) into the network's [0, 1] domain."""
    return _pu(radiance.clamp(0.0, HDR_MAX)) * _PU_NORM


def transfer_inverse(x: Tensor) -> Tensor:
    """The network's domain back to exposed linear radiance (negatives are not radiance)."""
    return _pu_inverse(x.clamp(min=0.0) / _PU_NORM)


def autoexposure(color: np.ndarray) -> float:
    """OIDN's exposure for an (H, W, 3) image: 0.18 over the geometric mean luminance of its 16x16-pixel
    bins' means (bins darker than 1e-8 left out), as the library computes it for HDR input."""
    lum = color[..., 0] * 0.212671 + color[..., 1] * 0.715160 + color[..., 2] * 0.072169
    h, w = lum.shape
    rows, cols = -(-h // 16), -(-w // 16)
    bins = np.array(
        [
            [lum[i * h // rows : (i + 1) * h // rows, j * w // cols : (j + 1) * w // cols].mean() for j in range(cols)]
            for i in range(rows)
        ],
        dtype=np.float64,
    )
    bins = bins[bins > 1e-8]
    return 1.0 if bins.size == 0 else float(0.18 / np.exp2(np.log2(bins).mean()))


def batch_exposure(color: Tensor) -> Tensor:
    """(N, 1, 1, 1) autoexposure of each (3, H, W) image of a batch: OIDN's, exactly where H and W are
    multiples of 16 (training patches); elsewhere its bins are pooled slightly differently."""
    lum = color[:, 0] * 0.212671 + color[:, 1] * 0.715160 + color[:, 2] * 0.072169
    h, w = lum.shape[-2:]
    bins = F.adaptive_avg_pool2d(lum[:, None].double(), (-(-h // 16), -(-w // 16))).flatten(1)
    valid = bins > 1e-8
    log_mean = (torch.log2(bins.clamp(min=1e-8)) * valid).sum(1) / valid.sum(1).clamp(min=1)
    exposure = torch.where(valid.any(1), 0.18 / torch.exp2(log_mean), torch.ones_like(log_mean))
    return exposure.to(color.dtype).view(-1, 1, 1, 1)


def network_input(
    color: Tensor, exposure: Tensor | float, albedo: Tensor | None = None, normal: Tensor | None = None
) -> Tensor:
    """(N, 3 or 9, H, W) from (N, 3, H, W) linear colour and, for the diffuse network, albedo and normal."""
    layers = [transfer(color * exposure)]
    if albedo is not None:
        layers += [albedo.clamp(0.0, 1.0), normal.clamp(-1.0, 1.0) * 0.5 + 0.5]
    return torch.cat(layers, 1)


def _conv(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1)


class OidnUNet(nn.Module):
    """OIDN's default-size U-Net; parameter names are OIDN's, so its archives load as they are."""

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        e1, e2, e3, e4, e5, d4, d3, d2a, d2b, d1a, d1b = 32, 48, 64, 80, 96, 112, 96, 64, 64, 64, 32
        self.enc_conv0, self.enc_conv1 = _conv(in_channels, e1), _conv(e1, e1)
        self.enc_conv2, self.enc_conv3, self.enc_conv4 = _conv(e1, e2), _conv(e2, e3), _conv(e3, e4)
        self.enc_conv5a, self.enc_conv5b = _conv(e4, e5), _conv(e5, e5)
        self.dec_conv4a, self.dec_conv4b = _conv(e5 + e3, d4), _conv(d4, d4)
        self.dec_conv3a, self.dec_conv3b = _conv(d4 + e2, d3), _conv(d3, d3)
        self.dec_conv2a, self.dec_conv2b = _conv(d3 + e1, d2a), _conv(d2a, d2b)
        self.dec_conv1a, self.dec_conv1b = _conv(d2b + in_channels, d1a), _conv(d1a, d1b)
        self.dec_conv0 = _conv(d1b, 3)

    @property
    def in_channels(self) -> int:
        return self.enc_conv0.in_channels

    def forward(self, x: Tensor) -> Tensor:
        """Network-domain input (sides multiples of ALIGNMENT) to network-domain output."""
        relu, pool = F.relu, lambda t: F.max_pool2d(t, 2, 2)
        up = lambda t: F.interpolate(t, scale_factor=2, mode="nearest")  # noqa: E731
        skip0 = x
        x = relu(self.enc_conv0(x))
        x = skip1 = pool(relu(self.enc_conv1(x)))
        x = skip2 = pool(relu(self.enc_conv2(x)))
        x = skip3 = pool(relu(self.enc_conv3(x)))
        x = pool(relu(self.enc_conv4(x)))
        x = relu(self.enc_conv5b(relu(self.enc_conv5a(x))))
        for skip, a, b in (
            (skip3, self.dec_conv4a, self.dec_conv4b),
            (skip2, self.dec_conv3a, self.dec_conv3b),
            (skip1, self.dec_conv2a, self.dec_conv2b),
            (skip0, self.dec_conv1a, self.dec_conv1b),
        ):
            x = relu(b(relu(a(torch.cat((up(x), skip), 1)))))
        return self.dec_conv0(x)

    def denoise(
        self, color: Tensor, exposure: Tensor | float, albedo: Tensor | None = None, normal: Tensor | None = None
    ) -> Tensor:
        """(N, 3, H, W) linear radiance in and out, any size: padded to ALIGNMENT with zeros as OIDN pads.
        `normal` is in [-1, 1] as renderers write it."""
        x = network_input(color, exposure, albedo, normal)
        h, w = x.shape[-2:]
        x = F.pad(x, (0, -w % ALIGNMENT, 0, -h % ALIGNMENT))
        return transfer_inverse(self(x)[..., :h, :w]) / exposure


class OidnUNetLarge(OidnUNet):
    """OIDN's `large` U-Net (RenderKit/oidn `training/model.py`, UNetLarge): two convs a level, wider, and a third
    full-resolution decoder conv. Parameter names are OIDN's."""

    def __init__(self, in_channels: int) -> None:
        nn.Module.__init__(self)
        e1, e2, e3, e4, e5 = 64, 96, 128, 192, 256
        self.enc_conv1a, self.enc_conv1b = _conv(in_channels, e1), _conv(e1, e1)
        self.enc_conv2a, self.enc_conv2b = _conv(e1, e2), _conv(e2, e2)
        self.enc_conv3a, self.enc_conv3b = _conv(e2, e3), _conv(e3, e3)
        self.enc_conv4a, self.enc_conv4b = _conv(e3, e4), _conv(e4, e4)
        self.enc_conv5a, self.enc_conv5b = _conv(e4, e5), _conv(e5, e5)
        self.dec_conv4a, self.dec_conv4b = _conv(e5 + e3, e4), _conv(e4, e4)
        self.dec_conv3a, self.dec_conv3b = _conv(e4 + e2, e3), _conv(e3, e3)
        self.dec_conv2a, self.dec_conv2b = _conv(e3 + e1, e2), _conv(e2, e2)
        self.dec_conv1a, self.dec_conv1b = _conv(e2 + in_channels, e1), _conv(e1, e1)
        self.dec_conv1c = _conv(e1, 3)

    @property
    def in_channels(self) -> int:
        return self.enc_conv1a.in_channels

    def forward(self, x: Tensor) -> Tensor:
        relu, pool = F.relu, lambda t: F.max_pool2d(t, 2, 2)
        up = lambda t: F.interpolate(t, scale_factor=2, mode="nearest")  # noqa: E731
        skips = [x]
        for a, b in (
            (self.enc_conv1a, self.enc_conv1b),
            (self.enc_conv2a, self.enc_conv2b),
            (self.enc_conv3a, self.enc_conv3b),
            (self.enc_conv4a, self.enc_conv4b),
        ):
            x = pool(relu(b(relu(a(x)))))
            skips.append(x)
        x = relu(self.enc_conv5b(relu(self.enc_conv5a(x))))
        for skip, a, b in (
            (skips[3], self.dec_conv4a, self.dec_conv4b),
            (skips[2], self.dec_conv3a, self.dec_conv3b),
            (skips[1], self.dec_conv2a, self.dec_conv2b),
            (skips[0], self.dec_conv1a, self.dec_conv1b),
        ):
            x = relu(b(relu(a(torch.cat((up(x), skip), 1)))))
        return self.dec_conv1c(x)


def network_for(state: dict, in_channels: int) -> OidnUNet:
    """An untrained network of the architecture whose parameters `state` (a state dict or archive) holds."""
    return (OidnUNetLarge if uses_clean_guides(state) else OidnUNet)(in_channels)


def uses_clean_guides(net_or_state) -> bool:
    """Whether the network is the large one, trained on prefiltered guides (clean_guides)."""
    keys = net_or_state.state_dict() if isinstance(net_or_state, nn.Module) else net_or_state
    return "enc_conv1a.weight" in keys


def oidn_unet(branch: str, network: str = "standard") -> OidnUNet:
    """A fresh copy of the branch's network with the weights the installed OIDN runs at quality "high" (see
    module doc): "large" is the diffuse branch's final-frame network (the specular branch has none)."""
    large = network == "large" and branch == "diffuse"
    weights = _large_library_weights() if large else _library_weights(branch)
    net = (OidnUNetLarge if large else OidnUNet)(INPUT_CHANNELS[branch])
    net.load_state_dict({name: torch.from_numpy(value) for name, value in weights.items()})
    return net


def clean_guides(albedo: Tensor, normal: Tensor) -> tuple[Tensor, Tensor]:
    """(N, 3, H, W) albedo and normal (in [-1, 1]) denoised by OIDN's own guide networks, in its library: what
    the large network was trained on. No gradient flows through them (they are inputs)."""
    from admc.common import oidn

    def each(name: str, batch: Tensor) -> Tensor:
        images = batch.detach().float().cpu().permute(0, 2, 3, 1).numpy()
        out = np.stack([oidn.prefilter(name, image) for image in images])
        return torch.from_numpy(out).permute(0, 3, 1, 2).to(batch.device, batch.dtype)

    return each("albedo", albedo), each("normal", normal)


@functools.cache
def _library_weights(branch: str) -> dict[str, np.ndarray]:
    """The archive in OIDN's library that its `branch` filter runs, found once per process (reading the
    library and trying its archives takes about 0.3 s, and every partner, test and export asks for it).

    The library does not name its archives, so each one of the right shape is run on a probe image beside
    OIDN itself and the one that reproduces it is taken. It must be within 3% on average: on the probe a wrong
    archive is 17-38% off and the right one 1e-6 in float32; CPUs with AMX-FP16, where OIDN computes in
    float16, move it by about 1% (an estimate: 16 layers of fp16 activations, amplified up to 16x by the
    PU curve's inverse).
    """
    from admc.common import oidn

    channels = INPUT_CHANNELS[branch]
    probe = _probe_image(channels)
    expected = oidn.denoise(*probe, quality="high")
    best, best_error = None, np.inf
    for archive in library_archives():
        if (
            archive.get("enc_conv0.weight", np.empty((0, 0))).shape[1] != channels
            or len(archive) != 32
            or archive["enc_conv2.weight"].shape[0] != 48
        ):
            continue
        error = _probe_error(OidnUNet(channels), archive, probe, expected)
        if error < best_error:
            best, best_error = archive, error
    if best is None or best_error > MATCH_TOLERANCE:
        raise ArchiveError(
            f"no weight archive in OIDN's library reproduces its {branch} filter "
            f"(closest {best_error:.1%} apart): an OIDN version admc does not know"
        )
    return best


@functools.cache
def _large_library_weights() -> dict[str, np.ndarray]:
    """The library's large clean-guide archive (`rt_hdr_calb_cnrm_large`), checked as `_library_weights` checks
    the others: on the probe with guides it has prefiltered, run with cleanAux."""
    from admc.common import oidn

    color, albedo, normal = _probe_image(INPUT_CHANNELS["diffuse"])
    probe = color, oidn.prefilter("albedo", albedo), oidn.prefilter("normal", normal)
    expected = oidn.denoise(*probe, quality="high", clean_aux=True)
    for archive in library_archives():
        if archive.get("enc_conv1a.weight", np.empty((0, 0))).shape[1] != INPUT_CHANNELS["diffuse"]:
            continue
        error = _probe_error(OidnUNetLarge(INPUT_CHANNELS["diffuse"]), archive, probe, expected)
        if error <= MATCH_TOLERANCE:
            return archive
        raise ArchiveError(
            f"the large weight archive in OIDN's library does not reproduce its final-frame filter ({error:.1%} "
            "apart): an OIDN version admc does not know"
        )
    raise ArchiveError("OIDN's library carries no large network for albedo and normal guides (OIDN 2.2 or later does)")


def _probe_error(net: OidnUNet, archive: dict, probe: tuple, expected: np.ndarray) -> float:
    """The mean relative difference between `net` with `archive`'s weights on the probe (colour[, albedo,
    normal]) and OIDN's own output `expected`."""
    net.load_state_dict({name: torch.from_numpy(value) for name, value in archive.items()})
    tensors = [torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None] for a in probe if a is not None]
    with torch.no_grad():
        out = net.eval().denoise(tensors[0], autoexposure(probe[0]), *tensors[1:])[0].numpy().transpose(1, 2, 0)
    return float(np.abs(out - expected).mean() / np.abs(expected).mean())


def _probe_image(channels: int, size: int = 32) -> tuple:
    """A fixed HDR image with edges and noise, and for the diffuse network noisy albedo and normal (which
    OIDN's `rt_hdr_alb_nrm` is trained for and its clean-guide variant is not: 4% apart with clean guides)."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[:size, :size] / size
    base = np.stack([0.2 + xx, 0.5 + 0.0 * yy, 0.3 + (yy > 0.5)], -1)
    color = (base * rng.exponential(1.0, (size, size, 1)) * 2.0).astype(np.float32)
    if channels == 3:
        return color, None, None
    albedo = np.clip(base * 0.6 * rng.uniform(0.5, 1.5, (size, size, 1)), 0, 1).astype(np.float32)
    normal = np.stack([xx - 0.5, yy - 0.5, np.ones_like(xx)], -1) + rng.normal(0.0, 0.3, (size, size, 3))
    normal = (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32)
    return color, albedo, normal
