"""The report: summary.md (each stage's status and detail, the benchmark's and the probe's tables, the
service's and the training's numbers, the output files against their limits), rewritten after
every stage."""

from __future__ import annotations

import datetime as dt
import json
import math
import platform
from pathlib import Path
from typing import Any

from .plans import MAX_FILE_BYTES, MAX_FILES, Plan, StageResult

BF16_TOLERANCE_PX = 0.05
"""bf16 is usable where its disparities are within this mean distance of fp32's (issue 11)."""


def write_summary(out: Path, plan: Plan, data: Path | None, results: dict[str, StageResult]) -> None:
    environment = results.get("environment", StageResult("skipped")).data
    lines = [
        f"# GPU check: {plan.label}",
        "",
        f"{dt.datetime.now(dt.UTC).isoformat(timespec='seconds')}, budget {plan.minutes:g} min; "
        f"device: {environment.get('device', '?')}; torch {environment.get('torch', '?')}; "
        f"Python {platform.python_version()}; dev pairs: {data or 'none (procedural scenes)'}",
        "",
        "| stage | status | seconds | detail |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {name} | {r.status} | {r.seconds:.0f} | {r.detail.replace('|', '/')} |" for name, r in results.items()
    ]
    if "bench" in results:
        lines += ["", *bench_tables(results["bench"].data)]
    if "service" in results and results["service"].data:
        lines += ["", "## Service", "", "```", json.dumps(results["service"].data, indent=1), "```"]
    if "probe" in results and results["probe"].data:
        lines += ["", *probe_table(results["probe"].data)]
    if "train" in results and results["train"].data:
        lines += ["", "## Training", "", "```", json.dumps(results["train"].data, indent=1), "```"]
    if "arms" in results and results["arms"].data:
        lines += ["", *arms_table(results["arms"].data)]
    lines += ["", *output_files_report(out)]
    (out / "summary.md").write_text("\n".join(lines) + "\n")


INFERENCE_NAMES = {False: "one pass", "auto": "default (auto)"}
"""The speed table's name for a row's ``two_pass``: one pass at the pair's size (the paper's
timing), or the default inference, which may enlarge the pair and take two passes."""


def bench_tables(data: dict[str, Any]) -> list[str]:
    """Markdown: the speed table (one row per model, size, inference, batch, precision, graphs) and the
    accuracy table (one row per model)."""
    lines = [
        f"## Inference ({data.get('device', '?')})",
        "",
        "`StereoPredictor.predict_batch` end to end (uint8 arrays in, numpy maps out, as the service "
        f"calls it), median of the timed calls after {data.get('warmup_calls')} untimed ones; iterations "
        f"{data.get('iters') or 'of each model'}; procedural scenes.",
        "",
        "| model | size | inference | batch | precision | CUDA graph | ms / batch | ms / pair | pairs / s | peak MiB "
        "| replays |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in data.get("rows", []):
        graphs = "yes" if row["graphs"] else "no"
        inference = INFERENCE_NAMES[row["two_pass"]]
        head = f"| {row['model']} | {row['size']} | {inference} | {row['batch']} | {row['precision']} | {graphs} |"
        if "skipped" in row:
            lines.append(f"{head} {row['skipped']} | | | | |")
        else:
            lines.append(
                f"{head} {row['ms_per_batch']:.2f} | {row['ms_per_pair']:.2f} | {row['pairs_per_s']:.1f} | "
                f"{row['peak_mib'] if row['peak_mib'] is not None else '-'} | {row['replays']} |"
            )
    lines += [
        "",
        f"bf16 against fp32 (eager) and graph replay against eager (fp32), per pair, mean over pairs; "
        f"bf16 is usable where the mean |difference| is within {BF16_TOLERANCE_PX} px.",
        "",
        "| model | pairs | source | mean abs bf16 - fp32 px | within tolerance | max abs graph - eager px "
        "| EPE fp32 | EPE bf16 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in data.get("accuracy", []):
        graph = "-" if row["graph_max_abs_px"] is None else f"{row['graph_max_abs_px']:.4f}"
        lines.append(
            f"| {row['model']} | {row['pairs']} | {row['source']} | {row['bf16_mean_abs_px']:.4f} | "
            f"{'yes' if row['bf16_mean_abs_px'] <= BF16_TOLERANCE_PX else 'NO'} | {graph} | "
            f"{row['epe_fp32']:.3f} | {row['epe_bf16']:.3f} |"
        )
    return lines


def probe_table(data: dict[str, Any]) -> list[str]:
    """Markdown: one row per model and setting; `vs recipe` is pairs/s against the model's first row."""
    lines = [
        f"## Training throughput ({data.get('device', '?')})",
        "",
        "Median seconds per optimiser step after two untimed steps (the batch made on the device included; "
        "`data ms` of it); the first step's seconds show compilation; lr scaled by the square root of the "
        "batch ratio.",
        "",
        "| model | row | setting | pairs / s | vs recipe | step ms | data ms | first step s | peak GiB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    recipe: dict[str, float] = {}
    for row in data.get("rows", []):
        head = f"| {row['model']} | {row['row']} | {row['setting']} |"
        if "skipped" in row:
            lines.append(f"{head} {row['skipped'].replace('|', '/')} | | | | | |")
            continue
        base = recipe.setdefault(row["model"], row["pairs_per_s"])
        peak = "-" if row["peak_gib"] is None else f"{row['peak_gib']:.1f}"
        lines.append(
            f"{head} {row['pairs_per_s']:.1f} | {row['pairs_per_s'] / base:.2f}x | {1000 * row['step_s']:.0f} | "
            f"{1000 * row['data_s']:.0f} | {row['first_step_s']:.1f} | {peak} |"
        )
    return lines


ARM_SCORES = ("dev", "apart", "family")
"""The arms' scores, each as EPE px / bad-1 % / bad-2 %: the dev pairs, the Middlebury 2014 ones
among them, the candidate's procedural scenes."""


def arms_table(data: dict[str, Any]) -> list[str]:
    """Markdown: one row per arm, its settings, steps and each of ARM_SCORES."""
    lines = [
        f"## Arms: {json.dumps(data.get('arm'))} against the recipe",
        "",
        f"{data.get('model')} from {data.get('weights')}, {data.get('steps')} steps ({data.get('pairs')} pairs) "
        f"each; default inference, torch fp32; EPE px / bad-1 % / bad-2 %; family: {data.get('family')}.",
        "",
        "| arm | settings | steps | train s | " + " | ".join(ARM_SCORES) + " |",
        "|---|---|---|---|" + "---|" * len(ARM_SCORES),
    ]
    for row in data.get("rows", []):
        cells = [
            f"{row[f'{name}_epe']:.3f} / {row[f'{name}_bad1']:.2f} / {row[f'{name}_bad2']:.2f} ({row[f'{name}_pairs']})"
            if f"{name}_epe" in row
            else "-"
            for name in ARM_SCORES
        ]
        lines.append(
            f"| {row['arm']} | {json.dumps(row['settings'])} | {row['steps']} | {row['train_s']} | "
            + " | ".join(cells)
            + " |"
        )
    rows = {row["arm"]: row for row in data.get("rows", [])}
    if {"control", "candidate"} <= set(rows):
        control, candidate = rows["control"], rows["candidate"]
        changes = [
            f"{name} {candidate[f'{name}_bad2'] - control[f'{name}_bad2']:+.2f} points "
            f"(EPE {candidate[f'{name}_epe'] - control[f'{name}_epe']:+.3f} px)"
            for name in ARM_SCORES
            if f"{name}_bad2" in control and f"{name}_bad2" in candidate
        ]
        lines += ["", "Candidate against control, bad-2: " + ", ".join(changes) + "."]
        each = [
            f"{name} {pair_by_pair(control[f'{name}_bad2_each'], candidate[f'{name}_bad2_each'])}"
            for name in ARM_SCORES
            if f"{name}_bad2_each" in control and f"{name}_bad2_each" in candidate
        ]
        lines += ["", "Pair by pair, the candidate's bad-2 against the control's: " + "; ".join(each) + "."]
    return lines


def pair_by_pair(control: list[float], candidate: list[float]) -> str:
    """How often the candidate's bad-2 (%, per pair, rounded to 0.01) is below the control's on
    the same pairs, and the two-sided sign test's p of that count (`sign_test`): whether a change
    of the mean is carried by the pairs or by one of them."""
    better = sum(b < a for a, b in zip(control, candidate, strict=True))
    worse = sum(b > a for a, b in zip(control, candidate, strict=True))
    return (
        f"better on {better}, worse on {worse}, level on {len(control) - better - worse} of {len(control)} "
        f"(sign test p = {sign_test(better, worse):.2f})"
    )


def sign_test(better: int, worse: int) -> float:
    """The two-sided exact sign test: the chance of a split at least as uneven as `better` against
    `worse` where each pair were as likely to go either way (ties left out); 1 without pairs."""
    pairs = better + worse
    tail: float = sum(math.comb(pairs, k) for k in range(min(better, worse) + 1)) / 2**pairs
    return min(1.0, 2 * tail)


def output_files_report(out: Path) -> list[str]:
    files = sorted(p for p in out.iterdir() if p.is_file())
    verdict = "within" if len(files) <= MAX_FILES and all(p.stat().st_size < MAX_FILE_BYTES for p in files) else "OVER"
    lines = [f"## Output files: {len(files)} ({verdict} the limit of {MAX_FILES} files under 16 MiB each)", ""]
    lines += [f"- {p.name}: {p.stat().st_size / 2**20:.2f} MiB" for p in files]
    return lines
