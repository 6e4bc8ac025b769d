"""Training of CREStereo++ / Lite-CREStereo++: typed config and presets, batch mixture of
procedural scenes and real datasets, exact-resume checkpoints, DDP under torchrun, export.

    from training.config import preset
    from training.trainer import train
    result = train(preset("pretrain", max_steps=1000, out_dir="runs/lite"))

Command line: `crestereo-pp train --help`, `crestereo-pp export --help`.
"""
