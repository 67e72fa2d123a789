"""Training settings: the `[train]` section of a run config (`[model]` is nets/settings.py). Torch-free and
outside training/: the config and every command read them, and denoising loads no training module.

Fields use only int/float/str/bool/tuple so the generic TOML loader can type-check them; `check()`
raises ValueError("<field>: <problem>"). The dataclass defaults are the paper's scale (values from
the authors' code where code and paper text disagree); the presets a run starts from are
configs/*.toml (default.toml: a CPU model that trains in minutes; paper.toml: the paper's scale).
"""

from __future__ import annotations

from dataclasses import dataclass

from admc.common.layout import BRANCHES

from .checks import non_negative_ints, positive_ints, require

SELECT_METRIC_LABELS = {"relmse": "relMSE", "relmse+ssim": "relMSE+1-SSIM score"}
"""train.select_metric -> its name in notes (selection.py: what each ranks by)."""
SELECT_METRICS = tuple(SELECT_METRIC_LABELS)

DEVICES = ("auto", "cpu", "cuda")
PRECISIONS = ("auto", "float32", "bfloat16")
OIDN_LOSSES = ("l1", "l1_msssim")
OIDN_NETWORKS = ("standard", "large")
"""train.oidn_network: which of OIDN's networks the diffuse branch's partner starts from (nets/oidn_unet.py)."""
OIDN_SELECTIONS = {"relmse": ("relmse",), "relmse+flip": ("relmse", "hdr_flip")}
"""train.oidn_select -> the val metrics whose ratios to OIDN's own weights rank its fine-tune's steps
(training/oidn_partner.py: their geometric mean)."""
STAGES = ("pretrain", "finetune")


@dataclass(frozen=True)
class TrainSettings:
    """One training stage. Steps are global iterations; every branch takes one step per iteration.

    Schedule: steps < l1_warmup_steps train the generator on L1 only; the next critic_only_steps
    train the critic alone against the frozen generator (the paper's critic pretraining); after
    that WGAN-GP training, critic_steps_per_g critic updates (each on a fresh batch) per generator
    update. adversarial=False is the "L1 only" ablation: every step is an L1 step.
    """

    steps: int = 600_000
    minutes: float = 0.0  # > 0: a wall-clock budget; the run ends at the first step past it (and
    # at `steps` at the latest), validated and checkpointed; 0 = no budget
    batch_size: int = 8
    l1_warmup_steps: int = 0
    critic_only_steps: int = 0
    critic_steps_per_g: int = 1
    lr_g_diffuse: float = 1e-6
    lr_g_specular: float = 1e-4
    lr_d: float = 1e-4
    body_lr_factor: float = 5.0  # body + encoder learn at this multiple of the branch's lr
    head_tail_start_step: int = 20_000  # head and tail stay fixed before this step
    lr_milestones: tuple[int, ...] = (50_000, 100_000, 150_000, 200_000)
    lr_gamma: float = 0.5
    l1_weight: float = 1.0
    l1_floor: float = 1.0  # L1 on log(v + l1_floor) of linear v; 1 = log1p (losses.log_floor)
    ssim_weight: float = 0.0  # weight of 1 - SSIM of the display images (losses.display_ssim_loss)
    distill_from: str = ""  # weights or checkpoint of a teacher generator ("" = none): the loss also
    # compares the output with the teacher's on the same input (teacher.py)
    distill_weight: float = 1.0  # weight of that term (L1 on log(v + l1_floor), as the reference's)
    ema: float = 0.0  # validate and ship an exponential moving average of the generator's
    # weights with this decay per step (branch.py); 0 = the weights themselves
    adv_weight: float = 5e-3
    gp_weight: float = 10.0
    adversarial: bool = True
    val_every: int = 5_000  # 0 = no validation
    val_patches: int = 64
    select_metric: str = "relmse"  # what ranks validated steps: relmse | relmse+ssim (selection.py)
    oidn_blend: bool = False  # choose, on the val patches, the share of its own output a model keeps
    # when blended with OIDN's (the rest OIDN's): shipped with the weights
    oidn_minutes: float = 0.0  # > 0: before its own steps, a fine-tune trains OIDN's networks this long on
    # the domain (training/oidn_partner.py), the partner the blend then mixes with; 0 = OIDN as it ships
    oidn_lr: float = 2e-5  # Adam's rate for that (chosen on the val frames of the domains: docs/results/)
    oidn_loss: str = "l1"  # its loss in OIDN's PU domain: l1 | l1_msssim (OIDN's own training loss; nets/losses.py)
    oidn_select: str = "relmse+flip"  # what ranks its validated steps: relmse+flip | relmse (OIDN_SELECTIONS)
    oidn_network: str = "standard"  # the diffuse partner's start: standard | large (OIDN's final-frame route:
    # its large network on guides it prefilters; nets/oidn_unet.py)
    oidn_lr_large: float = 5e-6  # Adam's rate for the large one (at oidn_lr it lost HDR-FLIP from step 100)
    select_z: float = 2.0  # a fine-tuning ships a step only this many standard errors better than
    # its starting weights on the val patches (selection.py); 0: any better
    checkpoint_every: int = 5_000
    log_every: int = 100
    num_workers: int = 4
    threads: int = 0  # CPU intra-op threads; 0 = torch's default
    device: str = "auto"
    precision: str = "auto"  # auto | float32 | bfloat16 (autocast; see branch.resolve_precision)
    seed: int = 0
    max_bad_steps: int = 20  # consecutive non-finite steps before training stops
    branches: tuple[str, ...] = BRANCHES

    def check(self) -> None:
        positive_ints(
            self, ("steps", "batch_size", "critic_steps_per_g", "checkpoint_every", "log_every", "max_bad_steps")
        )
        non_negative_ints(
            self,
            (
                "l1_warmup_steps",
                "critic_only_steps",
                "head_tail_start_step",
                "val_every",
                "num_workers",
                "threads",
                "seed",
            ),
        )
        require(
            self.val_every == 0 or (isinstance(self.val_patches, int) and self.val_patches >= 1),
            "val_patches",
            f"must be >= 1 when val_every > 0, got {self.val_patches!r}",
        )
        for name in (
            "lr_g_diffuse",
            "lr_g_specular",
            "lr_d",
            "oidn_lr",
            "oidn_lr_large",
            "body_lr_factor",
            "lr_gamma",
            "l1_floor",
        ):
            value = getattr(self, name)
            require(isinstance(value, (int, float)) and value > 0, name, f"must be > 0, got {value!r}")
        require(isinstance(self.distill_from, str), "distill_from", f'must be a path or "", got {self.distill_from!r}')
        for name in (
            "l1_weight",
            "ssim_weight",
            "adv_weight",
            "gp_weight",
            "select_z",
            "distill_weight",
            "minutes",
            "oidn_minutes",
        ):
            value = getattr(self, name)
            require(isinstance(value, (int, float)) and value >= 0, name, f"must be >= 0, got {value!r}")
        require(isinstance(self.ema, (int, float)) and 0 <= self.ema < 1, "ema", f"must be in [0, 1), got {self.ema!r}")
        require(self.lr_gamma <= 1, "lr_gamma", f"must be in (0, 1], got {self.lr_gamma!r}")
        milestones = list(self.lr_milestones)
        require(
            all(isinstance(m, int) and m >= 1 for m in milestones) and milestones == sorted(set(milestones)),
            "lr_milestones",
            f"must be strictly increasing ints >= 1, got {milestones}",
        )
        require(isinstance(self.adversarial, bool), "adversarial", f"must be true or false, got {self.adversarial!r}")
        require(isinstance(self.oidn_blend, bool), "oidn_blend", f"must be true or false, got {self.oidn_blend!r}")
        require(
            self.oidn_minutes == 0 or self.oidn_blend,
            "oidn_minutes",
            f"is {self.oidn_minutes:g}: it fine-tunes OIDN as the partner of the OIDN blend, but oidn_blend is "
            "false; set oidn_blend = true, or oidn_minutes = 0",
        )
        require(self.oidn_loss in OIDN_LOSSES, "oidn_loss", f"{self.oidn_loss!r} is not one of {OIDN_LOSSES}")
        require(
            self.oidn_select in OIDN_SELECTIONS,
            "oidn_select",
            f"{self.oidn_select!r} is not one of {tuple(OIDN_SELECTIONS)}",
        )
        require(
            self.oidn_network in OIDN_NETWORKS,
            "oidn_network",
            f"{self.oidn_network!r} is not one of {OIDN_NETWORKS}",
        )
        require(self.device in DEVICES, "device", f"{self.device!r} is not one of {DEVICES}")
        require(self.precision in PRECISIONS, "precision", f"{self.precision!r} is not one of {PRECISIONS}")
        require(
            self.select_metric in SELECT_METRICS,
            "select_metric",
            f"{self.select_metric!r} is not one of {SELECT_METRICS}",
        )
        require(
            len(self.branches) > 0
            and all(b in BRANCHES for b in self.branches)
            and len(set(self.branches)) == len(self.branches),
            "branches",
            f"must be distinct names from {BRANCHES}, got {list(self.branches)}",
        )
        require(
            self.l1_weight > 0 or self.ssim_weight > 0 or self.adversarial,
            "l1_weight",
            "and ssim_weight are 0 and adversarial is off: nothing to train",
        )

    def lr_g(self, branch: str) -> float:
        return self.lr_g_diffuse if branch == "diffuse" else self.lr_g_specular

    def phase(self, step: int) -> str:
        """ "l1", "critic" (generator frozen) or "adversarial" for a 0-based global step."""
        if not self.adversarial or step < self.l1_warmup_steps:
            return "l1"
        if step < self.l1_warmup_steps + self.critic_only_steps:
            return "critic"
        return "adversarial"
