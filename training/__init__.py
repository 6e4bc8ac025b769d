"""Training of CREStereo++ / Lite-CREStereo++: typed config and presets, batch mixture of
procedural scenes and real datasets, exact-resume checkpoints, DDP under torchrun, export.

    from crestereo_pp.training.config import preset
    from crestereo_pp.training.trainer import train
    result = train(preset("pretrain", max_steps=1000, out_dir="runs/lite"))

Command line: `crestereo-pp train --help`, `crestereo-pp export --help`.
"""
