"""The numerical path of evaluation, pinned so that every x86 CPU computes the same episodes.

ATen picks its CPU kernels by the machine's vector extensions (default / AVX2 / AVX-512) and MKL its BLAS
code path likewise; the float32 results differ in low-order bits, and over a 100-step closed-loop
episode a few of those bits can flip a near-miss into a collision (one episode per few thousand, on the
shipped checkpoints). ``crowdbench eval`` and ``crowdbench leaderboard`` therefore run with ATen's portable
``default`` kernels and MKL's conditional numerical reproducibility (``MKL_CBWR=COMPATIBLE``); both are
read when torch first dispatches a kernel, so :func:`pin` must run before crowdbench imports torch
(``crowdbench.entry``). NumPy dispatches too: its float64 ``sin``/``cos`` (CrowdNav's circle-crossing
placement, ORCA's preferred-velocity perturbation) have AVX-512 (``X86_V4``) kernels whose low-order bits
differ from the AVX2 and baseline ones, which both agree with the C library's; the AVX-512 groups are
disabled (read when numpy is imported, which torch does). The pin overrides the caller's environment: an official number must not depend
on it. Training is not pinned (the portable kernels are slower, and its numbers come from evaluation);
nor is the evaluation at the end of ``crowdbench run`` (results.json records what computed it).
Measured on the shipped checkpoints (docs/benchmarks.md): evaluation takes ~2x longer pinned
(+77% CPU on gatedgcn_td3_s0, +33% on mlp_td3_s0), ATen's share and MKL's; NumPy's is free. None of the
three can go: ATen's vectorised kernels agree with the portable ones on exactly-rounded ops but not on
``sigmoid``, ``softmax``, ``atan2`` or norms, and ATen reads its capability once, for every op; MKL's
native sgemm differs from its COMPATIBLE branch, whose bits the committed numbers are (tests/test_numerics.py).
"""

from __future__ import annotations

import os

# NPY_DISABLE_CPU_FEATURES takes the group names of numpy >= 2.4 (older ones warn and ignore them: pyproject.toml)
PINNED = {"ATEN_CPU_CAPABILITY": "default", "MKL_CBWR": "COMPATIBLE", "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"}


def pin() -> None:
    os.environ.update(PINNED)


def describe() -> dict:
    """What computed an evaluation: torch's version and the kernels it dispatched to."""
    import torch

    return {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "mkl_cbwr": os.environ.get("MKL_CBWR")}
