"""Which device torch computes on (a helper of the runs, train, policy and evaluate stages; no stage).

`--device auto|cpu|cuda` (also `cuda:N`) on `train`, `eval` and `table`: auto is CUDA where torch sees
a GPU, else the CPU. Under torchrun, "cuda" is the rank's own GPU (cuda:LOCAL_RANK). On CUDA the
learner runs under bf16 autocast with TF32 matmuls; on the CPU nothing changes (fp32, or bf16 with
the `bf16` option). The device a run trains on is part of its record, like the torch threads: the
numbers of a CUDA run are not those of a CPU run.
"""

from __future__ import annotations

import os

import torch

from .errors import KgnavbenchError

DEVICES = ("auto", "cpu", "cuda")


class DeviceError(KgnavbenchError, ValueError):
    """An unknown device, or CUDA asked for where torch sees none."""


def resolve(name: str = "auto") -> torch.device:
    """The torch device for `name` (DEVICES, or cuda:N); a DeviceError naming the problem."""
    kind, _, index = str(name).partition(":")
    if kind not in DEVICES or (index and (kind != "cuda" or not index.isdigit())):
        raise DeviceError(f"unknown device {name!r}; choose one of {', '.join(DEVICES)} (or cuda:N)")
    if kind == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        if kind == "auto":
            return torch.device("cpu")
        build = "a CPU-only torch build" if torch.version.cuda is None else "no GPU visible"
        raise DeviceError(f"--device {name}: CUDA is not available here ({build}); use --device cpu or auto")
    if not index:
        index = os.environ.get("LOCAL_RANK", "0")
    if int(index) >= torch.cuda.device_count():
        raise DeviceError(f"--device {name}: there are {torch.cuda.device_count()} CUDA devices")
    torch.backends.cuda.matmul.allow_tf32 = True  # the learner's matmuls: TF32 on CUDA
    torch.backends.cudnn.allow_tf32 = True
    return torch.device("cuda", int(index))


def name_of(device: torch.device) -> str:
    """What a run's record says: "cpu" or "cuda" (the GPU's index is no property of the run)."""
    return device.type
