"""The prepared GPU check: one command for a GPU machine lent for minutes, where nothing can be
debugged. Stages, each in its own process and each guarded (a failure or a timeout is recorded
and the next stage runs), within one time budget:

    environment  torch, the device, nvidia-smi
    tests        the CUDA tests (tests/gpu, the CUDA test of stereo_data)
    bench        inference table: lite and full at 384x1248, batch 1 and 8, fp32 and
                 bf16, eager and CUDA-graph replay, in one pass at the pair's size (as the paper
                 times the network), and the default inference at batch 1 in bf16
                 (StereoPredictor.predict_batch, as the service runs it); then bf16 against fp32
                 and graph against eager on the dev pairs
    service      `python -m crestereo_pp.service` on loopback with CRESTEREO_DEVICE=cuda: a real pair over HTTP,
                 concurrent requests (batches), both models; skipped when fastapi is missing
    probe        training throughput, lite and full: pairs/s and peak memory of the training step at
                 batch 1x-8x the recipe's, plain AdamW, channels-last, torch.compile and CUDA graphs
                 (bench/train_speed.py's `measure` and `probe_rows`), at most two minutes
    train        --model (lite) from --weights (its shipped file) for the minutes left: a short
                 probe run measures the step rate (with --adopt: the probe's best row, its rate
                 measured), then one run sized to end its flat-decay schedule (and its weight
                 average's horizon) within the time left, its decay brought forward where the run
                 falls behind that rate; a checkpoint with an optimiser state is resumed, a
                 weights-only file starts a fresh optimiser
    arms         (only when named in --stages, instead of train) a data candidate measured: the
                 recipe (control) and the recipe with --arm's settings (candidate), each trained
                 for the same steps from the same weights in half the time left, then scored with
                 the default inference on the dev pairs (the Middlebury 2014 ones also apart) and
                 on procedural scenes drawn as the candidate trains; each returned as arm-NAME.pt
                 (to serve) and arm-NAME-stable.pt (to resume)

    python3 bench/gpu_check --out DIR [--minutes 9] [--stages S,...] [--data DIR] [--wheels DIR]
                            [--model lite|full] [--weights FILE] [--train-set KEY=VALUE ...]
                            [--train-compile] [--adopt [--probe-from FILE]] [--arm KEY=VALUE ...]
    python3 bench/gpu_check --cpu-smoke --out DIR    # the same stages on the CPU, tiny
    python3 bench/gpu_check --pack-data [--data DIR]   # here, before a run: shared/stereo-dev.tar.gz

DIR (or $GPU_CHECK_OUT, else $OUT) receives at most 8 files, each under 16 MiB: gpu_check.log
(every stage's output), summary.md (stage results and tables), bench.json (the benchmark's
numbers, and the probe's under "probe": a later run's --probe-from FILE adopts from them without
probing again) and the training run's checkpoint.pt, log.csv, loss_curve.png (validation.csv with dev
pairs). --data: the real dev pairs (NAME/{left.png,right.png,disp.pfm}); by default $STEREO_DEV,
shared/data/stereo-dev in the checkout or beside it, then the pairs --pack-data packed (unpacked into
a scratch folder), else procedural scenes stand in. --wheels: a
folder of wheels (fastapi, uvicorn, ...) installed with pip --no-index for the service stage; by
default .whl/ in the checkout when present. Needs only the standard library in this process; the
stages need torch, numpy, OpenCV, httpx and the project. Exit status 0 when no stage failed.

The package (run from the tree, never installed; `__main__.py` says how it finds its imports):

    orchestrator  the options, the stages in turn, child mode (--stage); standard library only
    runner        a stage's process: its log, its time limit, its result
    wheels        the carried wheels, installed for the service stage
    report        summary.md
    plans         GPU and CPU_SMOKE: what each stage does and how long it may take
    pairs, recipe the dev pairs (or scenes) the stages compute; the weights and step they train
    stages/       one module per stage, importing torch and the project only when it runs

The stages measure with the benchmarks' own code: inference timing with timing.py's
`timed_calls` (as model_speed.py), the service's concurrent requests with service_load.py's
`concurrently`, the training step with train_speed.py's `measure` and `probe_rows`.
"""
