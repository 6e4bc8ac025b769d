"""Which backend and precision a predictor computes with: their names, and what ``auto`` picks
on this machine (``$CRESTEREO_BACKEND``, the device, whether OpenVINO is installed, whether the
CPU computes bf16 natively)."""

from __future__ import annotations

import os
from typing import Literal

import torch

from .openvino_backend import native_bf16, openvino_available

Precision = Literal["fp32", "bf16"]
"""fp32: the network in float32; bf16: torch under bf16 autocast, OpenVINO with bf16 inference
precision (its graphs keep the feature networks' ops other than convolutions in fp32,
``openvino_export.keep_features_in_fp32``); the maps stay float32 either way."""

Backend = Literal["torch", "openvino"]
"""torch: eager (CUDA graphs on a GPU), the reference; openvino: compiled for the CPU
(``inference.openvino_backend``)."""

BackendChoice = Literal["auto", "torch", "openvino"]
PrecisionChoice = Literal["auto", "fp32", "bf16"]


def requested_backend(backend: BackendChoice) -> BackendChoice:
    """The backend asked for: ``backend``, or for ``auto`` ``$CRESTEREO_BACKEND`` where set (the one
    place it is read; lower-cased, unchecked: ``resolve_backend`` refuses an unknown name)."""
    if backend != "auto":
        return backend
    return os.environ.get("CRESTEREO_BACKEND", "auto").strip().lower() or "auto"  # type: ignore[return-value]


def resolve_backend(backend: BackendChoice, device: torch.device) -> Backend:
    """``auto``: ``$CRESTEREO_BACKEND`` where set (``requested_backend``), else OpenVINO on a CPU
    where it is installed, else torch. ValueError where OpenVINO is asked for and cannot run
    (another device, or not installed), or for an unknown name. The one place a predictor's
    backend is chosen (``load_model``)."""
    backend = requested_backend(backend)
    if backend == "auto":
        return "openvino" if device.type == "cpu" and openvino_available() else "torch"
    if backend not in ("torch", "openvino"):
        raise ValueError(f"unknown backend {backend!r}; choose auto, torch or openvino")
    if backend == "openvino":
        if device.type != "cpu":
            raise ValueError(f"the openvino backend runs on the CPU, not on {device}")
        if not openvino_available():
            raise ValueError("the openvino backend needs the openvino package: pip install openvino")
    return backend


def resolve_precision(precision: PrecisionChoice, backend: Backend) -> Precision:
    """``auto``: bf16 for OpenVINO on a CPU that computes bf16 natively (AMX, AVX512-BF16),
    fp32 everywhere else (torch's bf16 autocast on a CPU spends its time casting)."""
    if precision == "auto":
        return "bf16" if backend == "openvino" and native_bf16() else "fp32"
    return precision
