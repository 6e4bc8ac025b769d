"""The `crestereo-pp` command line (train, eval, predict, export); entry point `cli.main:main`.

crestereo-pp train --model lite --crop-height 256 --crop-width 512 --max-minutes 10 --out-dir runs/lite
crestereo-pp train --resume runs/lite/checkpoint.pt --max-steps 20000
torchrun --nproc-per-node 4 -m cli.main train --model full --batch-size 6
crestereo-pp export runs/lite/checkpoint.pt -o model/weights/lite.pt --fp16
crestereo-pp eval ../shared/data/stereo-dev --model lite --baseline sgbm --json dev.json --sheets sheets/
crestereo-pp predict left.png right.png -o disp.pfm --uncertainty u.pfm --color disp.png
crestereo-pp predict 'seq/left/*.png' 'seq/right/*.png' -o out/ --format png
"""

import os

# Sleeping OpenMP waits, as in the service (see service/__init__.py): spinning threads run 10-50x
# slower on a shared or oversubscribed CPU. Must be set before torch loads; the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
