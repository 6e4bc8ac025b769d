"""The ONNX graphs' clean-up after torch's exporter: onnxscript's optimisation passes, in an order
that keeps its pattern rewriter fast."""

from __future__ import annotations

from typing import Any


def optimize_onnx(model: Any) -> None:
    """Optimise an exported ``onnx_ir.Model`` in place, as torch's exporter does with
    ``optimize=True`` (onnxscript's constant folding, its default rewrite rules, its fusions, the
    removal of unused and duplicated nodes), but with the constants lifted to initializers and
    the repeated nodes merged before each rewrite.

    Torch's own order rewrites first: its pattern matcher then tries every rule at each of the
    thousands of constant and shape nodes that the symbolic height and width leave in the graph,
    once per unrolled iteration. For lite at iterations 2, 4, 6 this took 33 s of an export's
    150 s against 7 s here, and gave the same graph (the same ops, and the same weights file,
    byte for byte, once converted to OpenVINO)."""
    import onnx_ir.passes.common as passes
    import onnxscript.optimizer
    import onnxscript.rewriter
    import onnxscript.rewriter.onnx_fusions

    for _ in range(2):  # as onnxscript's optimize_ir: a second round folds what the first rewrote
        onnxscript.optimizer.fold_constants(model)
        passes.LiftConstantsToInitializersPass(lift_all_constants=True, size_limit=0)(model)
        passes.DeduplicateInitializersPass()(model)
        passes.CommonSubexpressionEliminationPass()(model)
        onnxscript.rewriter.rewrite(model)  # the default rules; removes what they leave unused
    onnxscript.rewriter.onnx_fusions.fuse(model)
