"""Evaluation: disparity metrics (EPE, bad-N, D1-all), the OpenCV SGBM baseline, per-pair
reports and comparison sheets. Command line: `crestereo-pp eval --help`."""
