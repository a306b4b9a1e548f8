"""DSRNet's training options, in a module without torch (the stage table imports it)."""
from __future__ import annotations

from dataclasses import dataclass

from ..config import Options, param
from ..errors import ConfigError, escapes

PERCEPTUAL_WEIGHT = 0.1  # §5.2.2: "Weight w (default 0.1)"


@dataclass(frozen=True)
class TrainOptions(Options):
    """DSRNet training (§5.2.2, §6); the `supersample` stage embeds these as [supersample.train]."""

    steps: int = param(1200, "training steps (the cosine learning-rate decay spans them)",
                       min=1, max=1_000_000)
    batch: int = param(4, "crops per step", min=1, max=256)
    crop: int = param(48, "crop side in low-resolution pixels", min=8, max=1024)
    lr: float = param(1e-3, "Adam learning rate", min=1e-7, max=1.0)
    warmup_steps: int = param(100, "linear learning-rate warm-up before the cosine decay. Without "
                              "it Adam's first sign-sized steps blew up the zero-initialised "
                              "residual and the net settled at bicubic quality",
                              min=0, max=1_000_000)
    perceptual_weight: float = param(PERCEPTUAL_WEIGHT, "w of the filter / VGG term (§5.2.2: "
                                     "w = 0.1)", min=0.0, max=100.0)
    l1_weight: float = param(0.0, "optional L1 image term (Table 4 mentions L1, §5.2.2's equation "
                             "does not); 0 = the paper's loss", min=0.0, max=100.0)
    warp_weight: float = param(1.0, "weight of L_warp (§5.2.2 gives none)", min=0.0, max=100.0)
    vgg_weights: str = param("", "a VGG-16 features state dict (.pt/.pth, a path inside the "
                             "workspace) for the perceptual loss; none can be downloaded, so "
                             "empty = a fixed filter bank")
    seed: int = param(0, "seed of the weights and the crops (training is deterministic)",
                      min=0, max=2**31 - 1)
    checkpoint_every: int = param(100, "steps between checkpoints and validations", min=1,
                                  max=1_000_000)
    flip: bool = param(True, "random horizontal flips of the crops")
    capture_fraction: float = param(0.0, "share of the crops taken from capture pairs (the "
                                    "captured image area-downsampled, with its render's depth) "
                                    "instead of render pairs; our extension beyond §6, measured "
                                    "no gain (docs/DSRNET.md)", min=0.0, max=1.0)
    fit_budget: bool = param(True, "when `steps` would not fit the time budget, end the cosine "
                             "decay at the step the budget is expected to reach (our addition) "
                             "instead of stopping at a high learning rate")
    grad_clip: float = param(1.0, "clip the gradient's global L2 norm to this; 0 = off. Our "
                             "addition: a `paper`-width run diverged without it", min=0.0,
                             max=1e6)
    device: str = param("auto", "torch device", choices=("auto", "cpu", "cuda"),
                        affects_output=False)
    threads: int = param(0, "torch CPU threads; 0 = all cores, or 1 when the machine is already "
                         "loaded (cpu_threads)", min=0, max=512, affects_output=False)
    progress: bool = param(True, "show a progress bar", affects_output=False)

    def check(self, prefix: str) -> None:
        if self.vgg_weights and not self.vgg_weights.endswith((".pt", ".pth")):
            raise ConfigError(prefix + "vgg_weights", f"expected a .pt/.pth file, got "
                              f"{self.vgg_weights!r}")
        why = escapes(self.vgg_weights) if self.vgg_weights else None
        if why:
            raise ConfigError(prefix + "vgg_weights", f"{self.vgg_weights!r} {why}: give a path "
                              "inside the workspace")
