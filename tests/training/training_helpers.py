"""The tiny training config that the run and distributed tests share."""

from pathlib import Path

from crestereo_pp.training.config import TrainConfig


def tiny(out_dir: Path, **overrides) -> TrainConfig:
    """Lite at 64x96, one pair per step, every step logged, fp32 on the CPU."""
    values = dict(
        crop_height=64,
        crop_width=96,
        batch_size=1,
        max_steps=2,
        log_every=1,
        checkpoint_every=1000,
        num_workers=0,
        device="cpu",
        out_dir=str(out_dir),
        warmup_fraction=0.0,
        real_scale_range=(1.0, 1.0),
    )
    return TrainConfig(**{**values, **overrides})
