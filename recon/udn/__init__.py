"""Untrained deep network (UDN, deep image prior) reconstruction: network, runner, jobs.

- :mod:`recon.udn.network`: the encoder-decoder G(z; W) with skips, 2D / frames / 3D.
- :mod:`recon.udn.runner`: :class:`UDNRunner`, the stepwise solver (Adam, held-out early
  stopping, divergence recovery, EMA), with an exact state for resuming.
- :mod:`recon.udn.memory`: the memory estimate and the refusal when a run will not fit.
- :mod:`recon.udn.spec`: TOML job specs and their validation.
- :mod:`recon.udn.jobs`: run folders: checkpoints, previews, loss history, results, run
  records; run, resume, status, cancel.
- :mod:`recon.udn.rundir`: the run folder's lock, verified checkpoints with a fallback, the
  clean-up of interrupted writes, a full disk named.
- :mod:`recon.udn.state`: :class:`~recon.udn.state.JobState` and
  :class:`~recon.udn.state.FinishReason`, the str-Enums of job states.

The network and the runner (the names below) are loaded on first use, so ``import recon.udn``
and the job module (``jobs status``, ``jobs cancel``) do not build them; the job module itself
imports torch (its checkpoints are torch files).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from recon.udn.network import Generator, NetworkConfig
    from recon.udn.runner import UDNConfig, UDNResult, UDNRunner, UDNStep

#: torch.compile modes a run takes (``UDNConfig.compile_mode``; ``reduce-overhead`` records CUDA
#: graphs). Here, without torch, so the command line can list them without importing it.
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune-no-cudagraphs")
#: the most encoder/decoder levels a network may have: more than any axis can halve (2^32
#: pixels); 10^8 looped in the set-up at full CPU, deaf to SIGTERM. Here, without torch, for
#: the command line
MAX_SCALES = 32

_LAZY = {"Generator": "recon.udn.network", "NetworkConfig": "recon.udn.network",
         "UDNConfig": "recon.udn.runner", "UDNResult": "recon.udn.runner",
         "UDNRunner": "recon.udn.runner", "UDNStep": "recon.udn.runner"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "COMPILE_MODES",
    "MAX_SCALES",
    "Generator",
    "NetworkConfig",
    "UDNConfig",
    "UDNResult",
    "UDNRunner",
    "UDNStep",
]
